"""Compiled nearest-neighbour search for `quakescan.change.split.nearest_neighbours` (numba).

The post-event points are bucketed in square x/y columns (a counting sort, O(n)), each
column sorted by z. A query looks at its own column and then at rings of columns around
it; in a column it binary-searches its z and walks up and down while the height gap
alone is shorter than the best distance so far. It stops when the best distance is no
longer than the distance to the edge of the searched block, so the answer is exact
(ties: the lower index wins, as in a brute-force argmin). Airborne
clouds are 2.5-D, so columns hold few points and rings rarely grow past one; queries
whose neighbour is farther than a few rings are left to a kd-tree.
`quakescan.change._nn_reference` holds the numpy version of each function (tests compare the two).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(parallel=True, **_JIT)
def bounds_xy(xyz):
    """(min x, min y, max x, max y) of an (n, 3) array, in parallel."""
    n = xyz.shape[0]
    nb = 64
    part = np.empty((nb, 4))
    for b in prange(nb):
        a = b * n // nb
        e = (b + 1) * n // nb
        x0 = np.inf
        y0 = np.inf
        x1 = -np.inf
        y1 = -np.inf
        for i in range(a, e):
            x0 = min(x0, xyz[i, 0])
            y0 = min(y0, xyz[i, 1])
            x1 = max(x1, xyz[i, 0])
            y1 = max(y1, xyz[i, 1])
        part[b, 0] = x0
        part[b, 1] = y0
        part[b, 2] = x1
        part[b, 3] = y1
    out = np.empty(4)
    out[0] = part[:, 0].min()
    out[1] = part[:, 1].min()
    out[2] = part[:, 2].max()
    out[3] = part[:, 3].max()
    return out


@njit(parallel=True, **_JIT)
def column_index(xyz, lo_x, lo_y, cell, nx, ny):
    """Column of every point (clamped into the grid)."""
    n = xyz.shape[0]
    col = np.empty(n, np.int64)
    for i in prange(n):
        ix = int(math.floor((xyz[i, 0] - lo_x) / cell))
        iy = int(math.floor((xyz[i, 1] - lo_y) / cell))
        ix = min(max(ix, 0), nx - 1)
        iy = min(max(iy, 0), ny - 1)
        col[i] = ix * ny + iy
    return col


@njit(**_JIT)
def counting_sort(col, ncol):
    """Order of the points by column (stable) and the start of every column."""
    n = col.shape[0]
    starts = np.zeros(ncol + 1, np.int64)
    for i in range(n):
        starts[col[i] + 1] += 1
    for c in range(ncol):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        c = col[i]
        order[fill[c]] = i
        fill[c] += 1
    return order, starts


@njit(parallel=True, **_JIT)
def sort_columns_by_z(order, starts, xyz):
    """Sort each column's points by z (stable) and gather the sorted coordinates."""
    ncol = starts.shape[0] - 1
    for c in prange(ncol):
        a = starts[c]
        b = starts[c + 1]
        if b - a > 1:
            seg = order[a:b].copy()
            zs = np.empty(b - a)
            for t in range(b - a):
                zs[t] = xyz[seg[t], 2]
            k = np.argsort(zs, kind="mergesort")  # stable: equal heights keep index order
            for t in range(b - a):
                order[a + t] = seg[k[t]]
    n = order.shape[0]
    px = np.empty(n)
    py = np.empty(n)
    pz = np.empty(n)
    for j in prange(n):
        o = order[j]
        px[j] = xyz[o, 0]
        py[j] = xyz[o, 1]
        pz[j] = xyz[o, 2]
    return px, py, pz


@njit(inline="always", **_JIT)
def _walk(qx, qy, qz, j, stop, step, px, py, pz, orig, best_d2, best_i):
    """From sorted position j towards `stop` (exclusive) in direction step (+1 up, -1 down),
    until the height gap alone exceeds the best distance."""
    while j != stop:
        dz = pz[j] - qz
        if dz * dz > best_d2:
            break
        dx = px[j] - qx
        dy = py[j] - qy
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best_d2 or (d2 == best_d2 and orig[j] < orig[best_i]):
            best_d2 = d2
            best_i = j
        j += step
    return best_d2, best_i


@njit(inline="always", **_JIT)
def _scan_column(qx, qy, qz, a, b, px, py, pz, orig, best_d2, best_i):
    """Best (d², index) after looking at the column's points a:b (sorted by z)."""
    lo = a
    hi = b
    while lo < hi:  # first point with z >= qz
        mid = (lo + hi) // 2
        if pz[mid] < qz:
            lo = mid + 1
        else:
            hi = mid
    best_d2, best_i = _walk(qx, qy, qz, lo, b, 1, px, py, pz, orig, best_d2, best_i)
    return _walk(qx, qy, qz, lo - 1, a - 1, -1, px, py, pz, orig, best_d2, best_i)


@njit(parallel=True, **_JIT)
def nearest(q, px, py, pz, orig, starts, lo_x, lo_y, cell, nx, ny, max_ring, out_i, out_d):
    """Nearest of the sorted points (px, py, pz; columns starts) for every query.

    orig[j] is the original index of sorted point j (equal distances: the lower original
    index wins, as in a brute-force argmin); out_i receives original indices, or -1 for a
    query whose nearest point may lie beyond `max_ring` rings of columns (the caller
    answers those with a kd-tree: far neighbours, e.g. a roof point over a collapsed
    building, are what a hierarchical search does better)."""
    n = q.shape[0]
    for i in prange(n):
        x = q[i, 0]
        y = q[i, 1]
        z = q[i, 2]
        fx = (x - lo_x) / cell
        fy = (y - lo_y) / cell
        ix = min(max(int(math.floor(fx)), 0), nx - 1)
        iy = min(max(int(math.floor(fy)), 0), ny - 1)
        best_d2 = np.inf
        best_i = -1
        k = 0
        while True:
            x0 = ix - k
            x1 = ix + k
            y0 = iy - k
            y1 = iy + k
            for cx in range(max(x0, 0), min(x1, nx - 1) + 1):
                on_x_edge = cx == x0 or cx == x1
                step = 1 if on_x_edge else (y1 - y0)
                cy = y0
                while cy <= y1:
                    if 0 <= cy < ny:
                        # the column's nearest x/y distance: skip it when already too far
                        gx = max(lo_x + cx * cell - x, 0.0, x - (lo_x + (cx + 1) * cell))
                        gy = max(lo_y + cy * cell - y, 0.0, y - (lo_y + (cy + 1) * cell))
                        if gx * gx + gy * gy <= best_d2:
                            c = cx * ny + cy
                            best_d2, best_i = _scan_column(x, y, z, starts[c], starts[c + 1], px, py, pz,
                                                           orig, best_d2, best_i)
                    if step == 0:
                        break
                    cy += step
            # distance from the query to the edge of the searched block of columns
            covered = min(x - (lo_x + x0 * cell), lo_x + (x1 + 1) * cell - x,
                          y - (lo_y + y0 * cell), lo_y + (y1 + 1) * cell - y)
            whole = x0 <= 0 and y0 <= 0 and x1 >= nx - 1 and y1 >= ny - 1
            if whole or (best_i >= 0 and covered > 0 and best_d2 <= covered * covered):
                break
            if k >= max_ring:
                best_i = -1
                break
            k += 1
        out_i[i] = orig[best_i] if best_i >= 0 else -1
        out_d[i] = math.sqrt(best_d2)
