"""The per-building result for responders: CSV, GeoJSON, a PNG map and a graded LAS.

docs/DESIGN.md: "Result — one row per building: building_id, predicted grade, class
probabilities, share of changed points, point counts per epoch, an assessable flag; written
as CSV and as GeoJSON when footprints are known."

A building that cannot be assessed (too few points in an epoch, no point in its footprint)
has no grade: the files leave it empty, never a guess. Every writer goes through
`quakescan.runtime.atomic`, so a file under its final name is always complete.
"""
from __future__ import annotations

import csv
import datetime
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ResultsError, check_input_file
from ..formats.pointcloud import SCALE
from ..grades import grade_name, long_label
from ..grades import GRADE_SHORT_NAMES
from ..runtime.atomic import open_replacing, replacing, write_text

NOT_ASSESSABLE = "not assessable"
# Map / LAS colours (hex RGB). Green → yellow → orange → red with the grade; grades 1 and 2
# (geometrically "no damage" at UAV resolution) get the greens between, should a model predict them.
GRADE_COLOURS = {0: "#1a9641", 1: "#a6d96a", 2: "#d9ef8b", 3: "#ffd700", 4: "#fd8d3c", 5: "#d7191c"}
NOT_ASSESSABLE_COLOUR = "#8c8c8c"  # grey
BACKGROUND_COLOUR = "#d9d9d9"  # light grey: points that belong to no building (map scatter, LAS)
GRADE_NONE = 255  # `predicted_grade` in the LAS: not a building, or not assessable
SOURCE_CHUNK_POINTS = 2_000_000  # points of the source cloud converted at a time for the graded LAS
BUFFER_M = 0.5  # radius around the points of a building too small for a hull
OUTLINE_FOOTPRINT = "footprint"
OUTLINE_HULL = "convex hull of points"
OUTLINE_BUFFER = "buffer around points"  # fewer than 3 distinct points, or all on a line
_FIXED = ["building_id", "assessable", "predicted_grade", "label"]
_TAIL = ["share_changed", "n_pre", "n_post", "decided_by", "reason"]
# Columns added after the first files: written after all others, optional on reading, so
# readers that look columns up by name (quakescan.results.evaluation, read_csv) take old and new files.
_ADDED = ["confidence", "grade_name", "detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved",
          "min_wall_opening_m2"]
# Buildings graded 0 whose data cannot resolve heavy damage (`quakescan.change.detectability`):
# hatched on both maps, with this legend entry
HEAVY_UNRESOLVED = "no damage seen; heavy damage not resolvable here"
HATCH = "////"  # the PNG map's hatch of those buildings (matplotlib)
HATCH_COLOUR = "#333333"  # the outlines' colour: dark stripes on the green of "no damage"


@dataclass
class BuildingResult:
    building_id: int
    n_pre: int
    n_post: int
    assessable: bool
    reason: str = ""  # why not assessable, e.g. "12 pre-event points < 50"
    grade: int | None = None  # None when not assessable: never a guess
    probabilities: dict[int, float] = field(default_factory=dict)  # class grade → p
    share_changed: float | None = None
    decided_by: str = ""  # "model" | "no change" (no changed points → no damage, per the paper) | ""
    # probability of the predicted grade (DamageModel.confidence); 1.0 when decided by rule,
    # None when not assessable
    confidence: float | None = None
    # what the building's data could resolve (quakescan.change.detectability): the lowest
    # grade among 3, 4, 5 (None: none of them, or unknown), the smallest roof opening (m²; None:
    # unknown, e.g. not assessable) and lowering (m; None: unknown)
    detectable_grade: int | None = None
    min_opening_m2: float | None = None
    min_lowering_m: float | None = None
    # whether the walls resolve heavy damage confined to them, and the smallest wall hole they
    # resolve (m²); None: unknown (no facade band, or no facade record)
    walls_resolved: bool | None = None
    min_wall_opening_m2: float | None = None

    @property
    def heavy_unresolved(self) -> bool:
        """Graded 0 on data that cannot resolve heavy damage: "no damage" excludes nothing
        below the lowest grade it resolves (hatched on the maps, counted in the summary)."""
        from ..change.detectability import heavy_unresolved

        ok = self.assessable and self.grade is not None
        return heavy_unresolved(self.grade if ok else None, self.detectable_grade, self.min_opening_m2)

    @property
    def label(self) -> str:
        if not self.assessable or self.grade is None:
            return NOT_ASSESSABLE
        return GRADE_SHORT_NAMES.get(int(self.grade), f"grade {self.grade}")

    @property
    def grade_name(self) -> str:
        """EMS-98 name of the grade ("substantial to heavy"); "not assessable" without one."""
        if not self.assessable or self.grade is None:
            return NOT_ASSESSABLE
        return grade_name(self.grade)

    @property
    def colour(self) -> str:
        return colour_of(self.grade if self.assessable else None)


@dataclass(frozen=True)
class Outline:
    """A building's outline in world coordinates and where it came from."""

    geometry: object  # shapely Polygon / MultiPolygon
    source: str  # OUTLINE_FOOTPRINT | OUTLINE_HULL | OUTLINE_BUFFER


