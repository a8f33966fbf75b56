"""Compiled loops over the stored blocks' records (numba): the records of a box kept as they
are read and the order of ascending runs merged into one, for `reading.read_box`, and records
packed in a given order, for `streaming.stream_epoch`.

A tile's box is read from block runs whose points each lie in file order; the tile needs
them all in file order. A stable argsort of the joined indices and a gather of (then 29-byte)
records took a third of a second a tile epoch; a k-way merge of the runs gives the same
order in a pass over the points, and the plain arrays gathered by it are read nearly in
sequence. Streaming a chunk, numpy made its coordinates, bounds, blocks and block codes
in a dozen passes and (n, 2) temporaries; `chunk_frame` and `block_codes` make them in two.
A block's roof cells need each point's density cell and height only; made from the records
in one loop, beside numpy's coordinates, floors and strided minima (half the densities' time).
Cutting each file to the box with numpy (coordinates of every record, a mask,
four gathers) took more than the merge; one loop makes a record's coordinates and keeps it
or not. Writing the 29-byte records field by field from numpy was the slowest step of
streaming a chunk into blocks; one loop fills each record whole.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def keep_in_box(rec, scales, shifts, box, index, classification, building_id, xyz, n):
    """Append the records whose local x/y lie in `box` ((2, 2): min, max, edges included) to
    the outputs from row `n`; return the rows filled. A coordinate is made as
    `streaming.EpochFile.local_xyz` makes it: the integer as float64 × scale + shift (offset −
    origin), two roundings, so it is equal to the last bit."""
    x0, y0, x1, y1 = box[0, 0], box[0, 1], box[1, 0], box[1, 1]
    for i in range(rec.shape[0]):
        r = rec[i]
        x = np.float64(r.X) * scales[0] + shifts[0]
        if x < x0 or x > x1:
            continue
        y = np.float64(r.Y) * scales[1] + shifts[1]
        if y < y0 or y > y1:
            continue
        xyz[n, 0] = x
        xyz[n, 1] = y
        xyz[n, 2] = np.float64(r.Z) * scales[2] + shifts[2]
        index[n] = r.index
        classification[n] = r.classification
        building_id[n] = r.building_id
        n += 1
    return n


@njit(nogil=True, cache=True)
def gather_box(order, index, classification, building_id, xyz, out, out_xyz):
    """out[i] (BOX_FIELDS record) and out_xyz[i] = point order[i]: one pass, where numpy's
    four gathers and a structured assignment each walked the points again."""
    for i in range(order.shape[0]):
        j = order[i]
        r = out[i]
        r.index = index[j]
        r.classification = classification[j]
        r.building_id = building_id[j]
        out_xyz[i, 0] = xyz[j, 0]
        out_xyz[i, 1] = xyz[j, 1]
        out_xyz[i, 2] = xyz[j, 2]


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


@njit(nogil=True, cache=True)
def chunk_frame(X, Y, Z, scales, shifts, cell, block_cells, xyz, keys):
    """A streamed chunk's local coordinates, blocks and bounds in one pass: xyz[i] as
    `streaming.EpochFile.local_xyz` makes it (integer as float64 × scale + shift, two roundings:
    the same bits), keys[i] as `block_store.block_of` (the cell floor(x / cell) floor-divided by
    the block's cells). Returns the (3,) minimum and maximum of xyz and the (2,) minimum and
    maximum block."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    klo = np.full(2, np.iinfo(np.int64).max)
    khi = np.full(2, np.iinfo(np.int64).min)
    for i in range(X.shape[0]):
        xyz[i, 0] = np.float64(X[i]) * scales[0] + shifts[0]
        xyz[i, 1] = np.float64(Y[i]) * scales[1] + shifts[1]
        xyz[i, 2] = np.float64(Z[i]) * scales[2] + shifts[2]
        for k in range(3):
            v = xyz[i, k]
            if v < lo[k]:
                lo[k] = v
            if v > hi[k]:
                hi[k] = v
        for k in range(2):
            b = np.int64(math.floor(xyz[i, k] / cell)) // block_cells
            keys[i, k] = b
            if b < klo[k]:
                klo[k] = b
            if b > khi[k]:
                khi[k] = b
    return lo, hi, klo, khi


@njit(nogil=True, cache=True)
def block_codes(keys, klo, span, building_id):
    """2 × the block's code ((bx − klo) × span + (by − klo)) + 1 for a building point: one
    sort by the codes orders a chunk by block, and each block's other points before its
    building points."""
    out = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        flat = (keys[i, 0] - klo[0]) * span + (keys[i, 1] - klo[1])
        out[i] = 2 * flat + (1 if building_id[i] > 0 else 0)
    return out


@njit(nogil=True, cache=True)
def group_boxes(xyz, order, starts, ends):
    """(g, 2) x/y minimum and maximum of each group's points order[starts[g]:ends[g]]."""
    g = starts.shape[0]
    lo = np.full((g, 2), np.inf)
    hi = np.full((g, 2), -np.inf)
    for k in range(g):
        for t in range(starts[k], ends[k]):
            j = order[t]
            for c in range(2):
                v = xyz[j, c]
                if v < lo[k, c]:
                    lo[k, c] = v
                if v > hi[k, c]:
                    hi[k, c] = v
    return lo, hi


@njit(nogil=True, cache=True)
def cells_and_heights(rec, scales, shifts, cell, ci, cj, z, n, span):
    """Append each record's density cell (floor(x / cell), floor(y / cell)) and height, its
    coordinates made as `streaming.EpochFile.local_xyz` makes them, to the outputs from row
    `n`; widen `span` ((4,) int64: min i, min j, max i, max j) to the cells. Returns the
    rows filled."""
    for t in range(rec.shape[0]):
        r = rec[t]
        i = np.int64(math.floor((np.float64(r.X) * scales[0] + shifts[0]) / cell))
        j = np.int64(math.floor((np.float64(r.Y) * scales[1] + shifts[1]) / cell))
        ci[n] = i
        cj[n] = j
        z[n] = np.float64(r.Z) * scales[2] + shifts[2]
        if i < span[0]:
            span[0] = i
        if j < span[1]:
            span[1] = j
        if i > span[2]:
            span[2] = i
        if j > span[3]:
            span[3] = j
        n += 1
    return n
