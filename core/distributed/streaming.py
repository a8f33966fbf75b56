"""An epoch streamed from its LAS/LAZ file into the block files (`quakescan.distributed.block_store`).

The tiling step of a distributed classification. The file is read in chunks (laspy's chunk
iterator: memory holds one chunk, never the cloud), each point gets its building ID (the
file's `building_id` or the footprint that holds it), and is appended to the file of its
block. Several tasks may each stream a part of the file (a range of its points); their
stats join into the whole epoch's (`merge_stats`).

While streaming, the client keeps what needs the whole epoch and is small: per building its
point count and x/y box, the epoch's bounds, the stable points the registration check
samples (`quakescan.change.align.sample_mask`), every k-th point for the map, and the convex
hull of each building's pre-event points (the outline of a building without a footprint).
"""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..formats.pointcloud import PointCloudError, noise_mask, read_point_range
from ..grid.density import DENSITY_CELL_M
from .block_store import (
    INDEX_NAME,
    RECORD,
    part_index_path,
    part_path,
    record_dtype,
    run_keys,
    save_index,
    write_record,
)

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
    from ..formats.pointcloud import crs_of, check_point_cloud_path

    path = check_point_cloud_path(path)
    try:
        with laspy.open(path) as f:
            h = f.header
            names = list(h.point_format.dimension_names)
            ids = (np.dtype(h.point_format.dimension_by_name("building_id").dtype).str
                   if "building_id" in names else None)
            return EpochFile(str(path), int(h.point_count), [float(v) for v in h.scales],
                             [float(v) for v in h.offsets], [float(v) for v in h.mins], [float(v) for v in h.maxs],
                             crs_of(h, path), names, is_copc(h), ids)
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
            if noise.any():  # in no building, as `quakescan.formats.pair.load_pair` sets them
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
        write_record(folder, record, part)
        if part is None:
            save_index(folder / INDEX_NAME, rows)
        else:
            save_index(part_index_path(folder, part), rows)
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


_FOOTPRINTS: dict = {}


def worker_footprints(path: str, id_field):
    """The footprints of `path`, read once per worker process (every part of both epochs asks)."""
    from ..formats.footprints import read_footprints

    key = (path, id_field, Path(path).stat().st_mtime_ns)
    if key not in _FOOTPRINTS:
        _FOOTPRINTS.clear()
        _FOOTPRINTS[key] = read_footprints(path, id_field)
    return _FOOTPRINTS[key]


__all__ = ["CHUNK_POINTS", "EpochFile", "EpochStats", "MAP_POINTS", "PAGE_CACHE_SHARE", "SEGMENT_POINTS",
           "default_origin", "merge_stats", "open_epoch_file", "page_cache_cannot_hold", "stream_epoch",
           "worker_footprints"]
