"""Building footprints from a cloud's own building class, where no outline file exists.

Many archives classify their returns (ASPRS class 6: building) but ship no outlines. The
outline of a building is then where its class-6 returns lie: on a grid of `cell_m` cells,
a cell is building when it holds a class-6 return; gaps of sampling (a cell between two
returns that got none, at a few points per m²) are closed by one morphological closing
over `close_cells` cells; 8-connected components of building cells are buildings; each
outline is the union of its cells (axis-aligned, exact to a cell), simplified by half a cell.
Components smaller than `min_area_m2` (a misclassified tree crown, a car) are left out. IDs
are 1, 2, … in the order of each component's lowest cell (x, then y): the same cloud gives
the same IDs.

Adjacent buildings whose roofs touch come out as one component: class 6 does not say
where one building ends. Footprints from a cadastre or OpenStreetMap are better where they
exist.
"""
from __future__ import annotations

import math

import numpy as np

from .footprints import FootprintError, Footprints

VERSION = 1  # the outlines a cloud gives: a change makes every derived footprint file new
BUILDING_CLASS = 6
CELL_M = 1.0
CLOSE_CELLS = 1
MIN_AREA_M2 = 20.0


def footprints_from_class(xyz: np.ndarray, cls: np.ndarray, *, crs: str | None = None,
                          building_class: int = BUILDING_CLASS, cell_m: float = CELL_M,
                          close_cells: int = CLOSE_CELLS, min_area_m2: float = MIN_AREA_M2,
                          source: str = "building class") -> Footprints:
    """Footprints (world coordinates, `crs`) of the connected regions of `building_class` returns."""
    import shapely
    from scipy import ndimage

    xyz, cls = np.asarray(xyz, dtype=np.float64), np.asarray(cls)
    if xyz.ndim != 2 or xyz.shape[1] < 2 or len(cls) != len(xyz):
        raise FootprintError(f"{source}: points must be (n, 2 or 3) with one class each, got {xyz.shape} "
                             f"and {cls.shape}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise FootprintError(f"{source}: cell size must be a positive number of metres, got {cell_m!r}")
    sel = (cls == building_class) & np.all(np.isfinite(xyz[:, :2]), axis=1)
    if not sel.any():
        raise FootprintError(f"{source}: no return of class {building_class} (building): no footprints "
                             "can be derived; give footprints")
    xy = xyz[sel, :2]
    pad = close_cells + 1  # room for the closing at the edges
    lo = np.floor(xy.min(axis=0) / cell_m) * cell_m - pad * cell_m
    ij = ((xy - lo) // cell_m).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1 + pad)
    grid = np.zeros(shape, bool)
    grid[ij[:, 0], ij[:, 1]] = True
    if close_cells > 0:
        grid = ndimage.binary_closing(grid, structure=np.ones((3, 3), bool), iterations=close_cells)
    labels, n = ndimage.label(grid, structure=np.ones((3, 3), bool))
    ids, polygons, props = [], [], []
    for k in range(1, n + 1):
        ci, cj = np.nonzero(labels == k)  # in x, then y order: the lowest cell first
        if len(ci) * cell_m * cell_m < min_area_m2:
            continue
        x0, y0 = lo[0] + ci * cell_m, lo[1] + cj * cell_m
        outline = shapely.union_all(shapely.box(x0, y0, x0 + cell_m, y0 + cell_m)).simplify(cell_m / 2)
        if not outline.is_valid:
            outline = outline.buffer(0)
        if outline.is_empty:
            continue
        ids.append(len(ids) + 1)
        polygons.append(outline)
        props.append({"building_id": len(ids), "cells": int(len(ci))})
    if not polygons:
        raise FootprintError(f"{source}: the class-{building_class} returns form no region of "
                             f"{min_area_m2:g} m² or more: no footprints")
    return Footprints(np.array(ids, dtype=np.int64), polygons, crs, source, props)
