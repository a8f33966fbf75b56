"""Plain numpy references of `quakescan.change._nn_kernels`, one per compiled function, for the tests
that compare the two; nothing in production calls them. (`quakescan.change.split.
nearest_neighbours_reference`, scipy's kd-tree, is a public alternative to the whole
search, and the fallback for far queries; `nearest` here is the brute-force definition.)
"""
from __future__ import annotations

import numpy as np


def bounds_xy(xyz):
    """`_nn_kernels.bounds_xy`: (min x, min y, max x, max y)."""
    return np.array([xyz[:, 0].min(), xyz[:, 1].min(), xyz[:, 0].max(), xyz[:, 1].max()])


def column_index(xyz, lo_x, lo_y, cell, nx, ny):
    """`_nn_kernels.column_index`: column ix * ny + iy of every point, clamped into the grid."""
    ix = np.clip(np.floor((xyz[:, 0] - lo_x) / cell).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor((xyz[:, 1] - lo_y) / cell).astype(np.int64), 0, ny - 1)
    return ix * ny + iy


def counting_sort(col, ncol):
    """`_nn_kernels.counting_sort`: stable order by column and the start of every column."""
    order = np.argsort(col, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(col, minlength=ncol))]).astype(np.int64)
    return order, starts


def sort_columns_by_z(order, starts, xyz):
    """`_nn_kernels.sort_columns_by_z`: `order` re-sorted in place by z within each column
    (stable), and the coordinates in that order."""
    column = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    order[:] = order[np.lexsort((xyz[order, 2], column))]
    return xyz[order, 0].copy(), xyz[order, 1].copy(), xyz[order, 2].copy()


def nearest(q, px, py, pz, orig, out_i, out_d, chunk=256):
    """`_nn_kernels.nearest` by brute force: for every query the nearest of all points
    (the kernel's squared distance; ties to the lower original index `orig`). Unlike the
    kernel it answers every query (the kernel leaves far ones, -1, to a kd-tree)."""
    for a in range(0, len(q), chunk):
        b = min(a + chunk, len(q))
        dx = px[None, :] - q[a:b, 0:1]
        dy = py[None, :] - q[a:b, 1:2]
        dz = pz[None, :] - q[a:b, 2:3]
        d2 = dx * dx + dy * dy + dz * dz
        best = d2.min(axis=1)
        # among the points at the best distance, the lowest original index
        tied = np.where(d2 == best[:, None], orig[None, :], np.iinfo(np.int64).max)
        out_i[a:b] = tied.min(axis=1)
        out_d[a:b] = np.sqrt(best)
