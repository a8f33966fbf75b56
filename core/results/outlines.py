"""Each building's outline for the maps and the GeoJSON: its footprint, else the convex hull
of its points, else a buffer around them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BUFFER_M = 0.5  # radius around the points of a building too small for a hull
OUTLINE_FOOTPRINT = "footprint"
OUTLINE_HULL = "convex hull of points"
OUTLINE_BUFFER = "buffer around points"  # fewer than 3 distinct points, or all on a line


@dataclass(frozen=True)
class Outline:
    """A building's outline in world coordinates and where it came from."""

    geometry: object  # shapely Polygon / MultiPolygon
    source: str  # OUTLINE_FOOTPRINT | OUTLINE_HULL | OUTLINE_BUFFER


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


__all__ = ["BUFFER_M", "OUTLINE_BUFFER", "OUTLINE_FOOTPRINT", "OUTLINE_HULL", "Outline", "building_outlines",
           "hull_candidates"]
