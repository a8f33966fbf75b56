"""An epoch streamed from its LAS/LAZ file into square blocks on disk, and read back by box.

The tiling step of a distributed classification. The file is read in chunks (laspy's chunk
iterator: memory holds one chunk, never the cloud), each point gets its building ID (the
file's `building_id` or the footprint that holds it), and is appended to the file of its
block: a square of `block_cells` density cells (1 m, `quakescan.grid.density.DENSITY_CELL_M`)
in the pair's local frame. A block holds each point once; the halo a tile needs is read
from the blocks around it when the tile is described, so one tiling serves every halo.

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
index in the file. Reading a box turns the integers into the same float64 coordinates
`quakescan.formats.pointcloud.read_epoch` makes (integers × scale + (offset − origin), one
operation per element) and sorts the points by their index: a worker sees exactly the
values, in exactly the order, that a single process sees, so its descriptors are equal to
the last bit.

While streaming, the client keeps what needs the whole epoch and is small: per building its
point count and x/y box, the epoch's bounds, the stable points the registration check
samples (`quakescan.change.align.sample_mask`), every k-th point for the map, and the convex
hull of each building's pre-event points (the outline of a building without a footprint).
"""
from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..grid.density import DENSITY_CELL_M
from ..formats.pointcloud import PointCloudError, noise_mask, read_point_range

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
# Points per chunk read from a LAS/LAZ file. Every array of a chunk this size (the LAS
# records, ~19 MB; coordinates, 12 MB) stays under glibc's 32 MiB mmap ceiling, so its memory
# is reused chunk after chunk; at 2 M points each array was mapped anew and its pages faulted
# in again (150 k faults a 16 M-point part): streaming 16 M points took 3.2-4.1 s, at 500 k
# 2.1-2.3 s (one thread, side by side), 75 M points an epoch on 2 workers 13.9-14.2 s -> 11.4-12.8 s.
CHUNK_POINTS = 500_000
# Points a streaming part buffers before it writes them, sorted by block, as a segment of its
# file (~230 MB of records): a block has one run a segment, and a part (at most
# classify.PART_POINTS, 16 M) at most two segments.
SEGMENT_POINTS = 8_000_000
MAP_POINTS = 200_000  # points of the pre-event epoch drawn under the damage map (as classify does)


@dataclass
class EpochFile:
    """What an epoch's header says: enough to make its coordinates without reading points."""

    path: str
    n: int
    scales: list
    offsets: list
    mins: list
    maxs: list
    crs: str | None
    dimensions: list
    copc: bool = False  # a COPC file: read back by bounds from the file itself, no block files
    id_dtype: str | None = None  # numpy's name of the file's building_id type, if it has one

    def local_xyz(self, X, Y, Z, origin) -> np.ndarray:
        """float64 coordinates relative to `origin`, computed as `read_epoch` does."""
        scales, shifts = self.frame(origin)
        xyz = np.empty((len(X), 3))
        for k, ints in enumerate((X, Y, Z)):
            xyz[:, k] = np.asarray(ints, dtype=np.float64) * scales[k] + shifts[k]
        return xyz

    def frame(self, origin) -> tuple[np.ndarray, np.ndarray]:
        """(scales, shifts): a local coordinate is the integer as float64 × scale + shift
        (offset − origin), two roundings; the compiled record loops take these."""
        origin = np.asarray(origin, dtype=np.float64)
        return (np.asarray(self.scales, dtype=np.float64),
                np.array([self.offsets[k] - origin[k] for k in range(3)], dtype=np.float64))

    def to_json(self) -> dict:
        return dict(self.__dict__)


def open_epoch_file(path) -> EpochFile:
    """The header of a LAS/LAZ file, checked as `read_epoch` checks the whole file."""
    import laspy

    from ..formats.copc import is_copc
    from ..formats.pointcloud import _crs_of, check_point_cloud_path

    path = check_point_cloud_path(path)
    try:
        with laspy.open(path) as f:
            h = f.header
            names = list(h.point_format.dimension_names)
            ids = (np.dtype(h.point_format.dimension_by_name("building_id").dtype).str
                   if "building_id" in names else None)
            return EpochFile(str(path), int(h.point_count), [float(v) for v in h.scales],
                             [float(v) for v in h.offsets], [float(v) for v in h.mins], [float(v) for v in h.maxs],
                             _crs_of(h, path), names, is_copc(h), ids)
    except PointCloudError:
        raise
    except Exception as e:
        raise PointCloudError(f"{path}: cannot read as LAS/LAZ ({e})") from None


