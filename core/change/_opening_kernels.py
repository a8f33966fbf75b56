"""Compiled per-return tests of `quakescan.change.openings` (numba).

`fallen_and_surrounded` reads the k nearest reference returns of each candidate (a kd-tree's
answer: distances, inf where none within reach, and indices) in one pass, where numpy made
six (n, k) and (n, k, 2) arrays: on a destroyed building of a dense drone cloud nearly every
post-event return is a candidate, and those arrays took a quarter of the openings' time. The
arithmetic is numpy's, in its order (a difference, its length as sqrt(dx² + dy²), the unit
vectors summed from the nearest to the farthest), so the answers are the same bits.
`under_a_steep_surface` finds the wall above a flagged return among the returns of its cell and
the eight around it, where two kd-trees listed every pair within the radius first.
`quakescan.change.openings._fallen_reference` and `_on_a_wall_reference` are the numpy versions
(tests compare the two).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..grid.cells import bucket_order

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(**_JIT)
def fallen_and_surrounded(query, reference, dist, idx, radius, see_through, min_returns, max_mean):
    """Per query return (row of `dist`/`idx`): the reference returns within `radius` (one at
    least) all lie more than `see_through` above it, and those above it among all its
    neighbours surround it (at least `min_returns`, the mean of their unit directions at most
    `max_mean` long). Returns (that test, the mean length: nan where the return did not fall)."""
    n, k = dist.shape
    last = reference.shape[0] - 1
    out = np.zeros(n, np.bool_)
    means = np.full(n, np.nan)
    for i in range(n):
        qx, qy, qz = query[i, 0], query[i, 1], query[i, 2]
        lowest = np.inf
        near = False
        for j in range(k):
            if dist[i, j] <= radius:
                near = True
                z = reference[min(idx[i, j], last), 2]
                if z < lowest:
                    lowest = z
        if not (near and qz < lowest - see_through):
            continue
        sx, sy = 0.0, 0.0
        above = 0
        for j in range(k):
            if not math.isfinite(dist[i, j]):
                continue
            r = min(idx[i, j], last)
            if not reference[r, 2] > qz + see_through:
                continue
            above += 1
            dx, dy = reference[r, 0] - qx, reference[r, 1] - qy
            norm = math.sqrt(dx * dx + dy * dy)
            if norm > 0:
                scale = max(norm, 1e-12)
                sx += dx / scale
                sy += dy / scale
        mean = math.sqrt(sx * sx + sy * sy) / max(above, 1)
        means[i] = mean
        out[i] = above >= min_returns and mean <= max_mean
    return out, means


@njit(**_JIT)
def _cell(v, v0, size):
    return int(math.floor((v - v0) / size))


@njit(**_JIT)
def under_a_steep_surface(query, points, radius, low, high, steepness):
    """Per query return: a return of `points` within `radius` in x/y (distance <= radius),
    more than `low` and at most `high` above it, and at least `steepness` times as far up as
    across. The points are bucketed in square cells of at least `radius` (`grid.cells.bucket_order`), so
    a query reads its own cell and the eight around it."""
    n, m = query.shape[0], points.shape[0]
    out = np.zeros(n, np.bool_)
    if n == 0 or m == 0:
        return out
    x0, y0 = points[:, 0].min(), points[:, 1].min()
    w, h = points[:, 0].max() - x0, points[:, 1].max() - y0
    # cells of at least the radius (a neighbour lies in the eight around a query's), and about
    # as many as points: the grid of a 2 km footprint in 0.25 m cells would take 512 MB
    size = max(radius, math.sqrt(w * h / m), max(w, h) / m)
    # one expression for every cell, the points' and the queries': a cell computed two ways
    # may differ by one at its edge, and a neighbour two cells away is not read
    nx = _cell(points[:, 0].max(), x0, size) + 1
    ny = _cell(points[:, 1].max(), y0, size) + 1
    key = np.empty(m, np.int64)
    for p in range(m):
        key[p] = _cell(points[p, 0], x0, size) * ny + _cell(points[p, 1], y0, size)
    order = np.empty(m, np.int64)
    start = bucket_order(key, nx * ny, order)
    r2 = radius * radius
    for i in range(n):
        qx, qy, qz = query[i, 0], query[i, 1], query[i, 2]
        cx, cy = _cell(qx, x0, size), _cell(qy, y0, size)
        hit = False
        for a in range(max(cx - 1, 0), min(cx + 2, nx)):
            for b in range(max(cy - 1, 0), min(cy + 2, ny)):
                c = a * ny + b
                for s in range(start[c], start[c + 1]):
                    p = order[s]
                    dx, dy = qx - points[p, 0], qy - points[p, 1]
                    d2 = dx * dx + dy * dy
                    if d2 > r2:
                        continue
                    dz = points[p, 2] - qz
                    if dz > low and dz <= high and dz >= steepness * math.sqrt(d2):
                        hit = True
                        break
                if hit:
                    break
            if hit:
                break
        out[i] = hit
    return out