def colour_of(grade: int | None) -> str:
    """Hex colour of a grade; grey for None (not assessable)."""
    if grade is None:
        return NOT_ASSESSABLE_COLOUR
    return GRADE_COLOURS.get(int(grade), NOT_ASSESSABLE_COLOUR)


def _rgb8(hex_colour: str) -> tuple[int, int, int]:
    h = hex_colour.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


def _fmt(v: float | None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return format(float(v), ".6g")


def _sorted(rows) -> list[BuildingResult]:
    return sorted(rows, key=lambda r: int(r.building_id))


# ---------------------------------------------------------------------------------------- CSV

_FLOATS = ("share_changed", "min_opening_m2", "min_lowering_m", "min_wall_opening_m2")  # written with `_fmt`, empty when None


def csv_columns(classes) -> list[str]:
    return _FIXED + [f"p_{int(c)}" for c in classes] + _TAIL + _ADDED


def _record(r: BuildingResult, classes) -> dict:
    """The CSV/GeoJSON fields of a row as Python values (None = empty)."""
    ok = bool(r.assessable) and r.grade is not None
    rec = {"building_id": int(r.building_id), "assessable": ok,
           "predicted_grade": int(r.grade) if ok else None, "label": r.label}
    for c in classes:
        p = r.probabilities.get(int(c)) if ok else None
        rec[f"p_{int(c)}"] = None if p is None else float(p)
    rec.update({"share_changed": None if r.share_changed is None else float(r.share_changed),
                "n_pre": int(r.n_pre), "n_post": int(r.n_post), "decided_by": r.decided_by if ok else "",
                "reason": r.reason or "",
                "confidence": float(r.confidence) if ok and r.confidence is not None else None,
                "grade_name": r.grade_name})
    known = ok and r.min_opening_m2 is not None  # detectability of an assessed building only
    rec.update({"detectable_grade": int(r.detectable_grade) if known and r.detectable_grade is not None else None,
                "min_opening_m2": float(r.min_opening_m2) if known else None,
                "min_lowering_m": float(r.min_lowering_m) if known and r.min_lowering_m is not None else None})
    walls = known and r.walls_resolved is not None
    rec.update({"walls_resolved": (1 if r.walls_resolved else 0) if walls else None,
                "min_wall_opening_m2": float(r.min_wall_opening_m2) if walls and r.min_wall_opening_m2 is not None
                else None})
    return rec


def _json_number(v):
    """JSON has no infinity: an opening no size resolves (an epoch without points over the
    building) is null in the GeoJSON, "inf" in the CSV."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def write_csv(rows, path, classes, own_ids: dict | None = None, raw_text: bool = False) -> None:
    """One line per building, sorted by building_id. Columns: building_id, assessable (1/0),
    predicted_grade (empty when not assessable), label, p_<grade> per model class (empty when
    not assessable), share_changed, n_pre, n_post, decided_by, reason, confidence (probability
    of the predicted grade; empty when not assessable), grade_name (EMS-98 name, quakescan.grades;
    "not assessable" without a grade), detectable_grade (the lowest of 3, 4, 5 the building's
    data resolve; empty when they resolve none, or when min_opening_m2 is empty too: unknown),
    min_opening_m2 and min_lowering_m (the smallest roof opening and lowering they resolve;
    empty when unknown: not assessable, no surface descriptors, or no comparable core point
    for the lowering), walls_resolved (1/0: whether heavy damage confined to the walls could
    show; empty when unknown) and min_wall_opening_m2 (the smallest wall hole resolved). `quakescan.results.evaluation` reads it. `own_ids`
    ({building_id: footprint ID}, for footprints whose IDs are text) adds a last column
    `footprint_id`.

    The footprint IDs are somebody else's text: one that a spreadsheet would run as a
    formula (it begins with = + - @, TAB or CR) is written with a leading single quote
    (`quakescan.runtime.text_safety.spreadsheet_cell`; `read_footprint_ids` takes it off),
    unless `raw_text` (for machine readers). Numbers, ours or a footprint's, are never
    escaped. A field holding a comma, quote, CR or LF is quoted, so no ID splits a row.
    UTF-8 whatever the locale."""
    from ..runtime.text_safety import csv_line, spreadsheet_cell, utf8_text

    classes = [int(c) for c in classes]
    with open_replacing(path, "w", encoding="utf-8", newline="") as f:
        f.write(csv_line(csv_columns(classes) + (["footprint_id"] if own_ids else [])))
        for r in _sorted(rows):
            rec = _record(r, classes)
            line = []
            for col in csv_columns(classes):
                v = rec[col]
                if col == "assessable":
                    line.append("1" if v else "0")
                elif isinstance(v, float) or (col.startswith("p_") and v is None) or col in _FLOATS:
                    line.append(_fmt(v))
                else:
                    line.append("" if v is None else str(v))
            if own_ids:
                own = own_ids.get(int(r.building_id))
                if own is None:
                    line.append("")
                elif isinstance(own, str):
                    line.append(utf8_text(own) if raw_text else spreadsheet_cell(own))
                else:  # a number in the footprint file stays a number
                    line.append(str(own))
            f.write(csv_line(line))


def read_csv_rows(path, error=None, what: str = "file") -> tuple[list, list[dict]]:
    """(column names, rows as dicts) of a CSV table; a missing or unreadable file raises
    `error` (default ResultsError) naming the file as `what` ("result file", "truth file")."""
    error = error or ResultsError
    path = Path(path)
    check_input_file(path, what, error)  # a FIFO would block the read, a device never end it
    try:
        # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte order mark, which is not
        # part of the first column's name
        with open(path, encoding="utf-8-sig", newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            return list(reader.fieldnames or []), rows
    except FileNotFoundError:
        raise error(f"{path}: {what} does not exist") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise error(f"{path}: cannot read as a CSV table ({e})") from None


def read_footprint_ids(path) -> dict:
    """{building_id: footprint ID} of a buildings.csv with a `footprint_id` column (empty
    without one), each ID as the footprint file holds it: the single quote `write_csv` puts
    before a text a spreadsheet would run as a formula is taken off."""
    from ..runtime.text_safety import spreadsheet_raw

    path = Path(path)
    cols, data = read_csv_rows(path, what="result file")
    if "footprint_id" not in cols:
        return {}
    try:
        return {int(d["building_id"]): spreadsheet_raw(d["footprint_id"]) for d in data if d["footprint_id"]}
    except (ValueError, TypeError) as e:
        raise ResultsError(f"{path}: building_id must be an integer ({e})") from None


def read_csv(path) -> list[BuildingResult]:
    """BuildingResults from a CSV that `write_csv` wrote (files without the later columns,
    `_ADDED`, too: those fields stay empty)."""
    path = Path(path)
    cols, data = read_csv_rows(path, what="result file")
    missing = [c for c in _FIXED + _TAIL if c not in cols]
    if missing:
        raise ResultsError(f"{path}: missing columns {missing} (has {cols})")
    pcols = {c: int(c[2:]) for c in cols if re.fullmatch(r"p_\d+", c)}
    out = []
    for i, d in enumerate(data, start=2):
        try:
            ok = d["assessable"].strip() == "1"
            g = d["predicted_grade"].strip()
            probs = {k: float(d[c]) for c, k in pcols.items() if d[c].strip()} if ok else {}
            share = d["share_changed"].strip()
            conf = (d.get("confidence") or "").strip()
            resolved, opening, lowering, walls, wall_opening = (
                (d.get(c) or "").strip() for c in
                ("detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved", "min_wall_opening_m2"))
            out.append(BuildingResult(int(d["building_id"]), int(d["n_pre"]), int(d["n_post"]), ok,
                                      d["reason"], int(g) if ok and g else None, probs,
                                      float(share) if share else None, d["decided_by"],
                                      float(conf) if ok and conf else None,
                                      int(resolved) if ok and resolved else None,
                                      float(opening) if ok and opening else None,
                                      float(lowering) if ok and lowering else None,
                                      (walls == "1") if ok and walls else None,
                                      float(wall_opening) if ok and wall_opening else None))
        except (ValueError, AttributeError) as e:
            raise ResultsError(f"{path}: line {i}: {e}") from None
    return out


# ----------------------------------------------------------------------------------- outlines

# Directions whose extreme points span the octagon `hull_candidates` culls with, in
# counter-clockwise order (the support points of ordered directions are in hull order)
_OCTAGON = np.array([[0, -1], [1, -1], [1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1]], dtype=np.float64)
HULL_TOLERANCE_M = 1e-6  # a point this close to the octagon's edge is kept: rounding never drops a vertex
HULL_CULL_MIN_POINTS = 64  # below this GEOS is as quick as the test


def hull_candidates(xy: np.ndarray) -> np.ndarray:
    """The points of `xy` ((n, 2)) that can be vertices of their convex hull: every point but
    those strictly inside the octagon of its extreme points in eight directions (Akl and
    Toussaint 1978), which lies inside the hull. The hull of the candidates is the hull of
    all the points, with the same vertices: GEOS makes the same polygon from them, from a
    few hundred points where a building has tens of thousands."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < HULL_CULL_MIN_POINTS:
        return xy
    rel = xy - xy[0]  # small numbers for the cross products; the points returned are the given ones
    corners = rel[np.argmax(rel @ _OCTAGON.T, axis=0)]
    keep_corner = np.ones(len(corners), bool)
    keep_corner[1:] = np.any(corners[1:] != corners[:-1], axis=1)
    keep_corner[0] = np.any(corners[0] != corners[-1])
    corners = corners[keep_corner]
    if len(corners) < 3:  # the points lie on a line (or one spot): every one is kept
        return xy
    edges = np.roll(corners, -1, axis=0) - corners
    length = np.hypot(edges[:, 0], edges[:, 1])
    # signed distance of every point to the left of every edge (inside is positive)
    inside = np.ones(len(rel), bool)
    for a, e, n in zip(corners, edges, length):
        inside &= (e[0] * (rel[:, 1] - a[1]) - e[1] * (rel[:, 0] - a[0])) > HULL_TOLERANCE_M * n
    return xy[~inside]


def building_outlines(rows, footprints=None, xy_by_building=None, origin=(0.0, 0.0)
                      ) -> dict[int, Outline]:
    """{building_id: Outline} in world coordinates for the rows that have one.

    The footprint polygon when the footprints know the building (parts with the same ID are
    united); otherwise the convex hull of the building's points, given local in
    `xy_by_building` (anything with `.get(bid)`: a dict) and shifted by `origin[:2]`; a
    building with fewer than 3 distinct points (or all on one line) gets a BUFFER_M buffer
    around them. No footprint and no points: no outline.
    """
    import shapely

    origin = np.asarray(origin, dtype=np.float64)[:2]
    by_fp: dict[int, list] = {}
    if footprints is not None:
        for bid, poly in zip(footprints.ids, footprints.polygons):
            by_fp.setdefault(int(bid), []).append(poly)
    out: dict[int, Outline] = {}
    for r in rows:
        bid = int(r.building_id)
        if bid in by_fp:
            polys = by_fp[bid]
            geom = polys[0] if len(polys) == 1 else shapely.union_all(polys)
            out[bid] = Outline(geom, OUTLINE_FOOTPRINT)
            continue
        xy = None if xy_by_building is None else xy_by_building.get(bid)
        if xy is None or len(xy) == 0:
            continue
        world = np.asarray(xy, dtype=np.float64)[:, :2] + origin
        hull = shapely.convex_hull(shapely.multipoints(hull_candidates(world)))
        if hull.geom_type == "Polygon" and hull.area > 0:
            out[bid] = Outline(hull, OUTLINE_HULL)
        else:  # a point or a line
            out[bid] = Outline(hull.buffer(BUFFER_M), OUTLINE_BUFFER)
    return out


# ------------------------------------------------------------------------------------ GeoJSON

def _round_coords(c):
    if isinstance(c, (list, tuple)) and c and isinstance(c[0], (int, float)):
        return [round(float(v), 3) for v in c]
    return [_round_coords(x) for x in c]


def geojson_crs_member(crs: str | None) -> dict | None:
    """GeoJSON (2008) named CRS for an EPSG code, None when the CRS has no EPSG code."""
    if not crs:
        return None
    m = re.fullmatch(r"\s*EPSG:(\d+)\s*", str(crs), re.IGNORECASE)
    code = m.group(1) if m else None
    if code is None:
        try:
            import pyproj

            code = pyproj.CRS.from_user_input(crs).to_epsg()
        except Exception:
            code = None
    return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}"}} if code else None


