"""The one density measure of the project: points per m² of roof seen from above, on 1 m
cells of the clouds' frame.

Every stage that speaks of density measures it here: the simulators' thinning to a target
density (`quakescan.acquisition.density`), the descriptors' grids and chance rules
(`quakescan.change.surface`), the model's density features, the Dask blocks, which are squares
of these cells (`quakescan.distributed.block_store`), and the tiles' streamed shares of it
(`quakescan.distributed.tasks`).
"""
from __future__ import annotations

import math

import numpy as np

DENSITY_CELL_M = 1.0
ROOF_BAND_M = 1.0


def roof_cell_density(cells: np.ndarray, z: np.ndarray) -> tuple[float, int]:
    """(density [pts/m²], interior cells) of building points given their integer 1 m cells
    (n, 2) and heights: in each cell the points within ROOF_BAND_M of its highest point (roofs
    up to 45° whole, walls below the eaves not), over the cells whose eight neighbours are
    occupied too (a cell cut by an outline does not count), the interquartile mean of those
    counts per m² (robust to chimneys and leftover walls). NaN, 0 without an interior cell."""
    from scipy.stats import trim_mean

    if len(cells) == 0:
        return math.nan, 0
    lo = cells.min(axis=0) - 1  # cell - lo >= 1: every neighbour index stays >= 0
    span = int(cells[:, 1].max() - lo[1]) + 2
    key = (cells[:, 0] - lo[0]) * span  # built in place: no (n, 2) copy of a whole epoch's cells
    key += cells[:, 1] - lo[1]
    keys, inverse = np.unique(key, return_inverse=True)
    del key
    counts = roof_band_counts(inverse, z, len(keys))
    interior = np.ones(len(keys), bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx or dy:
                nb = keys + dx * span + dy
                interior &= keys[np.minimum(np.searchsorted(keys, nb), len(keys) - 1)] == nb
    if not interior.any():
        return math.nan, 0
    return float(trim_mean(counts[interior], 0.25)) / DENSITY_CELL_M ** 2, int(interior.sum())


def planimetric_density(xyz: np.ndarray, where: np.ndarray | None = None) -> float:
    """Points per m² of roof seen from above (`roof_cell_density` on 1 m cells of the given
    frame; the same measure as `quakescan.acquisition.density.measured_density`). A building too small for
    an interior cell takes the mean top-band count of all its cells; no point gives 0.
    `where`: a mask of the points to measure, so that a whole epoch's building points are
    measured without a copy of their coordinates (a column at a time: 0.7 GB less at the
    peak of a 37 M-point epoch)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    dense = _dense_planimetric_density(xyz, where)
    if dense is not None:
        return dense
    idx = slice(None) if where is None else np.flatnonzero(where)
    z = xyz[idx, 2]
    if len(z) == 0:
        return 0.0
    cells = np.empty((len(z), 2), dtype=np.int64)
    for k in range(2):
        cells[:, k] = np.floor(xyz[idx, k] / DENSITY_CELL_M)
    del idx
    d, n = roof_cell_density(cells, z)
    if n:
        return d
    keys, inverse = np.unique(cells[:, 0] * (int(cells[:, 1].max() - cells[:, 1].min()) + 2)
                              + (cells[:, 1] - cells[:, 1].min()), return_inverse=True)
    return float(roof_band_counts(inverse, z, len(keys)).mean()) / DENSITY_CELL_M ** 2


def _dense_planimetric_density(xyz: np.ndarray, where: np.ndarray | None) -> float | None:
    """`planimetric_density` counted on a dense grid over the points' cells, in compiled
    loops that make no per-point array: the same cells, counts and measure (the
    interquartile mean and the mean of integer counts do not depend on their order), at a
    few bytes per cell instead of about 60 per point (a 75 M-point epoch: 2.6 GB less at the
    peak). None where the grid would be much larger than the points (scattered clouds)."""
    from .cells import cell_span, dense_top_band_counts

    xyz = np.ascontiguousarray(xyz)
    mask = np.zeros(0, bool) if where is None else np.ascontiguousarray(where, dtype=bool)
    lo_i, lo_j, hi_i, hi_j, n = cell_span(xyz, mask, DENSITY_CELL_M)
    if n == 0:
        return 0.0
    # one empty cell of margin all round: every occupied cell has eight neighbours on the grid
    lo_i, lo_j = lo_i - 1, lo_j - 1
    rows, width = int(hi_i - lo_i) + 2, int(hi_j - lo_j) + 2
    if rows * width > max(8 * n, 1 << 20):
        return None
    counts = dense_top_band_counts(xyz, mask, DENSITY_CELL_M, lo_i, lo_j, width, rows * width,
                                   float(ROOF_BAND_M)).reshape(rows, width)
    occupied = counts > 0
    interior = occupied.copy()
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx or dy:
                interior[1:-1, 1:-1] &= occupied[1 + dx:rows - 1 + dx, 1 + dy:width - 1 + dy]
    interior[[0, -1], :] = False
    interior[:, [0, -1]] = False
    if interior.any():
        from scipy.stats import trim_mean

        return float(trim_mean(counts[interior], 0.25)) / DENSITY_CELL_M ** 2
    return float(counts[occupied].mean()) / DENSITY_CELL_M ** 2


def roof_band_counts(cell: np.ndarray, z: np.ndarray, n_cells: int) -> np.ndarray:
    """Per cell the points within ROOF_BAND_M of its highest (compiled: `quakescan.grid.cells`)."""
    from .cells import top_band_counts

    return top_band_counts(np.ascontiguousarray(cell, dtype=np.int64).reshape(-1),
                           np.ascontiguousarray(z, dtype=np.float64), int(n_cells), float(ROOF_BAND_M))[1]
