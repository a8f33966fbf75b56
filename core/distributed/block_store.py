"""The block files of a streamed epoch: how its points are stored, found and read back.

A block is a square of `block_cells` density cells (1 m, `quakescan.grid.density.DENSITY_CELL_M`)
in the pair's local frame; it holds each point once, so the halo a tile needs is read from the
blocks around it and one tiling serves every halo.

Each task that streams a part of the file (a range of its points) writes one file,
`part<k>.bin`, in which every block's points lie together: a block's points with a building
ID and the rest are two runs (the densities of the surface descriptors read building points
only, half of an epoch or less), and `part<k>.index.npy` says where each run lies. The part
buffers up to SEGMENT_POINTS points, sorts them by block and writes them as one segment, so a
block has one run a segment. The client joins the parts' indexes into `blocks.index.npy`
(`join_part_indexes`), which every reader looks its blocks up in: an epoch streamed in
625 parts (10 B points) is 1,250 files, not one per block, kind and part (25 M), and a tile
reads its blocks' runs from each part's file with one system call per contiguous stretch.

A point is stored as its file's integers (X, Y, Z), its classification, building ID and its
index in the file (`RECORD`, or the narrowest record the file allows: `record_dtype`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..formats.pointcloud import PointCloudError
from ..grid.density import DENSITY_CELL_M

# The stored point: the file's integers, so a float64 coordinate is made once, on reading.
# RECORD is the widest record, for any file; an epoch's blocks store the narrowest its file
# allows (`record_dtype`): 21 bytes where the point count and the building IDs fit in 4 bytes
# each, as in every file QuakeScan writes (uint32 IDs) and every footprint file seen so far.
RECORD = np.dtype([("index", "<i8"), ("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("classification", "u1"),
                   ("building_id", "<i8")])
# Where a folder's blocks say which record they store (written by every streaming part)
RECORD_NAME = "record.json"
# Bumped whenever the block files change: a store tiled by an earlier layout is tiled again
# (2: building points in files of their own; 3: one file a part, its runs in an index;
# 4: the narrowest record the file allows)
LAYOUT = 4


def block_of(xy: np.ndarray, block_cells: int) -> np.ndarray:
    """(n, 2) block indices of local x/y: the density cell (floored exactly as the density is
    counted) divided by the block's cells, so a density cell never straddles two blocks."""
    cells = np.floor(xy / DENSITY_CELL_M).astype(np.int64)
    return cells // int(block_cells)


def block_m(block_cells: int) -> float:
    return float(block_cells) * DENSITY_CELL_M


def blocks_in_box(box: np.ndarray, block_cells: int) -> list[tuple[int, int]]:
    """Every block that can hold a point of the x/y box ((2, 2): min, max; local frame)."""
    a, b = block_of(np.asarray(box, dtype=np.float64), block_cells)
    return [(i, j) for i in range(int(a[0]), int(b[0]) + 1) for j in range(int(a[1]), int(b[1]) + 1)]


# A run's row in an index: its sort key (block, then kind: `run_keys`), the part whose file
# holds it, where it begins (in records) and how many records it has. Stored column by column
# (Fortran order), so the sort keys are one contiguous column that a memory-mapped index is
# searched in without reading the rest.
INDEX_NAME = "blocks.index.npy"


def part_path(folder: Path, part: int | None) -> Path:
    """The file of one streaming part's points (`part` None: an epoch streamed whole, part 0)."""
    return Path(folder) / f"part{int(part or 0)}.bin"


def part_index_path(folder: Path, part: int | None) -> Path:
    return Path(folder) / f"part{int(part or 0)}.index.npy"


def run_keys(bx, by, buildings) -> np.ndarray:
    """The sort key of a block's run: block x, then block y, then kind (1: building points),
    so a block's two runs are neighbours and its building run comes second."""
    bx, by = np.asarray(bx, dtype=np.int64), np.asarray(by, dtype=np.int64)
    return ((bx << 32) + (by + (1 << 31))) * 2 + np.asarray(buildings, dtype=np.int64)


def join_part_indexes(folder: Path, parts: int) -> None:
    """Join the indexes of an epoch streamed in `parts` parts into the epoch's index, sorted
    by run key, part and offset (a block's runs in file order), written atomically."""
    rows = [np.load(part_index_path(folder, p)) for p in range(int(parts))]
    save_index(Path(folder) / INDEX_NAME, np.vstack(rows) if rows else np.zeros((0, 4), np.int64))


def save_index(path: Path, rows: np.ndarray) -> None:
    from ..runtime.atomic import open_replacing

    rows = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))] if len(rows) else rows.reshape(0, 4)
    with open_replacing(path, "wb") as out:
        np.save(out, np.asfortranarray(rows, dtype=np.int64))


def block_runs(folder: Path, keys, buildings_only: bool = False) -> np.ndarray:
    """(r, 3) rows [part, offset, count] of the runs holding the points of blocks `keys`
    (`buildings_only`: their points with a building ID), in the order of their files."""
    path = Path(folder) / INDEX_NAME
    try:
        index = np.load(path, mmap_mode="r")
    except OSError:
        raise FileNotFoundError(f"{path}: no block index (the epoch was not streamed into {folder}, "
                                "or its parts' indexes were not joined: join_part_indexes)") from None
    keys = np.asarray([(int(k[0]), int(k[1])) for k in keys], dtype=np.int64).reshape(-1, 2)
    if not len(keys) or not len(index):
        return np.zeros((0, 3), np.int64)
    column = index[:, 0]
    lo = np.searchsorted(column, run_keys(keys[:, 0], keys[:, 1], 1 if buildings_only else 0), side="left")
    hi = np.searchsorted(column, run_keys(keys[:, 0], keys[:, 1], 1), side="right")
    runs = np.vstack([np.asarray(index[a:b, 1:4]) for a, b in zip(lo.tolist(), hi.tolist()) if b > a]
                     or [np.zeros((0, 3), np.int64)])
    return runs[np.lexsort((runs[:, 1], runs[:, 0]))] if len(runs) else runs


