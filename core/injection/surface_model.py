"""The surface a real cloud saw, as a scene another sensor can fly over.

A responder's usual pair is an airborne archive before and a drone after. To put that pair
into the training set and the benchmark with damage in real points, the drone needs a
scene: the real city, not a model of it. `surface_scene` makes one from a real cloud's own
returns, a 2.5D surface (a digital surface model) on a grid of `cell_m` cells:

- per cell the highest return (the top of what a pulse from above meets first); noise
  classes are left out;
- a cell takes its height only from returns of its own region: inside a footprint from that
  footprint's returns, outside from the returns outside every footprint, and an empty cell
  from the nearest filled cell of its region. A wall then stands on the footprint's outline
  (within a cell), not wherever the sparse returns left the roof's last cell;
- vertices at cell centres (a cell's height is exact where it was measured), two triangles
  per four neighbouring cells;
- a triangle belongs to a building when any of its vertices lies in its footprint (the
  highest such vertex decides between two footprints), and is a wall where steeper than
  WALL_SLOPE_DEG, roof otherwise; outside the footprints its class is the top return's:
  ground (and water), vegetation, or an object.

Walls are as steep as one cell allows (a 6 m wall over 0.5 m: 85 degrees), overhangs and
anything under a tree crown are not in it: a 2.5D surface holds what a nadir view holds. The
returns of a drone flown over it then go through `quakescan inject` as a real cloud's do.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import QuakeScanError
from ..formats.scene import GROUND, OBJECT, ROOF, VEGETATION, WALL, Building, Scene

VERSION = 1  # the surface a cloud gives: a change makes every scene of it new
CELL_M = 0.5
WALL_SLOPE_DEG = 60.0
# ASPRS classes: noise (7 low, 18 high) is not a surface; what is ground, what is vegetation
NOISE_CLASSES = (7, 18)
GROUND_CLASSES = (2, 9)
VEGETATION_CLASSES = (3, 4, 5)
STOREY_M = 3.0
# the cells of a region are found among the filled cells of the same region first: a
# region's cells are put this far apart from the others' in the nearest-cell search
_REGION_SPACING = 1e7


class SurfaceModelError(QuakeScanError):
    """A surface scene cannot be made from the cloud as given."""


def surface_scene(xyz: np.ndarray, cls: np.ndarray | None, footprints, origin, *, cell_m: float = CELL_M,
                  crs: str | None = None, building_of_point: np.ndarray | None = None) -> Scene:
    """The 2.5D surface scene (relative to `origin`) of the cloud `xyz` (world coordinates),
    its buildings those of `footprints` (`quakescan.formats.footprints.Footprints`) that hold
    a return; every building undamaged (grade 0). `cls`: ASPRS classes or None."""
    from ..formats.footprints import assign_buildings

    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise SurfaceModelError(f"surface scene: points must be (n, 3), got shape {xyz.shape}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise SurfaceModelError(f"surface scene: cell size must be a positive number of metres, got {cell_m!r}")
    keep = np.all(np.isfinite(xyz), axis=1)
    if cls is not None:
        cls = np.asarray(cls)
        keep &= ~np.isin(cls, NOISE_CLASSES)
    if not keep.any():
        raise SurfaceModelError("surface scene: the cloud holds no return that is not noise")
    xyz = xyz[keep]
    cls = cls[keep] if cls is not None else np.ones(len(xyz), np.uint8)
    origin = np.asarray(origin, dtype=np.float64)
    lo = np.floor(xyz[:, :2].min(axis=0) / cell_m) * cell_m  # cells on multiples of cell_m: halves of one cloud share a grid
    nx = int(math.floor((xyz[:, 0].max() - lo[0]) / cell_m)) + 1
    ny = int(math.floor((xyz[:, 1].max() - lo[1]) / cell_m)) + 1
    if nx < 2 or ny < 2:
        raise SurfaceModelError(f"surface scene: the cloud spans {nx} x {ny} cells of {cell_m:g} m; "
                                "at least 2 x 2 are needed for a surface")
    cx = lo[0] + (np.arange(nx) + 0.5) * cell_m
    cy = lo[1] + (np.arange(ny) + 0.5) * cell_m
    CX, CY = np.meshgrid(cx, cy, indexing="ij")
    region = assign_buildings(CX.ravel(), CY.ravel(), footprints)  # footprint ID per cell, 0 outside
    point_region = (assign_buildings(xyz[:, 0], xyz[:, 1], footprints) if building_of_point is None
                    else np.asarray(building_of_point, dtype=np.int64)[keep])
    ci = np.minimum(((xyz[:, 0] - lo[0]) // cell_m).astype(np.int64), nx - 1)
    cj = np.minimum(((xyz[:, 1] - lo[1]) // cell_m).astype(np.int64), ny - 1)
    cell = ci * ny + cj
    own = point_region == region[cell]  # a return counts for its cell only if both lie in one region
    # a footprint none of whose cells holds a return of its own is not a building of this scene
    seen = np.unique(region[cell[own]])
    region = np.where(np.isin(region, seen), region, 0)
    own = point_region == region[cell]
    z, top_class = _highest(cell[own], xyz[own, 2], cls[own], nx * ny)
    z, top_class = _fill_by_region(z, top_class, region, nx, ny)
    vertices = np.c_[CX.ravel(), CY.ravel(), z] - origin
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1
    faces = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]]).astype(np.int64)
    face_building, face_surface = _labels(vertices, faces, region, top_class)
    present = set(np.unique(face_building[face_building > 0]).tolist())
    buildings = []
    for bid in footprints.ids.tolist():
        if bid not in present:
            continue
        tall = float(np.ptp(vertices[faces[face_building == bid]][..., 2]))
        buildings.append(Building(id=int(bid), grade=0, storeys=max(1, int(round(tall / STOREY_M))),
                                  typology="surface"))
    return Scene(vertices, faces, face_building.astype(np.int32), face_surface.astype(np.uint8), buildings,
                 origin=origin.copy(), crs=crs, epoch="pre")


def _highest(cell: np.ndarray, z: np.ndarray, cls: np.ndarray, n_cells: int):
    """(height, class of that return) of each cell's highest return; NaN, 0 where none."""
    height = np.full(n_cells, np.nan)
    top = np.zeros(n_cells, np.int64)
    if len(cell):
        order = np.lexsort((z, cell))  # by cell, then height: the last of each cell is its highest
        last = np.r_[cell[order][1:] != cell[order][:-1], True]
        pick = order[last]
        height[cell[pick]] = z[pick]
        top[cell[pick]] = cls[pick]
    return height, top


