"""Building footprints (GeoJSON polygons) → building IDs of real-world points.

Real pre/post clouds rarely carry a `building_id` dimension; footprints from a cadastre
(e.g. the Dutch BGT) give it. A point gets the ID of the footprint polygon that contains
its x/y (holes respected). Where footprints overlap, the smallest polygon wins: it is the
more specific part (a BGT building part inside a larger outline).
"""
from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ClassifyError, QuakeScanError, read_json_file

log = logging.getLogger(__name__)


class FootprintError(QuakeScanError):
    """A footprint file cannot be read or does not fit the point cloud."""


MAX_ID = 2 ** 63 - 1  # building IDs are int64 everywhere (arrays, the graded LAS's uint64 holds them)


@dataclass
class Footprints:
    ids: np.ndarray  # (k,) int64 > 0, one per polygon
    polygons: list  # shapely Polygon / MultiPolygon, in the file's coordinates
    crs: str | None = None
    source: str = "footprints"
    properties: list = field(default_factory=list)
    id_field: str | None = None  # the property the IDs came from (None: position or building_id)
    # buildings whose footprint cannot be used (NaN vertex, self-intersecting, no area):
    # (building ID, reason, properties); classify reports them as not assessable
    rejected: list = field(default_factory=list)

    def own_ids(self) -> dict:
        """{building ID: the footprint's own ID} where they differ (text IDs numbered 1, 2, …)."""
        if not self.id_field or not self.properties:
            return {}
        out = {}
        pairs = list(zip(self.ids.tolist(), self.properties)) + [(b, p) for b, _, p in self.rejected]
        for b, p in pairs:
            own = (p or {}).get(self.id_field)
            if own != b:
                out[int(b)] = own
        return out

    def attributes(self) -> dict:
        """{building ID: the footprint's properties} of every footprint that has any."""
        pairs = list(zip(self.ids.tolist(), self.properties)) + [(b, p) for b, _, p in self.rejected]
        return {int(b): p for b, p in pairs if p}

    def __len__(self):
        return len(self.ids)

    def bounds(self) -> np.ndarray:
        """(k, 4) minx, miny, maxx, maxy per polygon."""
        import shapely

        return shapely.bounds(np.array(self.polygons, dtype=object))


def parse_geojson_crs(doc: dict) -> str | None:
    """'EPSG:nnnn' from a GeoJSON (2008) `crs` member, None when absent (RFC 7946: WGS 84)."""
    name = (doc.get("crs") or {}).get("properties", {}).get("name")
    if not name:
        return None
    m = re.search(r"EPSG[:/]+(?:[\d.]*[:/]+)?(\d+)$", str(name))
    return f"EPSG:{m.group(1)}" if m else str(name)