def read_runs(folder: Path, runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(records, starts): the records of `runs` (`block_runs`) one after another, run r in
    records[starts[r]:starts[r + 1]]. Each part's file is opened once and read with one
    system call per stretch of runs that lie end to end in it."""
    runs = np.asarray(runs, dtype=np.int64).reshape(-1, 3)
    starts = np.zeros(len(runs) + 1, np.int64)
    np.cumsum(runs[:, 2], out=starts[1:])
    record = stored_record(folder)
    out = np.empty(int(starts[-1]), record)
    raw = out.view(np.uint8)
    size = record.itemsize
    r = 0
    while r < len(runs):
        part = int(runs[r, 0])
        path = part_path(folder, part)
        fd = os.open(path, os.O_RDONLY)
        try:
            while r < len(runs) and runs[r, 0] == part:
                e = r + 1  # runs that follow on in the file and in `out`: one read
                while e < len(runs) and runs[e, 0] == part and runs[e, 1] == runs[e - 1, 1] + runs[e - 1, 2]:
                    e += 1
                _read_exactly(fd, path, raw[starts[r] * size:starts[e] * size], int(runs[r, 1]) * size)
                r = e
        finally:
            os.close(fd)
    return out, starts


def _read_exactly(fd: int, path: Path, view: np.ndarray, offset: int) -> None:
    done = 0
    while done < len(view):
        got = os.preadv(fd, [view[done:]], offset + done)
        if got <= 0:
            raise PointCloudError(f"{path}: block file ends {len(view) - done} bytes early at byte "
                                  f"{offset + done}; delete the folder and stream the epoch again")
        done += got


def stored_points(folder: Path, keys, buildings_only: bool = False) -> int:
    """How many points the blocks `keys` hold (from the index: no file is read)."""
    return int(block_runs(folder, keys, buildings_only)[:, 2].sum())


def record_dtype(n_points: int, ids) -> np.dtype:
    """The record an epoch of `n_points` is stored in: RECORD's fields, each as narrow as the
    file allows. `ids`: the type of the file's building_id (numpy name or dtype), or the
    footprints' IDs (an array). Writing the blocks is the tiling's cost, and two workers
    writing at once wait on the page cache's writeback: the 2 x 75 M-point pair's blocks are
    3.1 GB of 21-byte records instead of 4.3 GB of 29-byte ones, and its tiling took 5.9 s
    instead of 8.5 on two workers, 13.4 instead of 16.8 on one (medians of 4 and 3 runs in
    turn, 2026-11-28)."""
    index = "<u4" if int(n_points) <= 2 ** 32 else "<i8"  # a point's index is below n_points
    if isinstance(ids, (str, np.dtype, type)):
        t = np.dtype(ids)
        building = ("<u4" if t.kind == "u" else "<i4") if t.kind in "iu" and t.itemsize <= 4 else "<i8"
    else:
        ids = np.asarray(ids)
        fits = not len(ids) or (int(ids.min()) >= -2 ** 31 and int(ids.max()) < 2 ** 31)
        building = "<i4" if fits else "<i8"
    return np.dtype([("index", index), ("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("classification", "u1"),
                     ("building_id", building)])


def stored_record(folder: Path) -> np.dtype:
    """The record the blocks under `folder` store (`record_dtype`; RECORD where no part says)."""
    try:
        descr = json.loads((Path(folder) / RECORD_NAME).read_text())
    except (OSError, ValueError):
        return RECORD
    return np.dtype([(str(name), str(t)) for name, t in descr])


def write_record(folder: Path, dtype: np.dtype, part: int | None) -> None:
    """`RECORD_NAME` under `folder`. Every part of an epoch, on any worker, writes the same
    text: each under a temporary name of its own, renamed into place (a reader sees one
    whole file or none)."""
    from ..runtime.atomic import write_text

    write_text(Path(folder) / RECORD_NAME, json.dumps([[name, dtype[name].str] for name in dtype.names]))


def epoch_json(folder: Path) -> dict:
    try:
        return json.loads((Path(folder) / "epoch.json").read_text())
    except (OSError, ValueError):
        return {}


def write_manifest(path: Path, d: dict) -> None:
    from ..runtime.atomic import write_text

    write_text(path, json.dumps(d))


def read_manifest(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def save_arrays(path: Path, arrays: dict) -> None:
    """The stats' arrays next to the manifest, written under a temporary name."""
    from ..runtime.atomic import open_replacing

    with open_replacing(path, "wb") as f:
        np.savez(f, **arrays)


__all__ = ["INDEX_NAME", "LAYOUT", "RECORD", "RECORD_NAME", "block_m", "block_of", "block_runs", "blocks_in_box",
           "epoch_json", "join_part_indexes", "part_index_path", "part_path", "read_manifest", "read_runs",
           "record_dtype", "run_keys", "save_arrays", "save_index", "stored_points", "stored_record",
           "write_manifest", "write_record"]