def write_geojson(rows, outlines: dict, path, crs: str | None, classes, attributes: dict | None = None) -> None:
    """A FeatureCollection, one Feature per building (sorted by ID) with the CSV's fields as
    properties (JSON types: assessable true/false, empty → null) plus `outline` (where the
    geometry comes from) and `colour` (the map's hex colour). A building without outline has
    geometry null.

    The coordinates are those of the point cloud, i.e. PROJECTED (metres in `crs`), not the
    WGS 84 longitude/latitude that RFC 7946 assumes; hence the GeoJSON 2008 `crs` member
    ("urn:ogc:def:crs:EPSG::n") when the CRS has an EPSG code, which QGIS/GDAL honour and
    `quakescan.formats.footprints.read_footprints` reads back. Coordinates are rounded to 1 mm.
    `attributes` ({building_id: the footprint's properties}) adds them as `footprint`: the
    cadastre's own ID, address or use stay with the result whatever their types (a number
    JSON cannot hold, NaN or infinity, as null).
    """
    import shapely.geometry

    from ..runtime.text_safety import json_text

    classes = [int(c) for c in classes]
    feats = []
    for r in _sorted(rows):
        props = {k: _json_number(v) for k, v in _record(r, classes).items()}
        o = outlines.get(int(r.building_id))
        geom = None
        if o is not None:
            g = shapely.geometry.mapping(o.geometry)
            geom = {"type": g["type"], "coordinates": _round_coords(g["coordinates"])}
        props["outline"] = o.source if o is not None else None
        props["colour"] = r.colour
        if attributes and int(r.building_id) in attributes:
            props["footprint"] = attributes[int(r.building_id)]
        feats.append({"type": "Feature", "id": int(r.building_id), "properties": props, "geometry": geom})
    doc = {"type": "FeatureCollection"}
    member = geojson_crs_member(crs)
    if member:
        doc["crs"] = member
    doc["features"] = feats
    # strict JSON: a footprint attribute NaN or Infinity (Python's reader takes them) is null
    write_text(path, json_text(doc, separators=(",", ":")) + "\n")


