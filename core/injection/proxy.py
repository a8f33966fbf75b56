"""A proxy model of each real building: the shape the add-on's damage patterns act on.

Damage is injected into a real cloud by damaging a model of its buildings and re-casting the
cloud's own pulses against it (`quakescan.injection.recast`). The model needs the building's
outline, its ground and its roof height: the footprint is extruded from the ground its
points give to the height of its roof, as an LoD1 block. The add-on's bundle import
(`addon/io_import.py`, `prepare_for_damage`) gives such a shell floors and inner walls, so
an opening shows a storey below it, as it does in the training set's cities.

Where the proxy is wrong (a pitched roof modelled flat, an eave the footprint does not
hold), nothing of it reaches the output by itself: a real point is replaced only where the
damaged proxy differs from the undamaged one along that point's pulse. The error moves where
the new surfaces lie, not whether an undamaged surface keeps its real points.

Heights: ground = 10th percentile of the ground points (ASPRS 2) within `GROUND_SEARCH_M` of
the footprint (within `GROUND_FALLBACK_M` where none is that near), as
`quakescan.change.surface` measures it (2nd percentile of all points there without a ground
class); roof = the median over the footprint's 1 m cells of each cell's
highest point, so a chimney or a tree over one corner does not lift the block.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import QuakeScanError
from ..formats.scene import GROUND, ROOF, WALL, Building, Scene

GROUND_CLASS = 2
GROUND_SEARCH_M = 10.0
# a tile cropped tightly around a building holds its ground only farther off (PDAL's sample_c:
# 15 m): where no ground return lies within GROUND_SEARCH_M, the ground within this reach counts
GROUND_FALLBACK_M = 50.0
ROOF_CELL_M = 1.0
# below this a block is no building the catalogue's patterns describe (a shed's roof is 2.2 m up)
MIN_HEIGHT_M = 2.0
MIN_POINTS = 20
STOREY_M = 3.0
# the block stands this far into the terrain, so a ray along the wall's foot never slips between them
FOUNDATION_M = 0.5
TERRAIN_CELL_M = 2.0
TERRAIN_MARGIN_M = 30.0
# share of proxies made reinforced concrete (the patterns differ by material); the rest masonry
RC_SHARE = 0.3


class ProxyError(QuakeScanError):
    """A proxy model cannot be built from the given points and footprints."""


@dataclass(frozen=True)
class ProxyBuilding:
    id: int
    ground_z: float
    roof_z: float
    n_points: int

    @property
    def height(self) -> float:
        return self.roof_z - self.ground_z


@dataclass
class ProxyModel:
    scene: Scene
    buildings: dict  # id -> ProxyBuilding
    skipped: dict  # id -> why it has no proxy


def ground_heights(xyz: np.ndarray, cls: np.ndarray | None, polygons) -> np.ndarray:
    """Ground height near each polygon (world z): of the ground returns within GROUND_SEARCH_M,
    else within GROUND_FALLBACK_M; NaN where none (without a ground class: of any return
    within GROUND_SEARCH_M)."""
    import shapely
    from scipy.spatial import cKDTree

    has_ground = cls is not None and (cls == GROUND_CLASS).any()
    pts = xyz[cls == GROUND_CLASS] if has_ground else xyz
    q = 10.0 if has_ground else 2.0
    tree = cKDTree(pts[:, :2])
    out = np.full(len(polygons), np.nan)
    for k, poly in enumerate(polygons):
        minx, miny, maxx, maxy = poly.bounds
        centre = ((minx + maxx) / 2, (miny + maxy) / 2)
        for search in (GROUND_SEARCH_M, GROUND_FALLBACK_M) if has_ground else (GROUND_SEARCH_M,):
            cand = tree.query_ball_point(centre, math.hypot(maxx - minx, maxy - miny) / 2 + search)
            if not cand:
                continue
            cand = np.asarray(cand)
            near = shapely.dwithin(poly, shapely.points(pts[cand, :2]), search)
            if near.any():
                out[k] = float(np.percentile(pts[cand[near], 2], q))
                break
    return out


def roof_height(xyz: np.ndarray) -> float:
    """Median over 1 m cells of each cell's highest point."""
    cells = np.floor(xyz[:, :2] / ROOF_CELL_M).astype(np.int64)
    key = (cells[:, 0] - cells[:, 0].min()) * (int(np.ptp(cells[:, 1])) + 1) + (cells[:, 1] - cells[:, 1].min())
    order = np.lexsort((xyz[:, 2], key))
    last = np.r_[key[order][1:] != key[order][:-1], True]
    return float(np.median(xyz[order[last], 2]))