def default_origin(f: EpochFile) -> np.ndarray:
    """The local frame `read_epoch` chooses for a file read first: its offset, or its
    minimum corner (floored) when the offset is zero."""
    origin = np.asarray(f.offsets, dtype=np.float64)
    if not np.any(origin) and f.n:
        origin = np.floor(np.asarray(f.mins, dtype=np.float64))
    return origin


@dataclass
class EpochStats:
    """What the client keeps of a streamed epoch."""

    n: int = 0
    counts: dict = field(default_factory=dict)  # building ID -> points
    lo: dict = field(default_factory=dict)  # building ID -> (x, y) minimum, local frame
    hi: dict = field(default_factory=dict)
    bounds: list | None = None  # [[x, y, z] min, [x, y, z] max] of every point, local
    blocks: list = field(default_factory=list)  # [bx, by] of the blocks holding points
    stable_sample: np.ndarray | None = None  # (m, 3) local: the registration check's points
    map_xy: np.ndarray | None = None  # (k, 2) local
    hulls: dict = field(default_factory=dict)  # building ID -> (h, 2) hull vertices, world x/y
    noise: int = 0  # ASPRS noise returns, in no building

    def to_json(self) -> dict:
        return {"n": self.n, "counts": {str(k): v for k, v in self.counts.items()},
                "lo": {str(k): list(v) for k, v in self.lo.items()},
                "hi": {str(k): list(v) for k, v in self.hi.items()},
                "bounds": self.bounds, "blocks": self.blocks, "noise": self.noise}

    @classmethod
    def from_json(cls, d: dict, arrays: dict) -> EpochStats:
        return cls(int(d["n"]), {int(k): int(v) for k, v in d["counts"].items()},
                   {int(k): tuple(v) for k, v in d["lo"].items()}, {int(k): tuple(v) for k, v in d["hi"].items()},
                   d["bounds"], [list(b) for b in d["blocks"]], arrays.get("stable_sample"), arrays.get("map_xy"),
                   {int(k[5:]): v for k, v in arrays.items() if k.startswith("hull_")}, int(d.get("noise", 0)))


def block_of(xy: np.ndarray, block_cells: int) -> np.ndarray:
    """(n, 2) block indices of local x/y: the density cell (floored exactly as the density is
    counted) divided by the block's cells, so a density cell never straddles two blocks."""
    cells = np.floor(xy / DENSITY_CELL_M).astype(np.int64)
    return cells // int(block_cells)


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
    _save_index(Path(folder) / INDEX_NAME, np.vstack(rows) if rows else np.zeros((0, 4), np.int64))


def _save_index(path: Path, rows: np.ndarray) -> None:
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