# ---------------------------------------------------------------------------------------- map

MAP_SIZE_IN = (10.0, 8.0)
MAP_DPI = 120


def _geometry_path(geom):
    """A matplotlib Path of a (Multi)Polygon, holes included (even-odd via ring orientation)."""
    from matplotlib.path import Path as MPath

    parts = list(geom.geoms) if hasattr(geom, "geoms") else [geom]
    paths = []
    for p in parts:
        if p.geom_type != "Polygon" or p.is_empty:
            continue
        for ring in [p.exterior, *p.interiors]:
            xy = np.asarray(ring.coords)[:, :2]
            codes = np.full(len(xy), MPath.LINETO, dtype=MPath.code_type)
            codes[0], codes[-1] = MPath.MOVETO, MPath.CLOSEPOLY
            paths.append(MPath(xy, codes))
    return MPath.make_compound_path(*paths) if paths else None


# Label every building with its ID up to this many; above, label only those with a grade > 0
# (and those not assessable), which a responder looks for first.
LABEL_ALL_MAX = 40
MAP_MARGIN_SHARE = 0.08  # frame = the outlines' extent plus this share of its larger side...
MAP_MARGIN_MIN_M = 10.0  # ...but at least this many metres


def map_frame(outlines: dict, margin_share: float = MAP_MARGIN_SHARE, margin_min_m: float = MAP_MARGIN_MIN_M):
    """(xmin, ymin, xmax, ymax) the maps show: the buildings' outlines plus a margin; None
    without outlines."""
    bounds = [o.geometry.bounds for o in outlines.values() if o is not None and not o.geometry.is_empty]
    if not bounds:
        return None
    b = np.asarray(bounds, dtype=np.float64)
    x0, y0, x1, y1 = b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()
    m = max(margin_min_m, margin_share * max(x1 - x0, y1 - y0))
    return x0 - m, y0 - m, x1 + m, y1 + m