def _fill_by_region(z, top_class, region, nx, ny):
    """Empty cells from the nearest filled cell of their own region (every region holds one)."""
    from scipy.spatial import cKDTree

    filled = np.isfinite(z)
    if not filled.any():  # every return lies in another region than its cell
        raise SurfaceModelError("surface scene: no cell holds a return of its own region")
    if filled.all():
        return z, top_class
    ij = np.c_[np.arange(nx * ny) // ny, np.arange(nx * ny) % ny].astype(np.float64)
    key = np.c_[ij, region.astype(np.float64) * _REGION_SPACING]
    tree = cKDTree(key[filled])
    empty = np.flatnonzero(~filled)
    _, near = tree.query(key[empty])
    source = np.flatnonzero(filled)[near]
    z, top_class = z.copy(), top_class.copy()
    z[empty] = z[source]
    top_class[empty] = top_class[source]
    return z, top_class


def _labels(vertices, faces, region, top_class):
    """Building and surface code per triangle."""
    fr = region[faces]  # (m, 3) footprint ID of each corner's cell
    fz = vertices[faces][..., 2]
    inside = fr > 0
    # the building of a triangle: the highest of its corners inside a footprint
    zz = np.where(inside, fz, -np.inf)
    pick = np.argmax(zz, axis=1)
    building = np.where(inside.any(axis=1), fr[np.arange(len(faces)), pick], 0)
    v = vertices[faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    up = np.abs(normal[:, 2]) / np.maximum(np.linalg.norm(normal, axis=1), 1e-300)
    steep = up < math.cos(math.radians(WALL_SLOPE_DEG))
    surface = np.where(steep, WALL, ROOF)
    # outside the footprints: what the first corner's top return was
    outer = top_class[faces[:, 0]]
    other = np.where(np.isin(outer, VEGETATION_CLASSES), VEGETATION,
                     np.where(np.isin(outer, GROUND_CLASSES) | (outer == 0), GROUND, OBJECT))
    surface = np.where(building > 0, surface, other)
    return building, surface
