"""`damage_map.png`: the buildings' outlines coloured by grade, their IDs, a legend, a scale
bar and the CRS; its frame and labels, which the HTML map shares.
"""
from __future__ import annotations

import math

import numpy as np

from ..grades import long_label
from ..runtime.atomic import open_replacing
from .building_result import NOT_ASSESSABLE, in_id_order
from .colours import BACKGROUND_COLOUR, NOT_ASSESSABLE_COLOUR, colour_of

# Buildings graded 0 whose data cannot resolve heavy damage (`quakescan.change.detectability`):
# hatched on both maps, with this legend entry
HEAVY_UNRESOLVED = "no damage seen; heavy damage not resolvable here"
HATCH = "////"  # the PNG map's hatch of those buildings (matplotlib)
HATCH_COLOUR = "#333333"  # the outlines' colour: dark stripes on the green of "no damage"

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
    drawn = [r for r in in_id_order(rows) if int(r.building_id) in outlines]
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
    for r in in_id_order(rows):
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


__all__ = ["HATCH", "HATCH_COLOUR", "HEAVY_UNRESOLVED", "LABEL_ALL_MAX", "MAP_DPI", "MAP_SIZE_IN", "crs_text",
           "import_map_modules", "label_priority", "labelled_ids", "legible_labels", "map_frame", "nice_length",
           "write_map_png"]