def nice_length(span: float) -> float:
    """A round scale-bar length (1, 2 or 5 × 10^k m) near a fifth of `span` metres."""
    target = max(float(span), 1e-9) / 5.0
    k = math.floor(math.log10(target))
    for f in (5.0, 2.0, 1.0):
        if f * 10 ** k <= target:
            return f * 10 ** k
    return 10 ** k


def crs_text(crs: str | None) -> str:
    """"CRS: EPSG:32633 (WGS 84 / UTM zone 33N)" for the map; says so when the CRS is unknown."""
    if not crs:
        return "CRS: unknown (coordinates in metres as in the point clouds)"
    text = str(crs).strip()
    try:
        import pyproj

        c = pyproj.CRS.from_user_input(text)
        code = c.to_epsg()
        text = f"EPSG:{code} ({c.name})" if code else c.name
    except Exception:
        text = text if len(text) < 60 else text[:57] + "..."
    return f"CRS: {text}"


def labelled_ids(rows, outlines: dict) -> list[int]:
    """IDs the maps write on the buildings: all when few, else the damaged and not assessable."""
    drawn = [r for r in _sorted(rows) if int(r.building_id) in outlines]
    if len(drawn) <= LABEL_ALL_MAX:
        return [int(r.building_id) for r in drawn]
    return [int(r.building_id) for r in drawn
            if not r.assessable or r.grade is None or int(r.grade) > 0]


# A label's box in units of its font size (in pixels): 0.7 a character and 0.3 for the two
# pads wide, 1.05 and the pads high (the rendered boxes of 1- to 6-digit IDs at 7 pt, 120 dpi:
# 0.685 em a digit, 1.01 em high, plus 0.3 em of pads).
LABEL_CHAR_EM = 0.7
LABEL_PAD_EM = 0.3
LABEL_HEIGHT_EM = 1.05


def label_priority(row) -> tuple:
    """The order the PNG map places IDs in when they cannot all be read: the worst grade
    first, then the buildings not assessable (to be checked on the ground), then the rest;
    by ID among equals."""
    if not row.assessable or row.grade is None:
        return (1, 0, int(row.building_id))
    grade = int(row.grade)
    return (0 if grade > 0 else 2, -grade, int(row.building_id))


def legible_labels(candidates, anchors_px: np.ndarray, size_px: float) -> list:
    """The labels of `candidates` (in priority order; `anchors_px` their centres in display
    pixels) that can be drawn without covering one already placed: a label's box is
    estimated from its text (`LABEL_CHAR_EM` a character). A map of a region has more
    damaged buildings than its pixels can name: 961 labels on the 2 x 75 M pair's map, most
    of them over each other, took 1.35 s of the 1.6 s it took to draw."""
    anchors = np.asarray(anchors_px, dtype=np.float64).reshape(-1, 2)
    half_h = (LABEL_HEIGHT_EM + LABEL_PAD_EM) * size_px / 2.0
    half_w = [(LABEL_CHAR_EM * len(str(c)) + LABEL_PAD_EM) * size_px / 2.0 for c in candidates]
    cell = 2.0 * max([half_h, *half_w])  # a box overlaps only boxes in its own or the next cells
    placed: dict = {}
    kept = []
    for c, (x, y), hw in zip(candidates, anchors.tolist(), half_w):
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        i, j = int(math.floor(x / cell)), int(math.floor(y / cell))
        clash = any(abs(x - u) < hw + hu and abs(y - v) < half_h * 2.0
                    for di in (-1, 0, 1) for dj in (-1, 0, 1) for u, v, hu in placed.get((i + di, j + dj), ()))
        if not clash:
            placed.setdefault((i, j), []).append((x, y, hw))
            kept.append(c)
    return kept