def read_footprints(path: str | os.PathLike, id_field: str | None = None) -> Footprints:
    """Read polygons from a GeoJSON FeatureCollection.

    The building ID of a polygon is the integer property `id_field` when given, else the
    property `building_id` when every feature has one, else the feature's position + 1.
    An `id_field` holding text (a GML id such as "b3fe1a…"), or mixing text and numbers,
    cannot be a point cloud's integer ID: the polygons are then numbered 1, 2, … in file
    order and each keeps its own ID, with all its other attributes, in `properties`
    (classify writes them into buildings.geojson and the ID into buildings.csv). Two
    features with the same ID are refused, naming both (merging them into one building
    doubled its points without a word), as is an integer ID beyond 2^63 - 1.

    A footprint that cannot stand for its building's outline (a vertex that is not a finite
    number, a ring that crosses itself like a bow-tie, no area) is not guessed at: the
    building is kept in `rejected` with the reason, and classify reports it as not
    assessable. Rings that only touch themselves (digitising artefacts) are repaired.
    Features that are not polygons (points, lines, no geometry) are not footprints: skipped
    with a warning. Coordinates that cannot be in the file's CRS (|x| > 180 or |y| > 90 in a
    geographic CRS: projected metres labelled as degrees) are refused.
    """
    import shapely
    import shapely.geometry

    path = Path(path)
    doc = read_json_file(path, "footprint file", FootprintError)
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise FootprintError(f"{path}: not a GeoJSON FeatureCollection")
    features = doc.get("features") or []
    if not isinstance(features, list) or not all(isinstance(f, dict) for f in features):
        raise FootprintError(f"{path}: 'features' must be a list of GeoJSON Feature objects")
    entries = []  # (raw ID, polygon or None, reason it is unusable, properties)
    first_with = {}  # raw ID → the feature that has it first
    use_field = id_field or ("building_id" if features and all(
        "building_id" in (f.get("properties") or {}) for f in features) else None)
    for i, f in enumerate(features):
        geom = f.get("geometry")
        if not isinstance(geom, dict) or geom.get("type") not in ("Polygon", "MultiPolygon"):
            log.warning("%s: feature %d is not a polygon (%s), skipped", path, i,
                        geom.get("type") if isinstance(geom, dict) else geom)
            continue
        p = f.get("properties") or {}
        if use_field:
            value = p.get(use_field)
            if value is None or isinstance(value, (bool, dict, list)) or value == "":
                raise FootprintError(f"{path}: feature {i}: property {use_field!r} must be an ID (an integer > 0 "
                                     f"or a text), got {value!r}")
            if isinstance(value, int) and value > MAX_ID:
                raise FootprintError(f"{path}: feature {i}: {use_field!r} {value} is too large for a building ID "
                                     f"(at most 2^63 - 1 = {MAX_ID}); give the footprints smaller IDs, or IDs as "
                                     "text, which are kept as they are")
            key = (type(value) is str, value)  # the text "7" is not the number 7
            if key in first_with:
                raise FootprintError(f"{path}: features {first_with[key]} and {i} have the same {use_field!r} "
                                     f"{value!r}: two footprints would be merged into one building; give each its "
                                     "own ID, or make the parts one MultiPolygon feature")
            first_with[key] = i
            bid = value
        else:
            bid = i + 1
        poly, reason = _polygon(geom, path, i)
        entries.append((bid, poly, reason, p))
    if not any(poly is not None for _, poly, _, _ in entries):
        raise FootprintError(f"{path}: no polygon footprints in the file that can be used"
                             + (f" ({entries[0][2]})" if entries else ""))
    ids = [b for b, _, _, _ in entries]
    if not all(isinstance(b, int) and b > 0 for b in ids):
        log.info("%s: %r holds text IDs; buildings are numbered 1..%d and keep their own ID as %r",
                 path, use_field, len(ids), use_field)
        ids = list(range(1, len(ids) + 1))
    crs = parse_geojson_crs(doc)
    kept = [(b, e[1], e[3]) for b, e in zip(ids, entries) if e[1] is not None]
    fp = Footprints(np.array([b for b, _, _ in kept], dtype=np.int64), [q for _, q, _ in kept], crs, str(path),
                    [p for _, _, p in kept], use_field)
    usable = set(fp.ids.tolist())
    for b, (_, poly, reason, p) in zip(ids, entries):
        if poly is None:
            log.warning("%s: building %s: %s%s", path, b, reason,
                        "; its other parts are used" if b in usable else "; reported as not assessable")
            if b not in usable:
                fp.rejected.append((int(b), f"footprint unusable: {reason}", p))
    if crs:
        from .pointcloud import check_coordinates_fit_crs

        check_coordinates_fit_crs(crs, fp.bounds()[:, :2].min(axis=0), fp.bounds()[:, 2:].max(axis=0), str(path),
                                  FootprintError)
    return fp


def _numbers(c):
    """Every leaf of a GeoJSON coordinate array (without recursion: no depth can overflow it)."""
    stack = [c]
    while stack:
        x = stack.pop()
        if isinstance(x, (list, tuple)):
            stack.extend(reversed(x))
        else:
            yield x


def _polygon(geom: dict, path, i: int):
    """(shapely polygon, "") of a GeoJSON polygon geometry, or (None, why it is unusable)."""
    import shapely
    import shapely.geometry

    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
               for v in _numbers(geom.get("coordinates"))):
        return None, "a vertex is not a finite number (NaN, infinity or text)"
    try:
        poly = shapely.geometry.shape(geom)
    except Exception as e:
        raise FootprintError(f"{path}: feature {i} has an invalid geometry ({e})") from None
    if poly.is_empty:
        return None, "the polygon is empty"
    if poly.envelope.area <= 0 or poly.convex_hull.area <= 0:  # every vertex on one line (or one point)
        return None, "the polygon has no area"
    if not poly.is_valid:
        why = shapely.is_valid_reason(poly)
        if not why.startswith("Ring Self-intersection"):  # a bow-tie: which lobe is the building?
            return None, f"the polygon is invalid ({why}): redraw its outline"
        poly = poly.buffer(0)  # self-touching rings from digitising; buffer(0) repairs them
    if poly.area <= 0:
        return None, "the polygon has no area"
    return poly, ""


