"""Compiled loops over the block files' records (numba): the order of ascending runs merged
into one, for `blocks.read_box`, and records packed in a given order, for `blocks.stream_epoch`.

A tile's box is read from block files whose points each lie in file order; the tile needs
them all in file order. A stable argsort of the joined indices and a gather of 29-byte
records took a third of a second a tile epoch; a k-way merge of the runs gives the same
order in a pass over the points, and the plain arrays gathered by it are read nearly in
sequence. Writing the 29-byte records field by field from numpy was the slowest step of
streaming a chunk into blocks; one loop fills each record whole.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def _before(v, r, w, s):
    return v < w or (v == w and r < s)


@njit(nogil=True, cache=True)
def merged_order(values, starts):
    """The order `np.argsort(values, kind="stable")` gives when `values` is made of
    ascending runs values[starts[r]:starts[r + 1]] (a binary heap of the runs' heads; ties
    go to the earlier run, as a stable sort keeps them)."""
    k = starts.shape[0] - 1
    head = np.empty(k, values.dtype)
    run = np.empty(k, np.int64)
    pos = starts[:-1].copy()
    m = 0
    for r in range(k):
        if starts[r] == starts[r + 1]:
            continue
        v = values[starts[r]]
        i = m
        m += 1
        while i > 0:
            p = (i - 1) >> 1
            if not _before(v, r, head[p], run[p]):
                break
            head[i] = head[p]
            run[i] = run[p]
            i = p
        head[i] = v
        run[i] = r
    out = np.empty(values.shape[0], np.int64)
    for o in range(values.shape[0]):
        r = run[0]
        out[o] = pos[r]
        pos[r] += 1
        if pos[r] < starts[r + 1]:
            v = values[pos[r]]
        else:  # the run is used up: its place goes to the heap's last entry
            m -= 1
            if m == 0:
                continue
            v = head[m]
            r = run[m]
        i = 0
        while True:
            c = 2 * i + 1
            if c >= m:
                break
            if c + 1 < m and _before(head[c + 1], run[c + 1], head[c], run[c]):
                c += 1
            if not _before(head[c], run[c], v, r):
                break
            head[i] = head[c]
            run[i] = run[c]
            i = c
        head[i] = v
        run[i] = r
    return out


@njit(nogil=True, cache=True)
def pack_records(rec, order, index, X, Y, Z, classification, building_id):
    """rec[i] = the record of point order[i], from the points' columns."""
    for i in range(order.shape[0]):
        j = order[i]
        r = rec[i]
        r.index = index[j]
        r.X = X[j]
        r.Y = Y[j]
        r.Z = Z[j]
        r.classification = classification[j]
        r.building_id = building_id[j]
