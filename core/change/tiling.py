"""Buildings grouped into tiles and points grouped by building: what lets a city-size pair be
described a tile at a time (one process or Dask workers), and points found by box.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..grid.cells import row_bounds


class GridIndex:
    """Points bucketed in square x/y cells: the points of a box without scanning the cloud."""

    def __init__(self, xy: np.ndarray, cell: float):
        self.cell = float(cell)
        if len(xy) == 0:
            self.lo = self.hi = np.zeros(2)
            self.dims = (1, 1)
            self.order = np.zeros(0, np.int64)
            self.starts = np.zeros(2, np.int64)
            return
        from ..grid.cells import bucket_order, column_bounds, grid_keys

        self.lo, self.hi = column_bounds(xy)  # one pass: numpy's min and max read the columns strided, four times
        lo0, lo1 = float(self.lo[0]), float(self.lo[1])
        self.dims = tuple(int(d) for d in np.floor((self.hi - self.lo) / self.cell).astype(np.int64) + 1)
        n_cells = self.dims[0] * self.dims[1]
        # cell keys in a compiled loop: the (n, 2) float temporaries of numpy expressions over
        # a city-size epoch would be several times the index itself
        key = np.empty(len(xy), np.int32 if n_cells < 2 ** 31 else np.int64)
        grid_keys(xy, lo0, lo1, self.cell, self.dims[1], key)
        self.order = np.empty(len(xy), np.int32 if len(xy) < 2 ** 31 else np.int64)  # halves a city's index
        self.starts = bucket_order(key, n_cells, self.order)

    def query(self, xy: np.ndarray, box: np.ndarray) -> np.ndarray:
        """Sorted indices of the points with box[0] <= xy <= box[1] (box: (2, 2) min/max)."""
        i0, j0 = np.floor((box[0] - self.lo) / self.cell).astype(np.int64)
        i1, j1 = np.floor((box[1] - self.lo) / self.cell).astype(np.int64)
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, self.dims[0] - 1), min(j1, self.dims[1] - 1)
        if i0 > i1 or j0 > j1:
            return np.zeros(0, np.int64)
        parts = [self.order[self.starts[i * self.dims[1] + j0]:self.starts[i * self.dims[1] + j1 + 1]]
                 for i in range(i0, i1 + 1)]
        idx = np.concatenate(parts).astype(np.int64)
        p = xy[idx]
        keep = np.all((p >= box[0]) & (p <= box[1]), axis=1)
        return np.sort(idx[keep])


def box_of(xy: np.ndarray, margin: float) -> np.ndarray:
    """(2, 2) [min, max] x/y box of the points `xy`, grown by `margin` on every side."""
    lo, hi = row_bounds(xy)
    return np.array([lo - margin, hi + margin])


def tile_key(lo_xy, hi_xy, tile_m: float) -> tuple[int, int]:
    """The tile of a building: the square of side `tile_m` holding the centre of its
    pre-event points' x/y box. Minimum and maximum are exact in whatever order or chunks the
    points are read (a mean is not), so a streamed, distributed run groups the buildings
    into the same tiles as this process does, and gives the same descriptors."""
    centre = (np.asarray(lo_xy, dtype=np.float64) + np.asarray(hi_xy, dtype=np.float64)) / 2
    return tuple(np.floor(centre / tile_m).astype(np.int64).tolist())


def tile_threads(workers: int, n_tiles: int) -> int:
    """Threads that describe tiles side by side: `workers` (-1: every core) at most one per
    tile, and 1 unless numba's threading layer lets parallel kernels be launched from
    several threads at once (tbb and omp do; workqueue aborts the process)."""
    if n_tiles <= 1:
        return 1
    try:
        import numba

        layer = numba.threading_layer()
    except (ImportError, ValueError):  # ValueError: no parallel kernel has run yet
        return 1
    if layer not in ("tbb", "omp"):
        return 1
    n = numba.config.NUMBA_NUM_THREADS if workers is None or workers < 1 else int(workers)
    return max(1, min(n, n_tiles))


def id_counts(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(ids, return_counts=True), by counting where the IDs span a range no longer
    than the array (building IDs do): no sorted copy of a city-size epoch (5 s and 8 bytes a
    point for 37 M points)."""
    if len(ids) == 0:
        return np.unique(ids, return_counts=True)
    lo, hi = int(ids.min()), int(ids.max())
    if hi - lo > max(len(ids), 1 << 16):
        return np.unique(ids, return_counts=True)
    counts = np.zeros(hi - lo + 1, np.int64)
    step = 1 << 22
    for a in range(0, len(ids), step):
        counts += np.bincount(ids[a:a + step] - lo, minlength=len(counts))
    present = np.flatnonzero(counts)
    return (present + lo).astype(ids.dtype), counts[present]


def grouped_by_id(ids: np.ndarray, uniq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, starts): the point indices grouped by ID (the IDs `uniq`, ascending, as
    np.unique gives them; within an ID in point order, as a stable argsort gives them) and
    where each ID's run starts. A counting sort of the IDs' ranks: a 75 M-point epoch's
    stable argsort took 8 s and its 8-byte index and sorted copy 1.2 GB."""
    from ..grid.cells import bucket_order

    rank = np.empty(len(ids), np.int32 if len(uniq) < 2 ** 31 else np.int64)
    step = 1 << 22
    for a in range(0, len(ids), step):
        rank[a:a + step] = np.searchsorted(uniq, ids[a:a + step])
    order = np.empty(len(ids), np.int32 if len(ids) < 2 ** 31 else np.int64)
    starts = bucket_order(rank, len(uniq), order)
    return order, starts[:-1]


def members_by_id(ids: np.ndarray) -> Callable[[int], np.ndarray]:
    """bid -> indices of its points, ascending (what a stable argsort's run gives)."""
    uniq, counts = id_counts(ids)
    order, starts = grouped_by_id(ids, uniq)

    def members(bid: int) -> np.ndarray:
        i = int(np.searchsorted(uniq, bid))
        if i == len(uniq) or uniq[i] != bid:
            return order[:0]
        return order[starts[i]:starts[i] + counts[i]]
    return members