def assign_buildings(x: np.ndarray, y: np.ndarray, footprints: Footprints) -> np.ndarray:
    """Building ID per point (0 = outside every footprint), (n,) int64.

    Each polygon tests only the points inside its bounding box (sorted by x, found by
    binary search), with shapely's vectorised point-in-polygon."""
    import shapely

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    out = np.zeros(len(x), np.int64)
    if len(x) == 0:
        return out
    order = np.argsort(x, kind="stable")
    xs = x[order]
    bounds = footprints.bounds()
    areas = np.array([p.area for p in footprints.polygons])
    for k in np.argsort(areas, kind="stable"):  # smallest first: it wins overlaps
        minx, miny, maxx, maxy = bounds[k]
        lo, hi = np.searchsorted(xs, minx, "left"), np.searchsorted(xs, maxx, "right")
        if lo == hi:
            continue
        cand = order[lo:hi]
        cand = cand[(y[cand] >= miny) & (y[cand] <= maxy) & (out[cand] == 0)]
        if len(cand) == 0:
            continue
        inside = shapely.contains_xy(footprints.polygons[k], x[cand], y[cand])
        out[cand[inside]] = footprints.ids[k]
    return out


def no_footprint_contains_a_point(footprints_path, fp: Footprints, points_x) -> ClassifyError:
    """The error of footprints that hold no pre-event point (`points_x`: the epoch's x range)."""
    b = fp.bounds()
    return ClassifyError(f"{footprints_path}: no footprint contains a pre-event point (footprints span "
                         f"x {b[:, 0].min():.1f}..{b[:, 2].max():.1f}, y {b[:, 1].min():.1f}..{b[:, 3].max():.1f}; "
                         f"points x {[round(float(v), 1) for v in points_x]}); wrong CRS?")


def coverage(fp: Footprints | None, pre_ids, post_ids) -> dict:
    """How many footprints hold points of both epochs, of the pre-event or the post-event one
    only, and of neither (`pre_ids`, `post_ids`: the building IDs each epoch's points got);
    empty without footprints."""
    if fp is None:
        return {}
    pre, post = {int(i) for i in pre_ids}, {int(i) for i in post_ids}
    ids = [int(i) for i in fp.ids]
    both = sum(1 for i in ids if i in pre and i in post)
    pre_only = sum(1 for i in ids if i in pre and i not in post)
    post_only = sum(1 for i in ids if i in post and i not in pre)
    return {"footprints": len(ids), "both": both, "pre_only": pre_only, "post_only": post_only,
            "neither": len(ids) - both - pre_only - post_only}


def coverage_words(c: dict) -> str:
    """`coverage` in a sentence."""
    return (f"of {c['footprints']} footprints, {c['both']} hold points of both epochs, {c['pre_only']} of the "
            f"pre-event epoch only (not covered after: not assessable), {c['post_only']} of the post-event epoch "
            f"only, {c['neither']} of neither")


def footprints_without_points(fp: Footprints | None, hit) -> list[int]:
    """The IDs of the footprints no point of either epoch fell in (`hit`: the IDs that got points)."""
    return [] if fp is None else sorted(int(i) for i in fp.ids if int(i) not in hit)


