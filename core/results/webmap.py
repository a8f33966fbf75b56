"""The offline HTML damage map (`damage_map.html`): one file a responder opens in any browser.

Leaflet (core/web/, BSD-2-Clause, from its npm package) and the buildings are inlined, so
the file works without internet and without the files beside it. There are no offline map
tiles, so the map uses Leaflet's `L.CRS.Simple` (1 unit = 1 m) with the projected
coordinates shifted to a local origin (the frame's lower-left corner, rounded to the
metre); the popups give the real coordinates and the CRS. Colours and names are those of
the PNG map and the CSV (`quakescan.results.colours.colour_of`, `quakescan.grades`).
"""
from __future__ import annotations

import math
from pathlib import Path

from ..grades import grade_name, long_label, short_name
from ..runtime.atomic import write_text
from ..runtime.text_safety import html_text, js_safe_id, script_json
from .building_result import NOT_ASSESSABLE, in_id_order
from .colours import NOT_ASSESSABLE_COLOUR, colour_of
from .png_map import HATCH_COLOUR, HEAVY_UNRESOLVED, crs_text, labelled_ids, map_frame

WEB = Path(__file__).resolve().parents[1] / "web"
LEAFLET_VERSION = "1.9.4"


def _vendored(name: str) -> str:
    text = (WEB / name).read_text(encoding="utf-8")
    # the source map is not shipped: a browser's developer tools would ask for it
    return "\n".join(line for line in text.splitlines() if not line.startswith("//# sourceMappingURL="))


def _shifted(coords, dx: float, dy: float):
    if isinstance(coords, (list, tuple)) and coords and isinstance(coords[0], (int, float)):
        return [round(float(coords[0]) - dx, 3), round(float(coords[1]) - dy, 3)]
    return [_shifted(c, dx, dy) for c in coords]


def _popup(r, classes, centre, own_id) -> str:
    """The popup's HTML table for one building."""
    def row(k, v):
        return f"<tr><th>{html_text(k)}</th><td>{html_text(v)}</td></tr>"

    ok = bool(r.assessable) and r.grade is not None
    lines = [row("building ID", int(r.building_id))]
    if own_id is not None:
        lines.append(row("footprint ID", own_id))
    lines.append(row("grade", long_label(r.grade) if ok else NOT_ASSESSABLE))
    if ok:
        probs = ", ".join(f"{int(c)}: {100 * r.probabilities.get(int(c), 0.0):.0f} %" for c in classes)
        lines.append(row("class probabilities", probs))
        if r.confidence is not None:
            lines.append(row("confidence", f"{100 * r.confidence:.0f} %"))
        if r.decided_by:
            lines.append(row("decided by", r.decided_by))
        if r.share_changed is not None:
            lines.append(row("share changed", f"{100 * r.share_changed:.1f} %"))
        lines += _detectability_rows(r, row)
    lines.append(row("points pre / post", f"{int(r.n_pre)} / {int(r.n_post)}"))
    if r.reason:
        lines.append(row("not assessable because", r.reason))
    if centre is not None:
        lines.append(row("centre (E, N)", f"{centre[0]:.1f}, {centre[1]:.1f}"))
    return "<table class='qs-popup'>" + "".join(lines) + "</table>"


def _detectability_rows(r, row) -> list[str]:
    """What the building's data could resolve (quakescan.change.detectability), as popup rows."""
    if r.min_opening_m2 is None:
        return []
    lowest = long_label(r.detectable_grade) if r.detectable_grade is not None else "none of grades 3-5"
    opening = f"{r.min_opening_m2:.1f} m²" if math.isfinite(r.min_opening_m2) else "none (an epoch has no points)"
    out = [row("lowest grade resolvable", lowest), row("smallest opening resolvable", opening)]
    if r.min_lowering_m is not None:
        out.append(row("smallest lowering resolvable", f"{r.min_lowering_m:.2f} m"))
    if r.walls_resolved is not None:
        out.append(row("heavy damage in walls alone", "resolvable" if r.walls_resolved else
                       "not resolvable (too few returns on the walls)"))
    if r.heavy_unresolved:
        out.append(row("note", HEAVY_UNRESOLVED))
    return out