class _PartFile:
    """A streaming part's file: the chunks' points, sorted by block and kind, buffered up to
    `segment_points` and written as one segment (each block's runs of every buffered chunk
    one after another, in the chunks' order, so a run's points stay in file order)."""

    def __init__(self, out, part: int | None, segment_points: int):
        self.out, self.part, self.segment_points = out, int(part or 0), int(segment_points)
        self.chunks: list = []  # (records in run order, run keys, run starts, run ends)
        self.buffered = self.written = 0
        self.rows: list = []

    def add(self, rec: np.ndarray, keys: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> None:
        self.chunks.append((rec, keys, starts, ends))
        self.buffered += len(rec)
        if self.buffered >= self.segment_points:
            self.flush()

    def flush(self) -> None:
        if not self.chunks:
            return
        keys = np.concatenate([c[1] for c in self.chunks])
        which = np.concatenate([np.full(len(c[1]), i) for i, c in enumerate(self.chunks)])
        starts = np.concatenate([c[2] for c in self.chunks])
        ends = np.concatenate([c[3] for c in self.chunks])
        order = np.lexsort((which, keys))
        keys, which, starts, ends = keys[order], which[order], starts[order], ends[order]
        first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        counts = np.add.reduceat(ends - starts, first) if len(first) else np.zeros(0, np.int64)
        offsets = self.written + np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        for c, s, t in zip(which.tolist(), starts.tolist(), ends.tolist()):
            self.out.write(self.chunks[c][0][s:t].view(np.uint8))
        self.rows.append(np.column_stack([keys[first], np.full(len(first), self.part), offsets, counts]))
        self.written += int(counts.sum())
        self.chunks, self.buffered = [], 0

    def index(self) -> np.ndarray:
        self.flush()
        return np.vstack(self.rows).astype(np.int64) if self.rows else np.zeros((0, 4), np.int64)


class _Hulls:
    """Each building's hull vertices in world x/y, grown chunk by chunk: the hull of a union
    is the hull of the parts' hull vertices. shapely (GEOS) makes them, from world
    coordinates made as `building_outlines` makes them, so the outline is the one a single
    process draws from every point."""

    def __init__(self, origin):
        self.origin = np.asarray(origin, dtype=np.float64)[:2]
        self.vertices: dict[int, np.ndarray] = {}

    def add(self, groups: "_Groups", xy: np.ndarray) -> None:
        import shapely

        from ..results.outlines import hull_candidates

        order = groups.order
        for b, s, t in zip(groups.ids.tolist(), groups.starts.tolist(), groups.ends.tolist()):
            if b <= 0:
                continue
            world = xy[order[s:t]] + self.origin
            if b in self.vertices:
                world = np.vstack([self.vertices[b], world])
            hull = shapely.convex_hull(shapely.multipoints(hull_candidates(world)))
            self.vertices[b] = shapely.get_coordinates(hull)  # a polygon's ring, a line or a point


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


def _write_record(folder: Path, dtype: np.dtype, part: int | None) -> None:
    """`RECORD_NAME` under `folder`. Every part of an epoch, on any worker, writes the same
    text: each under a temporary name of its own, renamed into place (a reader sees one
    whole file or none)."""
    from ..runtime.atomic import write_text

    write_text(Path(folder) / RECORD_NAME, json.dumps([[name, dtype[name].str] for name in dtype.names]))


def stream_epoch(f: EpochFile, origin: np.ndarray, folder: Path, *, block_cells: int, footprints=None,
                 with_hulls: bool = False, sample: tuple | None = None, map_step: int | None = None,
                 chunk_points: int = CHUNK_POINTS, on_chunk=None, part: int | None = None, start: int = 0,
                 stop: int | None = None, segment_points: int = SEGMENT_POINTS,
                 drop_read_pages: bool = False) -> EpochStats:
    """Write the epoch's points into block runs under `folder` and return its EpochStats.

    `footprints`: give building IDs by footprint (else the file's `building_id`);
    `sample`: (n_total, max_points) of the registration check's sample (`sample_mask`);
    `map_step`: keep every k-th point for the map; `with_hulls`: hull every building.
    `part`, `start`, `stop`: stream only the file's points start..stop into the file of that
    part (`part_path`) and its index, for one of several tasks streaming an epoch
    (`merge_stats` joins their stats into the whole epoch's, `join_part_indexes` their
    indexes); without `part`, the epoch's index is written too.
    `segment_points`: points buffered before they are written sorted by block.
    `drop_read_pages`: tell the kernel to drop the file's pages once streamed
    (`page_cache_cannot_hold`; an uncompressed file's point bytes only)."""
    import laspy

    from ..change.align import sample_mask, stable_mask
    from ..runtime.atomic import open_replacing
    from ._record_kernels import block_codes, chunk_frame

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stop = f.n if stop is None else min(int(stop), f.n)
    stats = EpochStats(n=0)
    scales, shifts = f.frame(origin)
    hulls = _Hulls(origin) if with_hulls else None
    lo_all, hi_all = np.full(3, np.inf), np.full(3, -np.inf)
    samples, maps, blocks = [], [], set()
    if footprints is None and "building_id" not in f.dimensions:
        raise PointCloudError(f"{f.path}: no building_id dimension; give building footprints "
                              "(--footprints F.geojson in the clouds' CRS)")
    try:
        source = open(f.path, "rb")
    except OSError as e:
        raise PointCloudError(f"{f.path}: cannot read as LAS/LAZ ({e})") from None
    try:
        reader = laspy.open(source, closefd=True)
    except Exception as e:
        source.close()
        raise PointCloudError(f"{f.path}: cannot read as LAS/LAZ ({e})") from None
    dropped = _ReadPages(source, reader.header) if drop_read_pages else None
    record = record_dtype(f.n, footprints.ids if footprints is not None else f.id_dtype or RECORD["building_id"])
    # a COPC epoch is read back by bounds from the file itself (`read_box`): no block files
    out = contextlib.nullcontext() if f.copc else open_replacing(part_path(folder, part), "wb")
    with reader, out as stream:
        written = None if f.copc else _PartFile(stream, part, segment_points)
        first = start
        # a COPC epoch is streamed for its summaries only: x, y, z, class and building IDs
        for chunk in read_point_range(reader, start, stop, chunk_points, geometry_only=f.copc):
            X, Y, Z = (chunk.array[c] for c in "XYZ")
            n = len(X)
            xyz, keys = np.empty((n, 3)), np.empty((n, 2), np.int64)
            lo, hi, klo, khi = chunk_frame(X, Y, Z, scales, shifts, DENSITY_CELL_M, int(block_cells), xyz, keys)
            lo_all, hi_all = np.minimum(lo_all, lo), np.maximum(hi_all, hi)
            cls = np.asarray(chunk.classification, dtype=np.uint8)
            if footprints is not None:
                from ..formats.footprints import assign_buildings

                ids = assign_buildings(xyz[:, 0] + origin[0], xyz[:, 1] + origin[1], footprints)
            else:
                from ..formats.pointcloud import checked_building_ids

                ids = np.asarray(checked_building_ids(chunk["building_id"], f.path), dtype=np.int64)
            noise = noise_mask(cls)
            if noise.any():  # in no building, as `classification.load_pair` sets them
                ids[noise] = 0
                stats.noise += int(noise.sum())
            groups = _Groups.of(ids)
            _add_building_stats(stats, groups, xyz)
            if hulls is not None:
                hulls.add(groups, xyz[:, :2])
            if sample is not None:
                # the hash first: it keeps a few hundred thousand of an epoch's points
                keep = sample_mask(range(start, start + n), *sample)
                keep[keep] = stable_mask(cls[keep], ids[keep])
                samples.append(xyz[keep])
            if map_step:
                maps.append(xyz[(start + np.arange(n)) % map_step == 0, :2])
            if f.copc:
                blocks.update(_unique_keys(keys))
            elif n:
                codes = block_codes(keys, klo, int(khi[1] - klo[1]) + 1, ids)
                written.add(*_sorted_runs(keys, codes, {"index": np.arange(start, start + n, dtype=record["index"]),
                                                        "X": X, "Y": Y, "Z": Z, "classification": cls,
                                                        "building_id": ids}, blocks, record))
            if dropped is not None:
                dropped.drop(start, n)
            start += n
            if on_chunk:
                on_chunk(start - first, stop - first)
        rows = None if f.copc else written.index()
    if rows is not None:
        # written after the part's file is complete: an index never points past its file
        _write_record(folder, record, part)
        if part is None:
            _save_index(folder / INDEX_NAME, rows)
        else:
            _save_index(part_index_path(folder, part), rows)
    stats.n = start - first
    stats.bounds = [lo_all.tolist(), hi_all.tolist()] if start > first else None
    stats.blocks = sorted([list(b) for b in blocks])
    stats.stable_sample = np.vstack(samples) if samples else np.zeros((0, 3))
    stats.map_xy = np.vstack(maps) if maps else np.zeros((0, 2))
    stats.hulls = hulls.vertices if hulls is not None else {}
    return stats


# The page cache holds the pair's files through a run when they take at most this share of the
# machine's memory: the blocks made from them (0.6 of their bytes) need the rest.
PAGE_CACHE_SHARE = 0.5


def page_cache_cannot_hold(pair_bytes: int | None, memory_bytes: int | None = None) -> bool:
    """True when the pair's files (`pair_bytes` together) are too large for this machine's
    page cache to keep through a run (more than `PAGE_CACHE_SHARE` of `memory_bytes`, this
    machine's memory when not given). Reading such a file fills the cache, and every page
    read then has to evict another: the kernel's reclaim took as much CPU as the streaming
    (two parts of 15 M points of the 2 x 262 M pair side by side, the cache full: 2.1-2.4 s
    each, 1.0-1.1 s of it in the kernel; 1.5 s, 0.2 s in the kernel, with the streamed pages
    dropped; 2026-11-29). The streamed pages are then dropped: no later step reads the file
    soon enough to find them, and the blocks the tiles read back keep their place."""
    if not pair_bytes:
        return False
    if memory_bytes is None:
        try:
            memory_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (AttributeError, ValueError, OSError):  # a system that does not say
            return False
    return int(pair_bytes) > PAGE_CACHE_SHARE * int(memory_bytes)


class _ReadPages:
    """Drops an uncompressed LAS file's pages from the page cache as its points are streamed
    (posix_fadvise DONTNEED of their byte range). A no-op where the system has no such call,
    and for a compressed file, whose points' bytes are not a range of their index."""

    def __init__(self, source, header):
        self.fd = source.fileno()
        self.size = int(header.point_format.size)
        self.offset = int(header.offset_to_point_data)
        self.usable = hasattr(os, "POSIX_FADV_DONTNEED") and not header.are_points_compressed

    def drop(self, start: int, n: int) -> None:
        if self.usable and n:
            os.posix_fadvise(self.fd, self.offset + int(start) * self.size, int(n) * self.size,
                             os.POSIX_FADV_DONTNEED)


def _unique_keys(keys: np.ndarray) -> list[tuple[int, int]]:
    """The distinct (bx, by) rows of `keys` (a flat code each: np.unique by rows sorts 25x slower)."""
    if not len(keys):
        return []
    lo = keys.min(axis=0)
    span = int(keys[:, 1].max() - lo[1]) + 1
    codes = np.unique((keys[:, 0] - lo[0]) * span + (keys[:, 1] - lo[1]))
    return [(int(c // span + lo[0]), int(c % span + lo[1])) for c in codes]


@dataclass
class _Groups:
    """A chunk's points grouped by building ID: the IDs (ascending), the point indices in ID
    then file order (a counting sort: `quakescan.change.tiling.grouped_by_id`) and each
    ID's run."""

    ids: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    ends: np.ndarray

    @classmethod
    def of(cls, ids: np.ndarray) -> "_Groups":
        from ..change.tiling import grouped_by_id, id_counts

        u, counts = id_counts(ids)
        order, starts = grouped_by_id(ids, u)
        return cls(u, order, starts, starts + counts)


def _add_building_stats(stats: EpochStats, groups: _Groups, xyz: np.ndarray) -> None:
    if not len(groups.ids):
        return
    from ._record_kernels import group_boxes

    lo, hi = group_boxes(xyz, groups.order, groups.starts, groups.ends)
    counts = groups.ends - groups.starts
    for b, c, a, z in zip(groups.ids.tolist(), counts.tolist(), lo.tolist(), hi.tolist()):
        if b <= 0:
            continue
        if b in stats.counts:
            stats.counts[b] += c
            pa, pz = stats.lo[b], stats.hi[b]
            stats.lo[b] = (min(pa[0], a[0]), min(pa[1], a[1]))
            stats.hi[b] = (max(pz[0], z[0]), max(pz[1], z[1]))
        else:
            stats.counts[b], stats.lo[b], stats.hi[b] = c, tuple(a), tuple(z)


def _sorted_runs(keys: np.ndarray, codes: np.ndarray, columns: dict, seen: set, record: np.dtype = RECORD):
    """The chunk's points (`columns`: RECORD's fields as arrays; `keys`: their blocks;
    `codes`: `_record_kernels.block_codes`) as `record`s sorted by block and kind, with each
    run's key (`run_keys`), start and end. The records are packed in block order (one
    counting sort, one compiled loop: gathering whole records was the stream's slowest
    step)."""
    from ..grid.cells import stable_order
    from ._record_kernels import pack_records

    n = len(keys)
    # one stable sort by (block, building or not): a run's points stay in file order
    order = stable_order(codes)
    rec = np.empty(n, record)
    pack_records(rec, order, *(np.asarray(columns[name], record[name]) for name in record.names))  # views too
    codes = codes[order]
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    ends = np.append(starts[1:], n)
    heads = keys[order[starts]]
    seen.update(zip(heads[:, 0].tolist(), heads[:, 1].tolist()))
    return rec, run_keys(heads[:, 0], heads[:, 1], codes[starts] % 2), starts, ends


def merge_stats(parts: list[EpochStats]) -> EpochStats:
    """The stats of an epoch streamed in parts (in the file's order), as streaming it whole
    gives them: counts added, boxes and bounds joined, samples and map points in file order,
    each building's hull made from its parts' hull vertices (the hull of a union is the hull
    of the parts' hulls, as chunks are joined while streaming)."""
    out = EpochStats(n=0)
    hulls: dict[int, list] = {}
    lo_all, hi_all = np.full(3, np.inf), np.full(3, -np.inf)
    blocks = set()
    for s in parts:
        out.n += s.n
        out.noise += s.noise
        for b, c in s.counts.items():
            if b in out.counts:
                out.counts[b] += c
                a, z = out.lo[b], out.hi[b]
                out.lo[b] = (min(a[0], s.lo[b][0]), min(a[1], s.lo[b][1]))
                out.hi[b] = (max(z[0], s.hi[b][0]), max(z[1], s.hi[b][1]))
            else:
                out.counts[b], out.lo[b], out.hi[b] = c, tuple(s.lo[b]), tuple(s.hi[b])
        if s.bounds:
            lo_all = np.minimum(lo_all, s.bounds[0])
            hi_all = np.maximum(hi_all, s.bounds[1])
        blocks.update(tuple(b) for b in s.blocks)
        for b, v in s.hulls.items():
            hulls.setdefault(b, []).append(np.asarray(v))
    out.bounds = [lo_all.tolist(), hi_all.tolist()] if out.n else None
    out.blocks = sorted([list(b) for b in blocks])
    out.stable_sample = np.vstack([s.stable_sample for s in parts]) if parts else np.zeros((0, 3))
    out.map_xy = np.vstack([s.map_xy for s in parts]) if parts else np.zeros((0, 2))
    if hulls:
        import shapely

        out.hulls = {b: shapely.get_coordinates(shapely.convex_hull(shapely.multipoints(np.vstack(v))))
                     for b, v in hulls.items()}
    return out


def blocks_in_box(box: np.ndarray, block_cells: int) -> list[tuple[int, int]]:
    """Every block that can hold a point of the x/y box ((2, 2): min, max; local frame)."""
    a, b = block_of(np.asarray(box, dtype=np.float64), block_cells)
    return [(i, j) for i in range(int(a[0]), int(b[0]) + 1) for j in range(int(a[1]), int(b[1]) + 1)]


def read_records(folder: Path, keys, buildings_only: bool = False, in_file_order: bool = True) -> np.ndarray:
    """The stored points of the given blocks (`buildings_only`: those with a building ID), in
    file order (their `index` ascending; `in_file_order=False`: in no particular order, for
    what does not depend on it, as the densities: a sort of every point less)."""
    epoch = _epoch_json(folder)
    if epoch.get("file", {}).get("copc"):
        return _copc_block_records(Path(folder), epoch, keys, buildings_only)
    rec, _ = read_runs(folder, block_runs(folder, keys, buildings_only))
    return rec[np.argsort(rec["index"], kind="stable")] if in_file_order and len(rec) else rec


# what a tile reads of its points besides the coordinates
BOX_FIELDS = np.dtype([("index", "<i8"), ("classification", "u1"), ("building_id", "<i8")])


def read_box(folder: Path, f: EpochFile, origin, box, block_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """(BOX_FIELDS records, local float64 coordinates) of the stored points inside the x/y
    `box` ((2, 2): min, max; local frame, edges included), in file order: the blocks the box
    touches, each run cut to the box (a tile's box covers about half of the blocks it
    touches), the coordinates made once. Each run's points lie in file order: merging the
    runs (`_record_kernels.merged_order`) puts them in file order."""
    from ._record_kernels import gather_box, keep_in_box, merged_order

    box = np.asarray(box, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if f.copc:
        rec, xyz = _copc_box(Path(folder), f, origin, box)
        return _box_fields(rec["index"], rec["classification"], rec["building_id"]), xyz
    records, runs = read_runs(folder, block_runs(folder, blocks_in_box(box, block_cells)))
    capacity = len(records)
    index, cls = np.empty(capacity, np.int64), np.empty(capacity, np.uint8)
    bid, xyz = np.empty(capacity, np.int64), np.empty((capacity, 3))
    scales, shifts = f.frame(origin)
    starts = [0]
    for a, b in zip(runs[:-1].tolist(), runs[1:].tolist()):
        starts.append(keep_in_box(records[a:b], scales, shifts, box, index, cls, bid, xyz, starts[-1]))
    n = starts[-1]
    order = merged_order(index[:n], np.asarray(starts, dtype=np.int64))
    out, out_xyz = np.empty(n, BOX_FIELDS), np.empty((n, 3))
    gather_box(order, index, cls, bid, xyz, out, out_xyz)
    return out, out_xyz


def _box_fields(index, classification, building_id) -> np.ndarray:
    out = np.empty(len(index), BOX_FIELDS)
    out["index"], out["classification"], out["building_id"] = index, classification, building_id
    return out


def _epoch_json(folder: Path) -> dict:
    try:
        return json.loads((Path(folder) / "epoch.json").read_text())
    except (OSError, ValueError):
        return {}


def _copc_box(folder: Path, f: EpochFile, origin: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`read_box` of a COPC epoch: the nodes the box overlaps, decompressed from the file, kept
    to the box as the block files are (local coordinates, edges included), in file order."""
    from ..formats.copc import copc_index

    margin = np.array([[-1.0], [1.0]])  # nodes chosen in world coordinates, points kept in local ones
    index = copc_index(f.path)
    # a record keeps x, y, z, class and building ID: the other fields are not decompressed
    packed, where = index.points_in_nodes(index.nodes_in_box(box + origin[:2] + margin), fields="geometry")
    xyz = f.local_xyz(packed["X"], packed["Y"], packed["Z"], origin)
    inside = np.all((xyz[:, :2] >= box[0]) & (xyz[:, :2] <= box[1]), axis=1)
    return _copc_records(folder, f, origin, packed[inside], where[inside], xyz[inside]), xyz[inside]


def _copc_block_records(folder: Path, epoch: dict, keys, buildings_only: bool) -> np.ndarray:
    """`read_records` of a COPC epoch: the points of the blocks `keys`, read by their box."""
    keys = [(int(k[0]), int(k[1])) for k in keys]
    if not keys:
        return np.zeros(0, RECORD)
    f = EpochFile(**epoch["file"])
    origin = np.asarray(epoch["origin"], dtype=np.float64)
    side = float(epoch.get("block_cells", 0)) * DENSITY_CELL_M
    k = np.asarray(keys, dtype=np.int64)
    lo, hi = k.min(axis=0), k.max(axis=0)
    rec, xyz = _copc_box(folder, f, origin, np.array([lo * side, (hi + 1) * side]))
    span = int(hi[1] - lo[1]) + 1
    b = block_of(xyz[:, :2], int(epoch["block_cells"])) - lo  # every point's block lies in the keys' box
    wanted = (k[:, 0] - lo[0]) * span + (k[:, 1] - lo[1])
    keep = np.isin(b[:, 0] * span + b[:, 1], wanted)
    if buildings_only:
        keep &= rec["building_id"] > 0
    return rec[keep]


def _copc_records(folder: Path, f: EpochFile, origin: np.ndarray, packed: np.ndarray, index: np.ndarray,
                  xyz: np.ndarray) -> np.ndarray:
    """RECORDs of a COPC file's points, building IDs given as `stream_epoch` gives them (the
    footprint holding the point, or the file's building_id)."""
    import laspy

    from ..formats.copc import copc_index

    points = laspy.PackedPointRecord(packed, copc_index(f.path).header.point_format)
    rec = np.empty(len(packed), RECORD)
    rec["index"], rec["X"], rec["Y"], rec["Z"] = index, packed["X"], packed["Y"], packed["Z"]
    rec["classification"] = np.asarray(points["classification"], dtype=np.uint8)
    footprints = _epoch_json(folder).get("footprints")
    if footprints:
        from ..formats.footprints import assign_buildings

        rec["building_id"] = assign_buildings(xyz[:, 0] + origin[0], xyz[:, 1] + origin[1],
                                              worker_footprints(footprints["path"], footprints.get("id_field")))
    else:
        rec["building_id"] = np.asarray(points["building_id"], dtype=np.int64)
    return rec


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


_FOOTPRINTS: dict = {}


def worker_footprints(path: str, id_field):
    """The footprints of `path`, read once per worker process (every part of both epochs asks)."""
    from ..formats.footprints import read_footprints

    key = (path, id_field, Path(path).stat().st_mtime_ns)
    if key not in _FOOTPRINTS:
        _FOOTPRINTS.clear()
        _FOOTPRINTS[key] = read_footprints(path, id_field)
    return _FOOTPRINTS[key]


def block_m(block_cells: int) -> float:
    return float(block_cells) * DENSITY_CELL_M


__all__ = ["CHUNK_POINTS", "EpochFile", "EpochStats", "RECORD", "block_of", "block_runs", "blocks_in_box",
           "default_origin", "join_part_indexes", "merge_stats", "open_epoch_file", "page_cache_cannot_hold",
           "read_box", "read_records", "read_runs", "record_dtype", "stored_points", "stored_record", "stream_epoch",
           "worker_footprints"]
