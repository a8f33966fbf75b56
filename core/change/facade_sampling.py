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
"""
from __future__ import annotations

import numpy as np

BAND_BOTTOM_M = 1.0  # above the ground: cars, hedges and the foot of the wall's debris stay out
BAND_TOP_M = 0.5  # below the eave: the roof's edge stays out
EAVE_PERCENTILE = 10.0
MIN_BAND_M = 1.0  # a band lower than this (a one-storey shed under a low eave) has no facade to count


def facade_densities(own_xyz: np.ndarray, pre_xyz: np.ndarray, post_xyz: np.ndarray, building_keys: np.ndarray,
                     ground: float, lo, cell_m: float, width: int) -> tuple[float, float, float]:
    """(pre-event returns per m² of facade, post-event ones, facade area m²) of one building
    from its own pre-event returns `own_xyz`, every return of each epoch near it (`pre_xyz`,
    `post_xyz`, its box and two cells more suffice) and every building's cells
    (`building_keys`, key = i * width + j of the grid at `lo` with cells of `cell_m`). (0, 0, 0)
    where it has no facade band."""
    def keys(xyz):
        return (np.floor((xyz[:, 0] - lo[0]) / cell_m).astype(np.int64) * width
                + np.floor((xyz[:, 1] - lo[1]) / cell_m).astype(np.int64))

    own_key, own_z = keys(own_xyz), own_xyz[:, 2]
    if not len(own_key):
        return 0.0, 0.0, 0.0
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
        return 0.0, 0.0, 0.0
    z_lo, z_hi = ground + BAND_BOTTOM_M, float(np.percentile(roof_z, EAVE_PERCENTILE)) - BAND_TOP_M
    if z_hi - z_lo < MIN_BAND_M:
        return 0.0, 0.0, 0.0
    ring = np.unique(nb[outside])
    # a wall on a cell boundary puts its returns on both sides of it: the outline cells and
    # the cells just inside them
    inner = cells[np.isin(nb, outline).any(axis=1)]
    band = np.unique(np.concatenate([outline, inner, ring[~np.isin(ring, building_keys)]]))
    area = length * (z_hi - z_lo)

    def count(xyz):
        if not len(xyz):
            return 0
        return int(np.count_nonzero(np.isin(keys(xyz), band) & (xyz[:, 2] > z_lo) & (xyz[:, 2] < z_hi)))
    return count(pre_xyz) / area, count(post_xyz) / area, area


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
