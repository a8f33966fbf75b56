"""Compiled per-cell reductions for the planimetric density (numba).

`top_band_counts` is `np.maximum.at` of the heights into their cells followed by a count of
the points within the band below each cell's top: numpy's unbuffered `ufunc.at` takes about
50 ns a point, this loop a few (the densities of a 2 x 37 M-point pair were mostly that call).
Same comparisons on the same float64 values, so the same tops and counts to the last bit;
`top_band_counts_reference` is the numpy version the tests compare it with.
"""
from __future__ import annotations

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(**_JIT)
def top_band_counts(cell, z, n_cells, band):
    """(top height, points within `band` of it) of each of `n_cells` cells, given each
    point's cell index (0 <= cell < n_cells) and height."""
    top = np.full(n_cells, -np.inf)
    for i in range(cell.shape[0]):
        c = cell[i]
        if z[i] > top[c]:
            top[c] = z[i]
    counts = np.zeros(n_cells, np.int64)
    for i in range(cell.shape[0]):
        c = cell[i]
        if z[i] >= top[c] - band:
            counts[c] += 1
    return top, counts


def top_band_counts_reference(cell, z, n_cells, band):
    top = np.full(n_cells, -np.inf)
    np.maximum.at(top, cell, z)
    counts = np.bincount(cell[z >= top[cell] - band], minlength=n_cells).astype(np.int64)
    return top, counts
