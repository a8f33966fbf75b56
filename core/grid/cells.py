"""Compiled per-cell loops (numba): the planimetric density's reductions and the bucket
order of a grid index.

`top_band_counts` is `np.maximum.at` of the heights into their cells followed by a count of
the points within the band below each cell's top: numpy's unbuffered `ufunc.at` takes about
50 ns a point, this loop a few (the densities of a 2 x 37 M-point pair were mostly that call).
Same comparisons on the same float64 values, so the same tops and counts to the last bit;
`top_band_counts_reference` is the numpy version the tests compare it with.

`bucket_order` is a counting sort: the order a stable argsort of the cell keys gives, in
two passes and without the argsort's 8-byte-a-point index and its copy of the sorted keys
(a 75 M-point epoch's grid index was 8 s and 1.3 GB of temporaries that way).
"""
from __future__ import annotations

import math

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


@njit(**_JIT)
def bucket_order(key, n_keys, order):
    """Fill `order` with the indices of `key` (0 <= key < n_keys) sorted by key, equal keys in
    index order (a stable argsort), and return the (n_keys + 1,) start of each key's run."""
    starts = np.zeros(n_keys + 1, np.int64)
    for i in range(key.shape[0]):
        starts[key[i] + 1] += 1
    for k in range(n_keys):
        starts[k + 1] += starts[k]
    fill = starts[:-1].copy()
    for i in range(key.shape[0]):
        k = key[i]
        order[fill[k]] = i
        fill[k] += 1
    return starts


@njit(**_JIT)
def cell_span(xyz, mask, cell_m):
    """(min i, min j, max i, max j, points) of the cells floor(x / cell_m), floor(y / cell_m)
    of the points where `mask` is set (all points when `mask` is empty)."""
    lo_i = lo_j = np.iinfo(np.int64).max
    hi_i = hi_j = np.iinfo(np.int64).min
    n = 0
    every = mask.shape[0] == 0
    for p in range(xyz.shape[0]):
        if every or mask[p]:
            i = np.int64(np.floor(xyz[p, 0] / cell_m))
            j = np.int64(np.floor(xyz[p, 1] / cell_m))
            lo_i, hi_i = min(lo_i, i), max(hi_i, i)
            lo_j, hi_j = min(lo_j, j), max(hi_j, j)
            n += 1
    return lo_i, lo_j, hi_i, hi_j, n


@njit(**_JIT)
def dense_top_band_counts(xyz, mask, cell_m, lo_i, lo_j, width, n_cells, band):
    """`top_band_counts` on a dense grid of `width` columns whose cell (0, 0) is (lo_i, lo_j),
    the cells computed in the loop: no per-point cell or height array is made."""
    every = mask.shape[0] == 0
    top = np.full(n_cells, -np.inf)
    for p in range(xyz.shape[0]):
        if every or mask[p]:
            c = (np.int64(np.floor(xyz[p, 0] / cell_m)) - lo_i) * width + np.int64(np.floor(xyz[p, 1] / cell_m)) - lo_j
            if xyz[p, 2] > top[c]:
                top[c] = xyz[p, 2]
    counts = np.zeros(n_cells, np.int64)
    for p in range(xyz.shape[0]):
        if every or mask[p]:
            c = (np.int64(np.floor(xyz[p, 0] / cell_m)) - lo_i) * width + np.int64(np.floor(xyz[p, 1] / cell_m)) - lo_j
            if xyz[p, 2] >= top[c] - band:
                counts[c] += 1
    return counts


@njit(**_JIT)
def grid_keys(xy, lo0, lo1, cell, width, key):
    """key[p] = floor((x - lo0) / cell) * width + floor((y - lo1) / cell): the same float64
    operations as numpy's, so the same cells."""
    for p in range(xy.shape[0]):
        key[p] = np.int64(np.floor((xy[p, 0] - lo0) / cell)) * width + np.int64(np.floor((xy[p, 1] - lo1) / cell))