def import_map_modules() -> None:
    """Import what `_draw_map` draws with (matplotlib: 0.6 s of the 2 x 75 M pair's results
    stage), for a caller with idle time before the results, such as a client whose workers
    are still streaming."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.collections  # noqa: F401
    import matplotlib.figure  # noqa: F401
    import matplotlib.patches  # noqa: F401
    import mpl_toolkits.axes_grid1.anchored_artists  # noqa: F401


def _draw_map(rows, outlines: dict, title: str, points_xy=None, crs: str | None = None):
    """(figure, axes) of the damage map; `write_map_png` saves it (kept apart for tests)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PathCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from ..runtime.text_safety import utf8_text

    fig = Figure(figsize=MAP_SIZE_IN, dpi=MAP_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    frame = map_frame(outlines)
    if points_xy is not None and len(points_xy):
        pts = np.asarray(points_xy, dtype=np.float64)
        if frame is not None:  # only what the frame shows: a smaller file, same picture
            x0, y0, x1, y1 = frame
            pts = pts[(pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)]
        ax.scatter(pts[:, 0], pts[:, 1], s=2.0, c=BACKGROUND_COLOUR, marker=".", linewidths=0,
                   rasterized=True, zorder=1)
    paths, colours, unresolved = [], [], []
    counts: dict = {}
    for r in _sorted(rows):
        key = int(r.grade) if r.assessable and r.grade is not None else None
        counts[key] = counts.get(key, 0) + 1
        o = outlines.get(int(r.building_id))
        p = None if o is None else _geometry_path(o.geometry)
        if p is not None:
            paths.append(p)
            colours.append(colour_of(key))
            if r.heavy_unresolved:
                unresolved.append(p)
    if paths:
        ax.add_collection(PathCollection(paths, facecolors=colours, edgecolors="#333333", linewidths=0.4,
                                         zorder=2))
    if unresolved:  # over their green fill: hatching is one setting of a whole collection
        hatched = PathCollection(unresolved, facecolors="none", edgecolors=HATCH_COLOUR, linewidths=0.0,
                                 hatch=HATCH, zorder=2.1)
        hatched.set_gid("heavy-unresolved")
        ax.add_collection(hatched)
    if frame is not None:
        ax.set_xlim(frame[0], frame[2])
        ax.set_ylim(frame[1], frame[3])
    else:
        ax.autoscale_view()
    # the frame stays as asked; the axes box takes its shape
    ax.set_aspect("equal", adjustable="box")
    fig.subplots_adjust(left=0.1, right=0.66, bottom=0.08, top=0.93)
    by_id = {int(r.building_id): r for r in rows}
    labels = sorted(labelled_ids(rows, outlines), key=lambda b: label_priority(by_id[b]))
    size = 7 if len(labels) <= LABEL_ALL_MAX else 5
    at = [outlines[bid].geometry.representative_point() for bid in labels]
    ax.apply_aspect()  # the axes' final box: where each label lands in pixels
    anchors = ax.transData.transform(np.array([[p.x, p.y] for p in at]).reshape(-1, 2))
    keep = set(legible_labels(labels, anchors, size * MAP_DPI / 72.0))
    for bid, p in zip(labels, at):
        if bid in keep:
            ax.text(p.x, p.y, str(bid), ha="center", va="center", fontsize=size, zorder=3, gid="building-id",
                    bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.7})
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.set_title(utf8_text(title), parse_math=False)  # a file name's "$" is text, not mathtext
    x0, x1 = ax.get_xlim()
    length = nice_length(x1 - x0)
    bar = AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower right", pad=0.5, sep=4,
                          borderpad=0.6, frameon=True, size_vertical=0, color="black", fontproperties={"size": 8})
    bar.set_gid("scale-bar")
    ax.add_artist(bar)
    ax.text(0.01, 0.01, utf8_text(crs_text(crs)), transform=ax.transAxes, fontsize=7, ha="left", va="bottom",
            zorder=4, gid="crs", parse_math=False, bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": "#999999",
                             "alpha": 0.85})
    shown = [0, 3, 4, 5] + sorted(k for k in counts if k is not None and k not in (0, 3, 4, 5))
    handles = [Patch(facecolor=colour_of(g), edgecolor="#333333", label=f"{long_label(g)}: {counts.get(g, 0)}")
               for g in shown]
    n_unresolved = sum(1 for r in rows if r.heavy_unresolved)
    if n_unresolved:  # right under "0 no damage", which these buildings are counted in too
        handles.insert(1, Patch(facecolor=colour_of(0), edgecolor=HATCH_COLOUR, hatch=HATCH, linewidth=0.0,
                                label=HEAVY_UNRESOLVED.replace("; ", ";\n") + f": {n_unresolved}"))  # fits the margin
    if counts.get(None):
        handles.append(Patch(facecolor=NOT_ASSESSABLE_COLOUR, edgecolor="#333333",
                             label=f"{NOT_ASSESSABLE}: {counts[None]}"))
    ax.legend(handles=handles, title=f"EMS-98 grade: {sum(counts.values())} buildings", loc="upper left",
              bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize="small")
    return fig, ax