def assign_buildings_reference(x, y, footprints: Footprints) -> np.ndarray:
    """Slow, obvious reference: even-odd ray casting over every ring of every polygon."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    out = np.zeros(len(x), np.int64)
    areas = np.array([p.area for p in footprints.polygons])
    for k in np.argsort(areas, kind="stable"):
        poly = footprints.polygons[k]
        parts = list(poly.geoms) if hasattr(poly, "geoms") else [poly]
        inside = np.zeros(len(x), bool)
        for part in parts:
            rings = [np.asarray(part.exterior.coords)] + [np.asarray(r.coords) for r in part.interiors]
            odd = np.zeros(len(x), bool)
            for ring in rings:
                for (x1, y1), (x2, y2) in zip(ring[:-1], ring[1:]):
                    crosses = (y1 > y) != (y2 > y)
                    with np.errstate(divide="ignore", invalid="ignore"):
                        xc = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
                    odd ^= crosses & (x < xc)
            inside |= odd
        take = inside & (out == 0)
        out[take] = footprints.ids[k]
    return out


def footprints_from_scene(scene, simplify_m: float = 0.02, min_hole_m2: float = 1.0) -> Footprints:
    """Top-view outlines of a scene's buildings, as a cadastre draws them (the Dutch BAG's
    "bovenaanzicht": roof overhangs included), in the scene's world coordinates.

    Simulated clouds carry the simulator's perfect `building_id`; real ones get theirs from
    footprints, where everything inside the polygon that is not ground (a tree crown over the
    roof, a parked car under the eaves) belongs to the building and debris outside it does
    not. Footprints made from the pre-event scene let training and evaluation label simulated
    clouds the same way `classify --footprints` labels real ones.

    A building's outline is the union of the x/y projections of its roof and wall faces
    (interior and debris faces are left out: slabs lie inside the walls, debris is not the
    building's outline); vertical faces project to nothing. Holes smaller than `min_hole_m2`
    (slivers between touching roof triangles) are filled; courtyards stay."""
    import shapely

    from .scene import ROOF, WALL

    tri = np.asarray(scene.vertices)[np.asarray(scene.faces)][:, :, :2]  # (m, 3, 2) local x/y
    cross = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
             - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0]))
    usable = (np.asarray(scene.face_building) > 0) & np.isin(scene.face_surface, (ROOF, WALL)) & (np.abs(cross) > 1e-6)
    ox, oy = float(scene.origin[0]), float(scene.origin[1])
    ids, polygons, props = [], [], []
    for b in scene.buildings:
        sel = usable & (scene.face_building == b.id)
        if not sel.any():
            continue
        rings = np.concatenate([tri[sel], tri[sel][:, :1]], axis=1)  # closed triangles
        outline = shapely.union_all(shapely.polygons(rings)).buffer(0)
        outline = _clean_outline(outline, simplify_m, min_hole_m2)
        if outline.is_empty or outline.area <= 0:
            continue
        ids.append(b.id)
        polygons.append(shapely.transform(outline, lambda c: c + (ox, oy)))
        props.append({"building_id": int(b.id), "typology": b.typology, "storeys": int(b.storeys)})
    if not polygons:
        raise FootprintError("the scene has no building with roof or wall faces: no footprints")
    return Footprints(np.array(ids, dtype=np.int64), polygons, scene.crs, "scene", props)


def _clean_outline(geom, simplify_m: float, min_hole_m2: float):
    """The outline simplified, its small holes filled, and valid: simplifying keeps each part
    valid but not the parts apart (two that met only to within float noise can overlap
    after it), so an invalid result is unioned again."""
    out = _fill_small_holes(geom.simplify(simplify_m), min_hole_m2)
    if not out.is_valid:
        out = _fill_small_holes(out.buffer(0), min_hole_m2)
    return out


def _fill_small_holes(geom, min_hole_m2: float):
    import shapely.geometry

    parts = list(geom.geoms) if hasattr(geom, "geoms") else [geom]
    kept = [shapely.geometry.Polygon(p.exterior, [r for r in p.interiors
                                                 if shapely.geometry.Polygon(r).area >= min_hole_m2])
            for p in parts if p.geom_type == "Polygon"]
    return kept[0] if len(kept) == 1 else shapely.geometry.MultiPolygon(kept)


def write_footprints(footprints: Footprints, path: str | os.PathLike) -> Path:
    """A GeoJSON FeatureCollection that `read_footprints` (and `classify --footprints`) reads
    back with the same IDs; the CRS, when known, as a GeoJSON 2008 `crs` member. Written
    atomically."""
    import shapely.geometry

    path = Path(path)
    features = [{"type": "Feature", "properties": {**(p or {}), "building_id": int(i)},
                 "geometry": shapely.geometry.mapping(poly)}
                for i, poly, p in zip(footprints.ids, footprints.polygons,
                                      footprints.properties or [None] * len(footprints))]
    doc = {"type": "FeatureCollection", "features": features}
    if footprints.crs:
        doc["crs"] = {"type": "name", "properties": {"name": footprints.crs}}
    from ..runtime.atomic import write_text
    from ..runtime.text_safety import json_text

    write_text(path, json_text(doc))  # strict: a NaN attribute is null
    return path