def column_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of every column of a 2-D array in one pass over its rows, as float64; no
    rows give (inf, -inf), a NaN in a column makes both of its bounds NaN (as numpy's)."""
    lo = np.full(a.shape[1], np.inf)
    hi = np.full(a.shape[1], -np.inf)
    _widen_bounds(a, lo, hi, 0)
    return lo, hi


def row_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(a.min(axis=0), a.max(axis=0))` of a 2-D array in one compiled pass over its rows:
    the same dtype and values, NaN propagating, and numpy's ValueError for no rows. numpy
    reduces an (n, 2) or (n, 3) array down its rows a few elements an inner loop (about
    20 ns a row for a strided x/y view): the bounds were a tenth of a tile's description."""
    if a.ndim != 2 or a.shape[0] == 0:
        return a.min(axis=0), a.max(axis=0)  # numpy's own answer or error
    lo, hi = a[0].copy(), a[0].copy()
    _widen_bounds(a, lo, hi, 1)
    return lo, hi


@njit(**_JIT)
def _widen_bounds(a, lo, hi, first):
    """Widen lo/hi over the rows from `first` on; a NaN, once met, stays."""
    for p in range(first, a.shape[0]):
        for k in range(a.shape[1]):
            v = a[p, k]
            if v < lo[k] or v != v:  # a NaN bound compares False with anything after it
                lo[k] = v
            if v > hi[k] or v != v:
                hi[k] = v


@njit(**_JIT)
def splitmix_below(start, index, n, threshold):
    """Whether the splitmix64 hash of each point index is below `threshold`: the indices
    `start + i` for i < n when `index` is empty, else `index` itself. Unsigned 64-bit
    arithmetic wraps as numpy's does, so the same bits as the numpy expression."""
    given = index.shape[0] > 0
    m = index.shape[0] if given else n
    out = np.empty(m, np.bool_)
    for i in range(m):
        z = np.uint64(index[i]) if given else np.uint64(start + i)
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
        out[i] = z < threshold
    return out


def stable_order(key: np.ndarray) -> np.ndarray:
    """`np.argsort(key, kind="stable")` of integer keys: a counting sort when their span is
    within a few times their number (cells of one region, IDs of its buildings), numpy's
    radix/merge sort otherwise."""
    key = np.asarray(key)
    n = len(key)
    if n == 0:
        return np.zeros(0, np.int64)
    lo, hi = int(key.min()), int(key.max())
    if hi - lo >= 4 * n + 1024:
        return np.argsort(key, kind="stable")
    order = np.empty(n, np.int64)
    bucket_order(key.astype(np.int64) - lo if lo else key.astype(np.int64, copy=False), hi - lo + 1, order)
    return order


@njit(**_JIT)
def cell_keys(xyz, lo0, lo1, cell, width):
    """floor((x - lo0) / cell) * width + floor((y - lo1) / cell) per point: numpy's expression
    over the (n, 2) columns, without its three temporaries."""
    out = np.empty(xyz.shape[0], np.int64)
    for p in range(xyz.shape[0]):
        out[p] = np.int64(math.floor((xyz[p, 0] - lo0) / cell)) * width + np.int64(math.floor((xyz[p, 1] - lo1) / cell))
    return out


@njit(**_JIT)
def top_layers(key, order, z_all, layer_m, stride):
    """Per cell (the runs of equal `key` in `order`): the key, the start of its run, its top
    layer's mean height (points within `layer_m` of the highest), the lowest height, the
    layer's count and sum of squared deviations, and every point's band key (cell number x
    `stride` + height above the lowest point), sorted. The sums run over the points in
    `order`, as numpy's bincount over them adds, so every value is numpy's to the bit."""
    n = order.shape[0]
    z = np.empty(n)
    n_runs = 0
    zmin = np.inf
    for p in range(n):
        z[p] = z_all[order[p]]
        if z[p] < zmin:
            zmin = z[p]
        if p == 0 or key[order[p]] != key[order[p - 1]]:
            n_runs += 1
    starts = np.empty(n_runs + 1, np.int64)
    keys = np.empty(n_runs, np.int64)
    r = -1
    for p in range(n):
        if p == 0 or key[order[p]] != key[order[p - 1]]:
            r += 1
            starts[r] = p
            keys[r] = key[order[p]]
    starts[n_runs] = n
    z0 = -zmin
    mean = np.empty(n_runs)
    bottom = np.empty(n_runs)
    layer_n = np.zeros(n_runs, np.int64)
    sq = np.zeros(n_runs)
    band = np.empty(n)
    for r in range(n_runs):
        a, b = starts[r], starts[r + 1]
        top = -np.inf
        low = np.inf
        for p in range(a, b):
            if z[p] > top:
                top = z[p]
            if z[p] < low:
                low = z[p]
            band[p] = r * stride + (z[p] + z0)
        bottom[r] = low
        s = 0.0
        for p in range(a, b):
            if z[p] >= top - layer_m:
                layer_n[r] += 1
                s += z[p]
        m = s / layer_n[r]
        mean[r] = m
        for p in range(a, b):
            if z[p] >= top - layer_m:
                d = z[p] - m
                sq[r] += d * d
        # the runs' band keys lie apart by the stride: sorting each run sorts them all
        if b - a <= 48:  # a cell's few points: in place, no array made
            for p in range(a + 1, b):
                v = band[p]
                q = p - 1
                while q >= a and band[q] > v:
                    band[q + 1] = band[q]
                    q -= 1
                band[q + 1] = v
        else:
            band[a:b] = np.sort(band[a:b])
    return keys, starts, mean, bottom, layer_n, sq, band, z0