def write_map_png(rows, outlines: dict, path, title: str, points_xy=None, crs: str | None = None) -> None:
    """A PNG map framed on the buildings (their outlines plus a margin, `map_frame`):
    outlines filled by grade colour (green / yellow / orange / red; grey = not assessable),
    hatched where a building graded 0 cannot resolve heavy damage (`HEAVY_UNRESOLVED`),
    building IDs on them (all when few, else the damaged and not assessable: `labelled_ids`;
    as many as can be read, the worst grade first: `legible_labels`),
    a legend with the EMS-98 name and count per class, a scale bar, the CRS, equal aspect,
    axes in metres of the CRS, `points_xy` (world x/y, subsample them) as a light-grey
    scatter underneath. Drawn with the Agg canvas directly: no display, no pyplot state."""
    fig, _ = _draw_map(rows, outlines, title, points_xy, crs)
    with open_replacing(path, "wb") as f:
        fig.savefig(f, format="png", dpi=MAP_DPI)


# ---------------------------------------------------------------------------------------- LAS

def write_grade_las(path, epoch_xyz, origin, crs: str | None, building_id,
                    grade_by_building: dict, source=None) -> None:
    """A LAS 1.4 (point format 7: RGB) of the given points for viewing, e.g. in CloudCompare.

    Extra dimensions `building_id` (uint32, or uint64 when an ID needs it: a national
    register's 15-digit IDs must not wrap) and `predicted_grade` (uint8; 255 = not a building
    or not assessable); RGB as on the map (16-bit = 8-bit × 257): the grade's colour, grey
    for a building not assessed, light grey for points of no building. `epoch_xyz` is float64
    relative to `origin`; stored with scale 0.001 and offset = origin, CRS as WKT when known.
    `source`: the LAS/LAZ file these points were read from, in the same order: every one of
    its attributes (classification, intensity, returns, GPS time, scan angle, point source,
    its extra dimensions) is kept, converted to format 7 as laspy converts formats. `.laz`
    output is compressed."""
    path = _grade_las_path(path)
    xyz = np.asarray(epoch_xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    ids = np.zeros(n, np.int64) if building_id is None else np.asarray(building_id, dtype=np.int64)
    if len(ids) != n:
        raise ResultsError(f"{path}: {len(ids)} building IDs for {n} points")
    max_id = int(ids.max()) if n else 0
    if source is None:
        header = grade_header(path, origin, crs, max_id, None)
        _write_grade_chunks(path, header, origin, grade_by_building, [(xyz, ids, None)])
        return
    import laspy

    # the source streamed a chunk at a time beside the epoch's arrays: a whole copy of a large
    # cloud in both point formats would double the peak of a classification
    with laspy.open(source) as reader:
        if reader.header.point_count != n:
            raise ResultsError(f"{path}: the source {source} has {reader.header.point_count} points, the epoch {n}")
        header = grade_header(path, origin, crs, max_id, source_extra_dims(reader.header))

        def chunks():
            start = 0
            for raw, kept in source_chunks_format7(reader, SOURCE_CHUNK_POINTS):
                stop = start + len(raw)
                yield xyz[start:stop], ids[start:stop], kept
                start = stop

        _write_grade_chunks(path, header, origin, grade_by_building, chunks())


def write_grade_las_streamed(path, chunks, origin, crs: str | None, grade_by_building: dict, *, max_id: int,
                             source_extra_dims: list | None = None) -> None:
    """`write_grade_las` of a cloud that arrives in chunks: (xyz local, building IDs, the
    source's points of the chunk converted to point format 7 or None) each; `max_id` sets the
    ID type; `source_extra_dims` [(name, dtype)] the source's extra dimensions to keep."""
    path = _grade_las_path(path)
    header = grade_header(path, origin, crs, max_id, source_extra_dims)
    _write_grade_chunks(path, header, origin, grade_by_building, chunks)


def source_chunks_format7(reader, chunk_points: int, start: int = 0, stop: int | None = None):
    """The points of an open laspy reader chunk by chunk (points start..stop, all by
    default), converted to point format 7 as `write_grade_las` converts its source (whole
    degrees of a legacy scan angle kept)."""
    import laspy

    from ..formats.pointcloud import read_point_range

    stop = reader.header.point_count if stop is None else stop
    for chunk in read_point_range(reader, start, stop, chunk_points):
        yield chunk, _format7(laspy.LasData(header=reader.header, points=chunk.copy()))


def source_extra_dims(header) -> list:
    """[(name, dtype)] of a source file's extra dimensions, which its graded cloud keeps."""
    return [(name, header.point_format.dimension_by_name(name).dtype)
            for name in header.point_format.extra_dimension_names]


def _grade_las_path(path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise ResultsError(f"{path}: output must end in .las or .laz")
    return path


def grade_header(path: Path, origin, crs, max_id: int, extra):
    """The LAS 1.4 header of a graded cloud (point format 7, the source's extra dimensions
    `extra` [(name, dtype)], building_id of a type that holds `max_id`, predicted_grade)."""
    import laspy

    id_type = np.uint32 if max_id <= np.iinfo(np.uint32).max else np.uint64
    header = laspy.LasHeader(point_format=7, version="1.4")
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=dtype) for name, dtype in extra
                               if name not in ("building_id", "predicted_grade")])
    header.add_extra_dims([
        laspy.ExtraBytesParams(name="building_id", type=id_type, description="building ID, 0 = none"),
        laspy.ExtraBytesParams(name="predicted_grade", type=np.uint8, description="EMS-98 grade, 255 = n.a.")])
    header.offsets = np.asarray(origin, dtype=np.float64)[:3]
    header.scales = np.array([SCALE] * 3)
    header.creation_date = datetime.date.today()
    header.generating_software = "QuakeScan"
    if crs:
        try:
            import pyproj

            header.add_crs(pyproj.CRS.from_user_input(crs))
        except Exception as e:
            raise ResultsError(f"{path}: cannot write CRS {crs!r} to LAS: {e}") from None
    return header