def build_proxy(xyz: np.ndarray, cls: np.ndarray | None, building_of_point: np.ndarray, footprints,
                origin: np.ndarray, seed: int = 0, crs: str | None = None) -> ProxyModel:
    """The proxy scene (relative to `origin`) of every footprint with at least MIN_POINTS
    points and a block at least MIN_HEIGHT_M tall, on a terrain grid of the ground points.

    `xyz`: world coordinates (float64); `cls`: ASPRS classes or None; `building_of_point`:
    footprint ID per point (0 outside every footprint, `quakescan.formats.footprints.assign_buildings`)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    ids = np.asarray(footprints.ids, dtype=np.int64)
    grounds = ground_heights(xyz, cls, footprints.polygons)
    order = np.argsort(building_of_point, kind="stable")
    sorted_ids = building_of_point[order]
    rng = np.random.default_rng([int(seed), 4401])
    rc = rng.random(len(ids)) < RC_SHARE
    proxies, skipped = {}, {}
    verts, faces, face_building, face_surface, buildings = [], [], [], [], []
    n_verts = 0
    for k, (bid, poly) in enumerate(zip(ids.tolist(), footprints.polygons)):
        lo, hi = np.searchsorted(sorted_ids, bid, "left"), np.searchsorted(sorted_ids, bid, "right")
        own = xyz[order[lo:hi]]
        if len(own) < MIN_POINTS:
            skipped[bid] = f"{len(own)} points < {MIN_POINTS}"
            continue
        if not math.isfinite(grounds[k]):
            skipped[bid] = (f"no ground return within {GROUND_FALLBACK_M:g} m (without a ground class: no return "
                            f"within {GROUND_SEARCH_M:g} m) to give its ground")
            continue
        roof = roof_height(own)
        if roof - grounds[k] < MIN_HEIGHT_M:
            skipped[bid] = f"roof {roof - grounds[k]:.2f} m above ground < {MIN_HEIGHT_M:g} m"
            continue
        proxy = ProxyBuilding(bid, float(grounds[k]), roof, len(own))
        v, f, s = prism(poly, proxy.ground_z - FOUNDATION_M, proxy.roof_z, origin)
        verts.append(v)
        faces.append(f + n_verts)
        n_verts += len(v)
        face_building.append(np.full(len(f), bid, np.int32))
        face_surface.append(s)
        proxies[bid] = proxy
        buildings.append(Building(id=bid, grade=0, material="reinforced_concrete" if rc[k] else "masonry",
                                  storeys=max(1, int(round(proxy.height / STOREY_M))), typology="proxy",
                                  seed=int(rng.integers(2**31))))
    if not proxies:
        raise ProxyError("no footprint holds enough points for a proxy building "
                         f"(at least {MIN_POINTS} points and {MIN_HEIGHT_M:g} m tall): " + _reasons(skipped))
    tv, tf = terrain_grid(xyz, cls, np.concatenate(verts) + origin, origin)
    verts.append(tv)
    faces.append(tf + n_verts)
    face_building.append(np.zeros(len(tf), np.int32))
    face_surface.append(np.full(len(tf), GROUND, np.uint8))
    scene = Scene(np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(face_building),
                  np.concatenate(face_surface), buildings, origin=origin.copy(), crs=crs, epoch="pre")
    return ProxyModel(scene, proxies, skipped)


def _reasons(skipped: dict) -> str:
    items = list(skipped.items())[:5]
    more = f" and {len(skipped) - 5} more" if len(skipped) > 5 else ""
    return "; ".join(f"building {b}: {why}" for b, why in items) + more


def prism(poly, z0: float, z1: float, origin: np.ndarray):
    """Vertices (relative to origin), triangles and surface codes of a polygon extruded from
    z0 to z1: walls outward, the roof up (ground faces of a block are never seen)."""
    import mapbox_earcut
    import shapely

    parts = list(poly.geoms) if hasattr(poly, "geoms") else [poly]
    verts, tris, surf = [], [], []
    n = 0
    for part in parts:
        part = shapely.geometry.polygon.orient(part, 1.0)  # exterior counter-clockwise, holes clockwise
        rings = [np.asarray(part.exterior.coords)[:-1, :2]] + [np.asarray(r.coords)[:-1, :2] for r in part.interiors]
        flat = np.concatenate(rings) - origin[:2]
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        roof = mapbox_earcut.triangulate_float64(flat, ends).reshape(-1, 3)
        m = len(flat)
        top = np.c_[flat, np.full(m, z1 - origin[2])]
        bottom = np.c_[flat, np.full(m, z0 - origin[2])]
        verts += [top, bottom]
        # earcut keeps the ring's orientation: counter-clockwise seen from above is an upward normal
        tris.append(_upward(roof, flat) + n)
        surf.append(np.full(len(roof), ROOF, np.uint8))
        start = 0
        for end in ends.tolist():
            i = np.arange(start, end)
            j = np.r_[i[1:], i[0]]
            # exterior ccw and holes cw: the wall (i, j) faces right of its direction, i.e. outwards
            tris.append(np.c_[i + m, j + m, j].astype(np.int64) + n)
            tris.append(np.c_[i + m, j, i].astype(np.int64) + n)
            surf.append(np.full(2 * len(i), WALL, np.uint8))
            start = end
        n += 2 * m
    return np.concatenate(verts), np.concatenate(tris).astype(np.int64), np.concatenate(surf)


def _upward(tris: np.ndarray, flat: np.ndarray) -> np.ndarray:
    a, b, c = flat[tris[:, 0]], flat[tris[:, 1]], flat[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    out = tris.astype(np.int64).copy()
    down = cross < 0
    out[down] = out[down][:, [0, 2, 1]]
    return out


def terrain_grid(xyz: np.ndarray, cls: np.ndarray | None, building_verts_world: np.ndarray, origin: np.ndarray):
    """A terrain of TERRAIN_CELL_M cells over the buildings' extent and TERRAIN_MARGIN_M
    around it: per cell the median of its ground points (all points' 2nd percentile per cell
    without a ground class), empty cells (under buildings) from the nearest filled one."""
    from scipy.spatial import cKDTree

    lo = building_verts_world[:, :2].min(axis=0) - TERRAIN_MARGIN_M
    hi = building_verts_world[:, :2].max(axis=0) + TERRAIN_MARGIN_M
    has_ground = cls is not None and (cls == GROUND_CLASS).any()
    pts = xyz[cls == GROUND_CLASS] if has_ground else xyz
    inside = np.all((pts[:, :2] >= lo) & (pts[:, :2] <= hi), axis=1)
    pts = pts[inside]
    nx = max(1, int(math.ceil((hi[0] - lo[0]) / TERRAIN_CELL_M)))
    ny = max(1, int(math.ceil((hi[1] - lo[1]) / TERRAIN_CELL_M)))
    z = np.full((nx, ny), np.nan)
    if len(pts):
        ci = np.clip(((pts[:, 0] - lo[0]) // TERRAIN_CELL_M).astype(np.int64), 0, nx - 1)
        cj = np.clip(((pts[:, 1] - lo[1]) // TERRAIN_CELL_M).astype(np.int64), 0, ny - 1)
        key = ci * ny + cj
        order = np.lexsort((pts[:, 2], key))
        key, zs = key[order], pts[order, 2]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ends = np.r_[starts[1:], len(key)]
        q = 0.5 if has_ground else 0.02
        picks = starts + np.floor((ends - starts - 1) * q).astype(np.int64)
        z.reshape(-1)[key[starts]] = zs[picks]
    filled = np.isfinite(z)
    if not filled.any():
        z[:] = building_verts_world[:, 2].min() + FOUNDATION_M
    elif not filled.all():
        fi, fj = np.nonzero(filled)
        ei, ej = np.nonzero(~filled)
        _, near = cKDTree(np.c_[fi, fj]).query(np.c_[ei, ej])
        z[ei, ej] = z[fi[near], fj[near]]
    # vertices at cell corners: the mean of the (up to four) cells around each corner
    pad = np.pad(z, 1, mode="edge")
    corner = 0.25 * (pad[:-1, :-1] + pad[1:, :-1] + pad[:-1, 1:] + pad[1:, 1:])
    gx = lo[0] + TERRAIN_CELL_M * np.arange(nx + 1)
    gy = lo[1] + TERRAIN_CELL_M * np.arange(ny + 1)
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    v = np.c_[X.ravel(), Y.ravel(), corner.ravel()] - origin
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    a = (i * (ny + 1) + j).ravel()
    b, c, d = a + (ny + 1), a + (ny + 1) + 1, a + 1
    faces = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]]).astype(np.int64)
    return v, faces
