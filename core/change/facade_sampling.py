"""How densely each epoch sampled a building's facades: the returns on its walls per m².

An airborne laser looks down: its returns on walls are few (AHN3: a fraction of a return per
m² of facade), a drone's oblique photos and pulses put dozens there. Heavy damage confined to
walls (holes and break-outs over 2-10 % of a facade, docs/DAMAGE_CATALOGUE.md) can only be seen
where both epochs sampled the walls (`quakescan.change.detectability.walls_resolved`).

The **facade band** of a building is its outline cells (a 4-neighbour outside the building),
the cells just inside them (a wall on a cell boundary puts its returns on both sides) and the
cells just outside them that belong to no building, between `BAND_BOTTOM_M` above the
ground and `BAND_TOP_M` below the eave (the 10th percentile of its cells' tops, each cell's
highest own pre-event return, where more than 2 m above the ground: the lower part of its
roof). Returns there are wall returns (or whatever stands against the wall: both epochs
alike). The facade area is the outline length (outline cells' outer edges) times the band's
height; each epoch's density is its band returns over that area.

Each **facing** (the outline edges open to +x, -x, +y or -y onto a cell of no building) is also
counted apart, its band without the corner cells that hold the next wall's returns: heavy
damage confined to walls may be on one facade, and an airborne flight may never face it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

BAND_BOTTOM_M = 1.0  # above the ground: cars, hedges and the foot of the wall's debris stay out
BAND_TOP_M = 0.5  # below the eave: the roof's edge stays out
EAVE_PERCENTILE = 10.0
MIN_BAND_M = 1.0  # a band lower than this (a one-storey shed under a low eave) has no facade to count
# A facing shorter than this holds no heavy wall damage of its own (the catalogue's holes are
# 0.5-2 m, one to four a facade, with masonry between): a jog of the outline is part of the wall beside it
MIN_FACING_M = 3.0


class FacadeSampling(NamedTuple):
    """How densely each epoch sampled a building's facades: all of them together (returns per
    m² of facade, and their area), and each open facing apart (`facings`: (area m², pre, post)
    of the outline edges facing +x, -x, +y and -y that no other building covers and that are
    at least `MIN_FACING_M` long), since heavy damage confined to walls may be on one facade."""

    pre: float
    post: float
    area_m2: float
    facings: tuple = ()


NO_FACADE = FacadeSampling(0.0, 0.0, 0.0)


def facade_densities(own_xyz: np.ndarray, pre_xyz: np.ndarray, post_xyz: np.ndarray, building_keys: np.ndarray,
                     ground: float, lo, cell_m: float, width: int) -> FacadeSampling:
    """The `FacadeSampling` of one building from its own pre-event returns `own_xyz`, every
    return of each epoch near it (`pre_xyz`, `post_xyz`, its box and two cells more suffice)
    and every building's cells (`building_keys`, key = i * width + j of the grid at `lo` with
    cells of `cell_m`). `NO_FACADE` where it has no facade band."""
    def keys(xyz):
        return (np.floor((xyz[:, 0] - lo[0]) / cell_m).astype(np.int64) * width
                + np.floor((xyz[:, 1] - lo[1]) / cell_m).astype(np.int64))

    own_key, own_z = keys(own_xyz), own_xyz[:, 2]
    if not len(own_key):
        return NO_FACADE
    cells = _closed(np.unique(own_key), width)
    steps = np.array([width, -width, 1, -1], np.int64)
    nb = cells[:, None] + steps[None, :]
    outside = ~np.isin(nb, cells)
    outline = cells[outside.any(axis=1)]
    length = float(outside.sum()) * cell_m  # outer edges of the outline cells
    # the eave: the low end of the cells' tops (each cell's highest own return: the roof,
    # wherever the walls' returns lie below it; an outline cell may hold only wall returns)
    tops = np.full(len(cells), -np.inf)
    np.maximum.at(tops, np.searchsorted(cells, own_key), own_z)
    roof_z = tops[tops > ground + 2.0]
    if not len(roof_z):
        return NO_FACADE
    z_lo, z_hi = ground + BAND_BOTTOM_M, float(np.percentile(roof_z, EAVE_PERCENTILE)) - BAND_TOP_M
    if z_hi - z_lo < MIN_BAND_M:
        return NO_FACADE
    ring = np.unique(nb[outside])
    # a wall on a cell boundary puts its returns on both sides of it: the outline cells and
    # the cells just inside them
    inner = cells[np.isin(nb, outline).any(axis=1)]
    band = np.unique(np.concatenate([outline, inner, ring[~np.isin(ring, building_keys)]]))
    area = length * (z_hi - z_lo)

    pre_keys, post_keys = (keys(xyz)[(xyz[:, 2] > z_lo) & (xyz[:, 2] < z_hi)] if len(xyz) else np.zeros(0, np.int64)
                           for xyz in (pre_xyz, post_xyz))

    def count(k, cells_of_band):
        return int(np.count_nonzero(np.isin(k, cells_of_band)))

    facings = []
    # a facing's edges: outline cells open on that side to a cell of no building (a party wall
    # shows nothing and falls on nothing)
    open_side = outside & ~np.isin(nb, building_keys)
    for side in range(4):
        edge = open_side[:, side]
        run_m = float(edge.sum()) * cell_m
        if run_m < MIN_FACING_M:
            continue
        at = cells[edge]
        # its band: those cells, the cell inside each and the open cell outside it, but no cell
        # on an edge of another side: a corner's cells hold the returns of the wall round it
        corners = cells[open_side[:, [k for k in range(4) if k != side]].any(axis=1)]
        own_band = np.setdiff1d(np.concatenate([at, at - steps[side], at + steps[side]]), corners)
        sampled = float(len(np.setdiff1d(at, corners))) * cell_m * (z_hi - z_lo)  # the wall the band sees
        if sampled <= 0.0:
            continue
        facings.append((round(run_m * (z_hi - z_lo), 1), round(count(pre_keys, own_band) / sampled, 3),
                        round(count(post_keys, own_band) / sampled, 3)))
    return FacadeSampling(count(pre_keys, band) / area, count(post_keys, band) / area, area, tuple(facings))


def _closed(cells: np.ndarray, width: int) -> np.ndarray:
    """The cells with the single empty cells of a sparse sampling closed (a 3 x 3 closing), so
    that they add no outline inside the building."""
    from scipy import ndimage

    i, j = cells // width, cells % width
    i0, j0 = i.min() - 2, j.min() - 2
    grid = np.zeros((i.max() - i0 + 3, j.max() - j0 + 3), bool)
    grid[i - i0, j - j0] = True
    grid |= ndimage.binary_closing(grid, np.ones((3, 3), bool))
    gi, gj = np.nonzero(grid)
    return np.sort((gi + i0) * width + (gj + j0))