def _write_grade_chunks(path: Path, header, origin, grade_by_building: dict, chunks) -> None:
    records = (grade_records(path, header, origin, grade_by_building, xyz, ids, kept) for xyz, ids, kept in chunks)
    write_grade_records(path, header, origin, records)


def write_grade_records(path, header, origin, records) -> None:
    """A graded LAS/LAZ (`path`, written atomically) of `header` (`grade_header`) and its point
    records, arriving in chunks (laspy point records of the header's format, or None)."""
    import laspy

    path = Path(path)
    origin = np.asarray(origin, dtype=np.float64)[:3]
    compress = path.suffix.lower() == ".laz"
    written = 0
    with replacing(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compress) as w:
            for points in records:
                if points is None or not len(points):
                    continue
                w.write_points(points)
                written += len(points)
            if not written:  # laspy leaves an empty file's bounds at ±inf
                w.header.mins = origin
                w.header.maxs = origin


def grade_records(path, header, origin, grade_by_building: dict, xyz, ids, kept):
    """The point records (laspy, `header`'s format) of one chunk of a graded cloud: `xyz` local
    to `origin`, building IDs, the source's points in format 7 or None; None when empty.
    `path` names the output in errors."""
    import laspy

    n = len(xyz)
    if not n:
        return None
    lim = np.iinfo(np.int32)
    id_type = header.point_format.dimension_by_name("building_id").dtype
    g, rgb = _grade_colours(ids, grade_by_building)
    ints = np.rint(xyz / SCALE)
    if ints.min() < lim.min or ints.max() > lim.max:
        raise ResultsError(f"{path}: coordinates lie more than 2 147 km from the offset "
                           f"{np.asarray(origin, dtype=np.float64)[:3].tolist()}")
    points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    a = points.array
    if kept is not None:  # every attribute of the input first; coordinates, colours and ours below
        for name in kept.array.dtype.names:
            if name in a.dtype.names and name not in ("X", "Y", "Z", "building_id", "predicted_grade"):
                a[name] = kept.array[name]
    else:
        a["bit_fields"] = 1 | (1 << 4)  # return 1 of 1
    a["X"], a["Y"], a["Z"] = ints[:, 0], ints[:, 1], ints[:, 2]
    a["red"], a["green"], a["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    a["building_id"] = np.maximum(ids, 0).astype(id_type)
    a["predicted_grade"] = g
    return points


def _grade_colours(ids: np.ndarray, grade_by_building: dict):
    """Grade (uint8) and 16-bit RGB per point through a lookup over the unique IDs."""
    uniq, inv = np.unique(ids, return_inverse=True)
    g_u = np.full(len(uniq), GRADE_NONE, np.uint8)
    rgb_u = np.tile(np.array(_rgb8(BACKGROUND_COLOUR), np.uint16), (len(uniq), 1))
    for k, b in enumerate(uniq):
        b = int(b)
        if b <= 0 or b not in grade_by_building:
            continue
        g = grade_by_building[b]
        if g is not None:
            g_u[k] = int(g)
        rgb_u[k] = _rgb8(colour_of(g))
    rgb_u = rgb_u * 257
    return g_u[inv], rgb_u[inv]


def _format7(src):
    """The points of a LasData in point format 7."""
    import laspy

    if src.point_format.id != 7:
        legacy = "scan_angle_rank" in src.point_format.dimension_names
        rank = np.asarray(src.scan_angle_rank, dtype=np.float64) if legacy else None
        src = laspy.convert(src, point_format_id=7, file_version="1.4")
        if legacy:  # laspy copies fields by name: whole degrees become 0.006° steps (LAS 1.4)
            src.points.array["scan_angle"] = np.rint(rank / 0.006).astype(np.int16)
    return src.points


__all__ = ["BACKGROUND_COLOUR", "BuildingResult", "GRADE_COLOURS", "GRADE_NONE", "HEAVY_UNRESOLVED",
           "NOT_ASSESSABLE", "NOT_ASSESSABLE_COLOUR", "Outline", "ResultsError", "building_outlines", "colour_of",
           "read_csv", "read_footprint_ids", "write_csv", "write_geojson", "write_grade_las",
           "write_grade_las_streamed", "write_map_png"]