def map_features(rows, outlines: dict, classes, origin_xy, own_ids: dict | None = None) -> list[dict]:
    """GeoJSON features (local coordinates: world minus `origin_xy`) of the buildings that
    have an outline, with what the page shows."""
    import shapely.geometry

    labels = set(labelled_ids(rows, outlines))
    feats = []
    for r in in_id_order(rows):
        bid = int(r.building_id)
        o = outlines.get(bid)
        if o is None or o.geometry.is_empty:
            continue
        g = shapely.geometry.mapping(o.geometry)
        ok = bool(r.assessable) and r.grade is not None
        at = o.geometry.representative_point()
        feats.append({"type": "Feature", "id": js_safe_id(bid),  # beyond 2^53 as text: a double rounds it
                      "geometry": {"type": g["type"], "coordinates": _shifted(g["coordinates"], *origin_xy)},
                      "properties": {"id": js_safe_id(bid), "grade": int(r.grade) if ok else None,
                                     "name": grade_name(r.grade) if ok else NOT_ASSESSABLE,
                                     "colour": colour_of(r.grade if ok else None),
                                     "hatched": r.heavy_unresolved,
                                     "label": bid in labels,
                                     "popup": _popup(r, classes, (at.x, at.y),
                                                     None if not own_ids else own_ids.get(bid))}})
    return feats


def legend_entries(rows) -> list[dict]:
    counts: dict = {}
    for r in rows:
        key = int(r.grade) if r.assessable and r.grade is not None else None
        counts[key] = counts.get(key, 0) + 1
    grades = [0, 3, 4, 5] + sorted(k for k in counts if k is not None and k not in (0, 3, 4, 5))
    out = [{"colour": colour_of(g), "text": long_label(g), "short": short_name(g), "count": counts.get(g, 0)}
           for g in grades]
    if counts.get(None):
        out.append({"colour": NOT_ASSESSABLE_COLOUR, "text": NOT_ASSESSABLE, "short": NOT_ASSESSABLE,
                    "count": counts[None]})
    unresolved = sum(1 for r in rows if r.heavy_unresolved)
    if unresolved:  # right under "0 no damage", which these buildings are counted in too
        out.insert(1, {"colour": colour_of(0), "text": HEAVY_UNRESOLVED, "short": HEAVY_UNRESOLVED,
                       "count": unresolved, "hatched": True})
    return out


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="QuakeScan">
<title>{title}</title>
<!-- Leaflet {leaflet_version}, (c) 2010-2023 Volodymyr Agafonkin, (c) 2010-2011 CloudMade, BSD-2-Clause:
     the licence is in core/web/LEAFLET_LICENSE of QuakeScan and at the end of this file -->
<style>
{leaflet_css}
</style>
<style>
html, body {{ height: 100%; margin: 0; font: 13px/1.35 sans-serif; }}
#map {{ position: absolute; top: 0; bottom: 0; left: 0; right: 0; background: #f4f4f4; }}
.qs-box {{ background: rgba(255,255,255,0.92); padding: 6px 9px; border-radius: 4px;
          box-shadow: 0 1px 4px rgba(0,0,0,0.3); }}
.qs-box h4 {{ margin: 0 0 4px; font-size: 13px; }}
.qs-legend i {{ display: inline-block; width: 14px; height: 14px; margin-right: 6px; vertical-align: -2px;
               border: 1px solid #333; }}
.qs-id {{ background: rgba(255,255,255,0.75); border: none; box-shadow: none; padding: 0 2px;
         font-size: 11px; }}
.qs-popup th {{ text-align: left; padding-right: 8px; font-weight: 600; vertical-align: top; }}
.qs-legend i.qs-hatch {{ background: {hatch_css}; }}
</style>
</head>
<body>
<!-- the fill of buildings graded 0 whose data cannot resolve heavy damage (Leaflet draws SVG) -->
<svg width="0" height="0" style="position: absolute" aria-hidden="true"><defs>
<pattern id="qs-hatch" patternUnits="userSpaceOnUse" width="8" height="8" patternTransform="rotate(45)">
<rect width="8" height="8" fill="{no_damage}"></rect><rect width="3" height="8" fill="{hatch}"></rect>
</pattern></defs></svg>
<div id="map" data-expected-features="{n_features}"></div>
<script>
{leaflet_js}
</script>
<script>
(function () {{
  var data = {data};
  var map = L.map("map", {{crs: L.CRS.Simple, minZoom: -6, maxZoom: 6, zoomSnap: 0.25, attributionControl: false}});
  var layer = L.geoJSON(data.features, {{
    style: function (f) {{
      var p = f.properties;
      return {{color: "#333333", weight: 1, fillColor: p.hatched ? "url(#qs-hatch)" : p.colour, fillOpacity: 0.9,
               className: p.hatched ? "qs-building qs-heavy-unresolved" : "qs-building"}};
    }},
    onEachFeature: function (f, l) {{
      l.bindPopup(f.properties.popup, {{maxWidth: 420}});
      if (f.properties.label) {{
        l.bindTooltip(String(f.properties.id), {{permanent: true, direction: "center", className: "qs-id"}});
      }} else {{
        l.bindTooltip("building " + f.properties.id + ": " + f.properties.name);
      }}
    }}
  }}).addTo(map);
  var f = data.frame;
  map.fitBounds([[f[1], f[0]], [f[3], f[2]]]);
  L.control.scale({{metric: true, imperial: false, maxWidth: 160}}).addTo(map);
  var legend = L.control({{position: "topright"}});
  legend.onAdd = function () {{
    var d = L.DomUtil.create("div", "qs-box qs-legend");
    var h = "<h4>EMS-98 grade (" + data.buildings + " buildings)</h4>";
    data.legend.forEach(function (e) {{
      h += "<div><i" + (e.hatched ? " class='qs-hatch'" : " style='background:" + e.colour + "'") + "></i>"
        + e.text + ": " + e.count + "</div>";
    }});
    d.innerHTML = h;
    return d;
  }};
  legend.addTo(map);
  var info = L.control({{position: "bottomright"}});
  info.onAdd = function () {{
    var d = L.DomUtil.create("div", "qs-box");
    d.textContent = data.crs + "; map coordinates are metres from E " + data.origin[0] + ", N " + data.origin[1];
    return d;
  }};
  info.addTo(map);
  var title = L.control({{position: "topleft"}});
  title.onAdd = function () {{
    var d = L.DomUtil.create("div", "qs-box");
    d.innerHTML = "<h4></h4>";
    d.firstChild.textContent = data.title;
    return d;
  }};
  title.addTo(map);
  // what the tests (and anyone checking the page) read: the buildings actually drawn
  var drawn = 0;
  layer.eachLayer(function (l) {{ if (map.hasLayer(l) && l._path) {{ drawn += 1; }} }});
  document.getElementById("map").setAttribute("data-rendered-features", String(drawn));
}})();
</script>
<!--
{leaflet_license}
-->
</body>
</html>
"""


def write_map_html(rows, outlines: dict, path, title: str, crs: str | None, classes,
                   own_ids: dict | None = None) -> None:
    """A self-contained HTML map: building outlines coloured by grade (the PNG's colours),
    striped (an SVG pattern) where a building graded 0 cannot resolve heavy damage,
    a popup per building (ID, grade with its EMS-98 name, class probabilities, confidence,
    what its data could resolve, point counts, the reason when not assessable), permanent ID labels as on the PNG, a
    legend with counts, a scale bar and the CRS. Buildings without outline are counted in
    the legend but not drawn."""
    classes = [int(c) for c in classes]
    frame = map_frame(outlines) or (0.0, 0.0, 100.0, 100.0)
    origin = (float(math.floor(frame[0])), float(math.floor(frame[1])))
    feats = map_features(rows, outlines, classes, origin, own_ids)
    data = {"title": title, "crs": crs_text(crs), "origin": [origin[0], origin[1]],
            "frame": [round(frame[0] - origin[0], 3), round(frame[1] - origin[1], 3),
                      round(frame[2] - origin[0], 3), round(frame[3] - origin[1], 3)],
            "buildings": len(rows), "legend": legend_entries(rows), "features": feats}
    # every text from the inputs (file names in the title, CRS names, footprint IDs in the
    # popups) goes through quakescan.runtime.text_safety: `html_text` in the markup,
    # `script_json` in the script, where no "</script>" or "<!--<script>" can end it early or late
    page = _PAGE.format(title=html_text(title), leaflet_version=LEAFLET_VERSION,
                        leaflet_css=_vendored("leaflet.css"), leaflet_js=_vendored("leaflet.js"),
                        data=script_json(data, separators=(",", ":")),
                        n_features=len(feats), no_damage=colour_of(0), hatch=HATCH_COLOUR,
                        hatch_css=f"repeating-linear-gradient(45deg, {HATCH_COLOUR} 0 2px, {colour_of(0)} 2px 6px)",
                        leaflet_license=_vendored("LEAFLET_LICENSE").replace("--", "- -"))
    write_text(path, page)


__all__ = ["LEAFLET_VERSION", "legend_entries", "map_features", "write_map_html"]
