"""`quakescan classify --workers N | --scheduler ADDRESS`: the classify run's engine on Dask.

The client never holds an epoch. It streams both files chunk by chunk into square blocks
on disk (`quakescan.distributed.streaming`, `block_store`), keeping per building its point counts and x/y box.
Then it asks the workers, each reading only the blocks it needs:

1. the roof-cell counts of every block (the pair's densities, which set the surface
   descriptors' grid: `tasks.block_roof_cells`), and
2. the rows of every tile: the buildings whose pre-event box centre lies in one square of
   the model's tile size, with every point their descriptors read (`tasks.describe_tile_task`).

The tiles, the densities, the registration check's sample and the order of every point are
those of the single-process run, so `buildings.csv` is the same file byte for byte. A
worker that dies has its tasks redone by the scheduler; finished tiles are checkpointed to
OUT/.checkpoint.jsonl (the single-process run's file: either run resumes the other's), and
the block files to OUT/.blocks, valid for one fingerprint of the inputs.
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from ..assessment import record
from ..assessment.engine import Engine, ReadPair
from ..assessment.run import classify
from ..change.registration import check_max_points
from ..errors import ClassifyError
from ..formats.footprints import coverage, footprints_without_points, no_footprint_contains_a_point
from ..formats.pair import check_footprints_against_headers
from ..formats.pointcloud import (HeaderFacts, check_coordinates_fit_crs, check_not_all_noise,
                                  check_pair_headers)
from ..runtime.output_folder import empty_own_subfolder, is_own_subfolder, remove_own_subfolder
from .block_store import (
    LAYOUT,
    block_m,
    epoch_json,
    join_part_indexes,
    read_manifest,
    save_arrays,
    write_manifest,
)
from .streaming import CHUNK_POINTS, EpochStats, default_origin, merge_stats, open_epoch_file
from .cluster import dashboard_address

log = logging.getLogger(__name__)

# A block is 50 × 50 density cells (50 m): a 150 m tile with its halo (~174 m) reads 4 × 4 or
# 5 × 5 of them, 1.3-2.1 times its box. 25 m blocks (1.3-1.7 times) made the pair's
# tiles 2.5-4 % faster on one worker, but a tile then read a file per block and part (the
# layout before one file a part): on the 2 × 262 M pair (17 parts an epoch, its blocks beyond
# the page cache) the tiles took 358 s against 324 s, the run 455 s against 410 s.
BLOCK_CELLS = 50
MANIFEST = "manifest.json"
UNMOVED_CHECKPOINT = ".checkpoint.unmoved.jsonl"
# QuakeScan's working folders in OUT (with the marker of `runtime.output_folder`: a user's
# folder of the name is refused, never emptied): the epochs' blocks, the graded cloud's parts
STORE_NAME, GRADED_NAME = ".blocks", ".graded"
HALO_STEP_M = 10.0  # a tile whose nearest neighbours reach beyond its halo asks again with this much more
# What a tile task holds at its peak, per point: the records of every block it reads (their
# bytes, the index sort and the sorted copy) and, per point inside its box, the coordinates,
# grid index, descriptor arrays and scratch. Set from the peak RSS of describe_tile_task on the
# three largest 150 m tiles of bench_pipeline's 75 M-point pair (8-10 M points read, 1.3-1.5 GB
# above the worker's 0.5 GB at rest): these constants put them at 1.45-1.8 GB, 15-20 % over.
READ_BYTES_PER_POINT = 60
DESCRIBE_BYTES_PER_POINT = 200
# A tile is split when its estimate passes this share of the smallest worker's memory limit:
# Dask's nanny pauses a worker at 80 % and kills it at 95 %, and the estimate is an average
TILE_MEMORY_SHARE = 0.5
# The densities are counted a square of 200 m (4 × 4 blocks) a task, each square as one part
# (an aligned epoch's ring of blocks is read once a square): counted one part a block, every
# block's rim cells went back to the client undecided, as Python lists it merged alone.
DENSITY_GROUP_M = 200.0
PART_POINTS = 16_000_000  # points of one epoch streamed by one task at most: a few tasks a worker to balance
# the registration check before any tile task: the tiles' rows stand only once it has answered
REGISTRATION_PRIORITY = 10 ** 9
MAX_SPLIT_DEPTH = 12  # quarters of a 150 m tile down to 4 cm: buildings sharing one centre stay together


class DaskEngine(Engine):
    """The classify run's engine on the workers of `client` (a dask.distributed Client): the
    epochs streamed into blocks, the densities and the tiles described by the workers, the
    graded cloud's records made by them. Same files, same rows as one process; the summary
    adds "dask". `on_stage(name)`: called as each stage begins (tiling, densities, tiles,
    results, graded cloud). One engine object serves one run at a time."""

    working_folders = (STORE_NAME, GRADED_NAME)

    def __init__(self, client, *, block_cells: int = BLOCK_CELLS, chunk_points: int = CHUNK_POINTS,
                 on_stage=None):
        self.client, self.block_cells, self.chunk_points, self.on_stage = client, block_cells, chunk_points, on_stage

    def _stage(self, pair, name):
        pair.stages.append((name, time.perf_counter()))
        if self.on_stage:
            self.on_stage(name)

    def read(self, job, load):
        pre_path, post_path, out = job.pre_path, job.post_path, job.out
        pre_f, post_f = open_epoch_file(pre_path), open_epoch_file(post_path)
        fp = _read_footprints(job.footprints_path, job.id_field, pre_f, post_f)
        crs = _pair_crs(pre_f, post_f, fp)
        origin = default_origin(pre_f)
        out.mkdir(parents=True, exist_ok=True)
        store = out / STORE_NAME
        job.before_first_write()
        sample = None if job.align is False else check_max_points(job.align)
        pair = ReadPair(points={}, noise_points={}, crs=crs, footprints=fp, footprint_ids_without_points=[],
                        map_xy=None, outline_points=None, outline_origin=(0.0, 0.0))
        self._stage(pair, "tiling")
        footprints = None if job.footprints_path is None else {"path": str(Path(job.footprints_path).resolve()),
                                                               "id_field": job.id_field}

        def meanwhile():  # the client's own work while the workers stream: the model is read meanwhile
            load()
            from ..results.png_map import import_map_modules

            import_map_modules()

        pre_s, post_s = _tiled_epochs(self.client, store, job.digest, pre_f, post_f, origin, fp, footprints,
                                      self.block_cells, sample, self.chunk_points, job.progress, meanwhile=meanwhile)
        for path, stats in ((pre_path, pre_s), (post_path, post_s)):
            check_not_all_noise(stats.noise, stats.n, path)
        if fp is not None and not pre_s.counts:
            raise no_footprint_contains_a_point(job.footprints_path, fp, (pre_f.mins[0], pre_f.maxs[0]))
        if not (set(pre_s.counts) | set(post_s.counts)):
            raise ClassifyError(f"{pre_path}: no point belongs to a building (all building IDs are 0)")
        pair.points = {"pre": pre_s.n, "post": post_s.n}
        pair.noise_points = {"pre": pre_s.noise, "post": post_s.noise}
        pair.footprint_ids_without_points = footprints_without_points(fp, set(pre_s.counts) | set(post_s.counts))
        pair.coverage = coverage(fp, set(pre_s.counts), set(post_s.counts))
        pair.map_xy = pre_s.map_xy + origin[:2]
        pair.outline_points = pre_s.hulls if fp is None else None
        pair.state = _DaskPair(pre_f, post_f, pre_s, post_s, origin, store, footprints)
        return pair

    def describe(self, job, pair, settings, summary):
        client, block_cells, d = self.client, self.block_cells, pair.state
        align = job.align
        self._stage(pair, "densities")

        def check_registration():
            """The registration check as a task of its own (None when it is off). Submitted after
            the densities are gathered: its ICP holds a worker's GIL for up to a second at a time
            (open3d's normal estimation), and a density result kept on that worker waited for it
            (the densities took 2.5 s on two workers for 0.8 s of tasks)."""
            if align is False:
                summary["registration"] = {"mode": "off", "checked": False}
                return None
            from .tasks import registration_task

            # The samples (up to 2 x 12 MB) are read by the task from the tiling's saved stats: inside
            # the task they would make a large graph (held by the scheduler), and scattered they
            # would be lost with the worker holding them. The check runs first (its priority),
            # beside the tiles. One thread, as a tile: open3d would take every core.
            return client.submit(registration_task, str(d.store), settings.to_json(), align,
                                 {"pre": summary["pre"], "post": summary["post"]}, d.post_s.bounds, 1,
                                 pure=False, priority=REGISTRATION_PRIORITY)

        def settle(checked) -> list | None:
            """The registration check's answer into the summary and the log: the alignment's
            transform when one is applied, else None."""
            for level, message in checked["messages"]:
                log.log(level, "%s", message)
            summary["registration"] = checked["record"]
            if checked["alignment"] is not None:
                summary["alignment"] = checked["alignment"]
            if summary["registration"].get("applied"):
                return summary["alignment"]["transform"]
            return None

        # The tiles start before the check has answered, as if the epochs were aligned (almost
        # always: an alignment is applied only past `MIN_FIT_GAIN`): on two workers the check's
        # seconds no longer hold up the tiles. When it applies an alignment, they are cancelled
        # and described again from the moved post-event epoch.
        registration = None
        try:
            geometry = _pair_geometry(client, d.store, d.pre_s, d.post_s, settings, block_cells, None)
            registration = check_registration()
            self._stage(pair, "tiles")
            d.budget = tile_memory_budget(client)
            rows, resumed, d.widened, d.split = _describe_tiles(client, d.store, d.pre_s, d.post_s, settings,
                                                                geometry, block_cells, None, 0.0, job.out,
                                                                job.digest, job.progress, d.budget,
                                                                pending=registration, settle=settle)
        except _Realign as moved:
            d.transform, shift = moved.transform, float(summary["registration"]["offset_m"])
            geometry = _pair_geometry(client, d.store, d.pre_s, d.post_s, settings, block_cells, d.transform)
            rows, resumed, d.widened, d.split = _describe_tiles(client, d.store, d.pre_s, d.post_s, settings,
                                                                geometry, block_cells, d.transform, shift, job.out,
                                                                job.digest, job.progress, d.budget)
        except BaseException:
            if registration is not None:
                client.cancel([registration])
            raise
        return rows, resumed

    def described(self, job, pair):
        self._stage(pair, "results")
        pair.state.deleting = _delete_store(pair.state.store)

    def write_graded_cloud(self, job, pair, path, grade_by_building):
        d = pair.state
        self._stage(pair, "graded cloud")
        _write_graded_cloud(self.client, path, d.post_f, d.origin, pair.crs, d.footprints, d.transform,
                            grade_by_building, max(d.post_s.counts, default=0), self.chunk_points,
                            job.out / GRADED_NAME, job.progress)

    def add_to_summary(self, pair, summary, seconds, end):
        d = pair.state
        summary["dask"] = {"workers": len(self.client.scheduler_info().get("workers", {})),
                           "dashboard": dashboard_address(self.client), "block_m": block_m(self.block_cells),
                           "tiles_widened": d.widened, "tiles_split": d.split,
                           "tile_memory_budget_bytes": int(d.budget) if np.isfinite(d.budget) else None}
        seconds["stages"] = _stage_seconds(pair.stages, end)

    def close(self, job, pair):
        for done_with in (".checkpoint.jsonl", UNMOVED_CHECKPOINT):
            (job.out / done_with).unlink(missing_ok=True)
        if pair.state.deleting is not None:
            pair.state.deleting.join()


class _DaskPair:
    """The Dask engine's state of one run: the files, their tiling, the block store, the alignment."""

    def __init__(self, pre_f, post_f, pre_s, post_s, origin, store, footprints):
        self.pre_f, self.post_f, self.pre_s, self.post_s = pre_f, post_f, pre_s, post_s
        self.origin, self.store, self.footprints = origin, store, footprints
        self.transform, self.budget, self.widened, self.split = None, float("inf"), 0, 0
        self.deleting = None


def classify_distributed(pre_path, post_path, out_dir, client, *, block_cells: int = BLOCK_CELLS,
                         chunk_points: int = CHUNK_POINTS, on_stage=None, **options) -> dict:
    """`quakescan.assessment.run.classify` with the tiles described by the workers of `client`
    (the `DaskEngine`); `options` are `classify`'s. `progress(done, total, stage)`: the points
    of each epoch streamed into blocks (stages "tiling pre", "tiling post"), then the buildings
    described (no stage), as `classify`."""
    return classify(pre_path, post_path, out_dir,
                    engine=DaskEngine(client, block_cells=block_cells, chunk_points=chunk_points, on_stage=on_stage),
                    **options)


def _delete_store(store: Path):
    """Delete the block files once every tile is described, beside the results (a thread,
    returned for the caller to join): nothing reads them again, and deleting them is the
    kernel's work of seconds on a large pair (3.1 GB of files took 0.4-0.65 s here, the
    2 x 262 M pair has 11 GB). The manifest goes first: a run interrupted from
    here on tiles its epochs again (its tiles' rows stay checkpointed) instead of trusting
    blocks half deleted."""
    import threading

    if is_own_subfolder(store):
        (store / MANIFEST).unlink(missing_ok=True)
    thread = threading.Thread(target=remove_own_subfolder, args=(store,), name="quakescan-delete-blocks", daemon=True)
    thread.start()
    return thread


def _stage_seconds(marks: list, end: float) -> dict:
    """Seconds from each stage's start to the next's (the last to `end`)."""
    ends = [t for _, t in marks[1:]] + [end]
    return {name: round(max(0.0, stop - start), 2) for (name, start), stop in zip(marks, ends)}


def _read_footprints(footprints_path, id_field, pre_f, post_f):
    if footprints_path is None:
        for f in (pre_f, post_f):
            if "building_id" not in f.dimensions:
                raise ClassifyError(f"{f.path}: no building_id dimension; give building footprints "
                                       "(--footprints F.geojson in the clouds' CRS)")
        return None
    from ..formats.footprints import read_footprints

    fp = read_footprints(footprints_path, id_field)
    check_footprints_against_headers(footprints_path, fp, _facts(pre_f), _facts(post_f))
    return fp


def _facts(f) -> HeaderFacts:
    return HeaderFacts(Path(f.path), f.crs, f.n, np.asarray(f.mins, dtype=np.float64),
                       np.asarray(f.maxs, dtype=np.float64))


def _pair_crs(pre_f, post_f, fp) -> str | None:
    """The pair's CRS, checked from the headers as `load_pair` checks them."""
    check_pair_headers(_facts(pre_f), _facts(post_f))
    for f in (pre_f, post_f):
        check_coordinates_fit_crs(f.crs, f.mins, f.maxs, f.path)
    crs = pre_f.crs or post_f.crs
    if not crs and fp is not None and fp.crs:
        crs = fp.crs
    return crs


def _tiled_epochs(client, store: Path, digest: str, pre_f, post_f, origin, fp, footprints, block_cells, sample,
                  chunk_points, progress=None, meanwhile=None):
    """Both epochs as blocks under `store`, streamed now by the workers or kept from an
    interrupted run of the same inputs (its manifest is written last). Each epoch is streamed
    in parts, ranges of the file's points, one task each (`tasks.stream_part`), so the
    tiling runs on every worker instead of the client alone; `progress` counts the points
    streamed, as the stages "tiling pre" and "tiling post". `meanwhile()`: the client's own
    work, done while the workers stream (the streaming is cancelled if it raises)."""
    from dask.distributed import as_completed

    from .tasks import stream_part

    kept = kept_epochs(store, digest, block_cells)
    if kept is not None:
        if meanwhile:
            meanwhile()
        return kept
    empty_own_subfolder(store, ClassifyError)
    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    pair_bytes = sum(Path(f.path).stat().st_size for f in (pre_f, post_f))
    futures = {}
    for name, f in (("pre", pre_f), ("post", post_f)):
        folder = store / name
        folder.mkdir(parents=True, exist_ok=True)
        bounds = part_bounds(f.n, n_workers, chunk_points)
        (folder / "epoch.json").write_text(json.dumps({"file": f.to_json(), "origin": origin.tolist(),
                                                       "parts": len(bounds) - 1, "block_cells": block_cells,
                                                       "footprints": footprints}))
        for part, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
            fut = client.submit(stream_part, str(folder), f.to_json(), origin.tolist(), part, a, b, block_cells,
                                footprints, name == "pre" and fp is None,
                                None if sample is None else (f.n, sample),
                                record.map_step(f.n) if name == "pre" else None, chunk_points, pair_bytes, pure=False,
                                key=f"stream-{name}-{part}-{run_token()}")
            futures[fut] = (name, part, b - a)
    if meanwhile:
        try:
            meanwhile()
        except BaseException:
            client.cancel(list(futures))
            raise
    parts: dict[str, dict] = {"pre": {}, "post": {}}
    done = {"pre": 0, "post": 0}
    for fut in as_completed(list(futures)):
        name, part, n = futures[fut]
        parts[name][part] = fut.result()
        done[name] += n
        if progress:
            progress(done[name], (pre_f if name == "pre" else post_f).n, f"tiling {name}")
    stats = {}
    for name, f in (("pre", pre_f), ("post", post_f)):
        if not f.copc:
            join_part_indexes(store / name, len(parts[name]))
        s = merge_stats([parts[name][k] for k in sorted(parts[name])])
        arrays = {"stable_sample": s.stable_sample, "map_xy": s.map_xy}
        arrays.update({f"hull_{b}": v for b, v in s.hulls.items()})
        save_arrays(store / f"{name}.npz", arrays)
        stats[name] = s
    write_manifest(store / MANIFEST, {"fingerprint": digest, "block_cells": block_cells, "layout": LAYOUT,
                                         "pre": stats["pre"].to_json(), "post": stats["post"].to_json()})
    return stats["pre"], stats["post"]


def kept_epochs(store: Path, digest: str, block_cells: int):
    """(pre, post) EpochStats of the blocks an interrupted run of the same inputs, block size
    and block layout finished under `store`, or None (none, other, or unreadable: tiled again)."""
    if not is_own_subfolder(store):
        return None
    manifest = read_manifest(store / MANIFEST)
    if not (manifest and manifest.get("fingerprint") == digest and manifest.get("block_cells") == block_cells
            and manifest.get("layout") == LAYOUT):
        return None
    try:
        return tuple(EpochStats.from_json(manifest[name], dict(np.load(store / f"{name}.npz")))
                     for name in ("pre", "post"))
    except (OSError, KeyError, ValueError):
        return None


def run_token() -> str:
    """A part of the task keys new in every run: the keys of a run interrupted a moment ago may
    still be cancelling on the scheduler, and a new future under such a key is cancelled too."""
    import uuid

    return uuid.uuid4().hex[:8]


def part_bounds(n: int, n_workers: int, chunk_points: int) -> list[int]:
    """Where the parts an epoch of `n` points is streamed in begin and end: two parts a worker
    at least (the last part of one epoch overlaps the first of the other), at most
    PART_POINTS a part, never fewer points than a chunk in a part."""
    parts = max(2 * n_workers, -(-n // PART_POINTS))
    parts = max(1, min(parts, -(-n // max(1, chunk_points))))
    return [round(k * n / parts) for k in range(parts + 1)]


def _pair_geometry(client, store, pre_s, post_s, settings, block_cells, transform):
    """The surface descriptors' grid and cylinder sizes, from the densities the workers count
    (`transform`: the post epoch's alignment, or None)."""
    from .tasks import group_roof_cells, merge_roof_cells

    def submit(name, stats, building_only, moved):
        keys = {tuple(k) for k in stats.blocks}
        if moved is not None:  # a block empty before the alignment may hold points after it
            keys = {(k[0] + dx, k[1] + dy) for k in keys for dx in (-1, 0, 1) for dy in (-1, 0, 1)}
        groups: dict[tuple, list] = {}
        per_group = max(1, round(DENSITY_GROUP_M / block_m(block_cells)))
        for k in sorted(keys):
            groups.setdefault((k[0] // per_group, k[1] // per_group), []).append(k)
        return [client.submit(group_roof_cells, str(store / name), g, block_cells, building_only, moved,
                              per_group * block_cells, pure=False) for g in groups.values()]

    def density(futures):
        return merge_roof_cells([part for parts in client.gather(futures) for part in parts])

    if settings.surface is None:
        return None
    from ..change.surface import SurfaceGeometry

    pre_jobs, post_jobs = submit("pre", pre_s, True, None), submit("post", post_s, True, transform)
    try:
        d_pre, d_post = density(pre_jobs), density(post_jobs)
    except BaseException:
        client.cancel(pre_jobs + post_jobs)
        raise
    if d_post == 0.0:
        d_post = density(submit("post", post_s, False, transform))
    return SurfaceGeometry.for_pair(settings.surface, d_pre, d_post)


class _Realign(Exception):
    """The registration check applied an alignment after the tiles had started unmoved."""

    def __init__(self, transform):
        super().__init__("the post-event epoch is aligned: its tiles are described again")
        self.transform = transform


def _describe_tiles(client, store, pre_s, post_s, settings, geometry, block_cells, transform, shift, out, digest,
                    progress, budget, pending=None, settle=None):
    """Rows of every building, its tile described by a worker; finished tiles are checkpointed.

    `pending`: the registration check's future, when the tiles start before it answers (as
    if no alignment were applied); `settle(result)` returns its transform or None. Until it
    answers, finished rows go to a checkpoint of their own (UNMOVED_CHECKPOINT), which a
    resumed run reads while it, too, waits; a transform discards it, cancels the tiles and
    raises _Realign."""
    from dask.distributed import as_completed

    from ..change.pipeline import quality_gate, rows_by_counts
    from ..change.tiling import tile_key
    from .tasks import TileReachError, add_facing_counts, describe_tile_task

    rows, ok = rows_by_counts(pre_s.counts, post_s.counts, settings)
    halo = _halo(settings, geometry)
    tiles: dict[tuple, list[int]] = {}
    for b in ok:
        tiles.setdefault(tile_key(pre_s.lo[b], pre_s.hi[b], settings.tile_m), []).append(b)
    ckpt = record.RowCheckpoint(out / ".checkpoint.jsonl", digest)
    # rows described before the registration check answered, unmoved: valid unless it aligns
    unmoved = record.RowCheckpoint(out / UNMOVED_CHECKPOINT, digest) if pending is not None else None
    known = {**unmoved.rows, **ckpt.rows} if unmoved is not None else ckpt.rows
    resumed = 0
    total, finished = len(ok), 0
    settings_json = settings.to_json()
    geometry_json = None if geometry is None else dict(geometry.__dict__)
    post_box = np.asarray(post_s.bounds)[:, :2] if post_s.bounds else None

    def spec(key, bids, h):
        lo = np.min([np.minimum(np.asarray(pre_s.lo[b]) - h, np.asarray(post_s.lo.get(b, pre_s.lo[b])) - shift)
                     for b in bids], axis=0)
        hi = np.max([np.maximum(np.asarray(pre_s.hi[b]) + h, np.asarray(post_s.hi.get(b, pre_s.hi[b])) + shift)
                     for b in bids], axis=0)
        return {"key": list(key), "bids": sorted(bids), "box": [lo.tolist(), hi.tolist()], "halo": h,
                "block_cells": block_cells, "read_margin": shift,
                "whole_post_box": None if post_box is None else post_box.tolist()}

    estimates: dict = {}

    def estimate(s):  # asked when splitting, warning and submitting: each tile's blocks looked up once
        key = (tuple(s["bids"]), s["halo"])
        if key not in estimates:
            estimates[key] = tile_memory_bytes(store, s, block_cells)
        return estimates[key]

    def centre_of(b):  # the point tile_key floors: the centre of the building's pre-event x/y box
        return (np.asarray(pre_s.lo[b], dtype=np.float64) + np.asarray(pre_s.hi[b], dtype=np.float64)) / 2

    futures, groups, widened, split = {}, {}, 0, 0
    token = run_token()

    def submit(s, facing=None, name=None):
        # the largest tiles first, so that no worker is left with a large one while the others idle
        fut = client.submit(describe_tile_task, str(store), s, settings_json, geometry_json, transform, 1, facing,
                            pure=False, priority=int(estimate(s) // 1e6), **({"key": name} if name else {}))
        futures[fut] = (s, facing)
        return fut

    for key in sorted(tiles):
        bids = tiles[key]
        if all(b in known for b in bids):
            for b in bids:
                rows[b] = known[b]
            resumed += len(bids)
            finished += len(bids)
            if progress:
                progress(finished, total)
            continue
        parts = split_tile(key, bids, centre_of, settings.tile_m, lambda k, b: estimate(spec(k, b, halo)), budget)
        split += len(parts) - 1
        _warn_alone(parts, lambda k, b: estimate(spec(k, b, halo)), budget)
        # the parts of a split tile count their walls first: lost walls are judged by the whole tile's counts
        count_first = len(parts) > 1 and settings.surface is not None
        if count_first:
            groups[tuple(key)] = {"parts": parts, "counts": []}
        for part_key, part_bids in parts:
            s = spec(part_key, part_bids, halo)
            name = "_".join(str(v) for v in part_key)
            if count_first:
                submit({**s, "count_facing": True, "group": list(key)}, name=f"count-{name}-{token}")
            else:
                submit(s, name=f"tile-{name}-{token}")
    queue = as_completed(list(futures) + ([pending] if pending is not None else []))
    for fut in queue:
        if fut is pending:
            try:
                moved = settle(fut.result())
            except BaseException:
                client.cancel(list(futures))
                raise
            if moved is not None:
                client.cancel(list(futures))
                unmoved.path.unlink(missing_ok=True)
                raise _Realign(moved)
            unmoved = None  # its rows stand; the next go to the checkpoint
            continue
        s, facing = futures.pop(fut)
        try:
            result = fut.result()
        except TileReachError as e:  # widen the halo and ask again
            wider = {**spec(tuple(s["key"]), s["bids"], max(s["halo"] + HALO_STEP_M, e.needed_m + HALO_STEP_M)),
                     **{k: s[k] for k in ("count_facing", "group") if k in s}}
            queue.add(submit(wider, facing))
            widened += 1
            continue
        if s.get("count_facing"):
            group = groups[tuple(s["group"])]
            group["counts"].append(result)
            if len(group["counts"]) == len(group["parts"]):
                whole = add_facing_counts(*group["counts"])
                for part_key, part_bids in group["parts"]:
                    name = "_".join(str(v) for v in part_key)
                    queue.add(submit(spec(part_key, part_bids, halo), whole, name=f"tile-{name}-{token}"))
            continue
        tile_rows = result["rows"]
        for r in tile_rows:
            r.n_pre, r.n_post = pre_s.counts.get(r.building_id, 0), post_s.counts.get(r.building_id, 0)
            rows[r.building_id] = r
        (ckpt if unmoved is None else unmoved).add([r for r in tile_rows if r.assessable])
        finished += len(s["bids"])
        if progress:
            progress(finished, total)
    if resumed:
        log.warning("%s: resuming, %d buildings already described", out, resumed)
    if split:
        log.info("%d tiles more than the model's tiling: tiles split to fit %.1f GB per worker", split,
                 budget / 1e9)
    return [quality_gate(rows[b], settings) for b in sorted(rows)], resumed, widened, split


def _warn_alone(parts, estimate, budget) -> None:
    """Say so where a building alone is over the budget: it cannot be split, and is described whole."""
    if len(parts) < 2:
        return
    for key, bids in parts:
        if len(bids) == 1 and (need := estimate(key, bids)) > budget:
            log.warning("building %d alone needs about %.1f GB to describe, more than the %.1f GB a worker may "
                        "take (%.0f %% of its memory limit): it is described whole", bids[0], need / 1e9,
                        budget / 1e9, 100 * TILE_MEMORY_SHARE)


def tile_memory_budget(client) -> float:
    """Bytes a tile task may take: a share of the smallest worker memory limit of the
    cluster (infinite where the workers have none)."""
    limits = [w.get("memory_limit") or 0 for w in client.scheduler_info().get("workers", {}).values()]
    limits = [v for v in limits if v > 0]
    return TILE_MEMORY_SHARE * min(limits) if limits else float("inf")


def tile_memory_bytes(store: Path, tile: dict, block_cells: int) -> float:
    """The peak memory of `describe_tile_task` on `tile`, estimated from the points of the blocks
    it reads: every point of those blocks is read, the share of them inside the tile's
    box is described (a COPC epoch: the points of the file's nodes the box overlaps)."""
    from .block_store import blocks_in_box, stored_points

    box = np.asarray(tile["box"], dtype=np.float64)
    area = float(np.prod(np.maximum(box[1] - box[0], 0.0)))
    side = block_m(block_cells)
    read = inside = 0.0
    for name, grow in (("pre", 0.0), ("post", float(tile.get("read_margin", 0.0)))):
        keys = blocks_in_box(box + np.array([[-grow], [grow]]), block_cells)
        epoch = epoch_json(Path(store) / name)
        if epoch.get("file", {}).get("copc"):  # the points of the file's nodes the box overlaps
            from ..formats.copc import copc_index

            world = box + np.array([[-grow], [grow]]) + np.asarray(epoch["origin"], dtype=np.float64)[:2]
            n, n_inside = copc_index(epoch["file"]["path"]).points_for_box(world)
            read += n
            inside += n_inside
            continue
        n = stored_points(Path(store) / name, keys)
        read += n
        inside += n * min(1.0, area / (len(keys) * side * side)) if keys else 0.0
    return read * READ_BYTES_PER_POINT + inside * DESCRIBE_BYTES_PER_POINT


def split_tile(key: tuple, bids: list, centre_of, tile_m: float, estimate, budget: float) -> list[tuple[tuple, list]]:
    """The tile as (key, buildings) parts whose `estimate(key, bids)` fits `budget`: split into
    the four quarters of its square (a building goes to the quarter holding `centre_of(b)`, as
    it went to the tile), and those again, down to one building a part. A part's key is the
    tile's followed by its quarters' (0/1, 0/1) indices. A building's descriptors read only the
    points around it but for the wall counts its tile shares (`count_by_facing`), which the
    parts add up before they describe (`_describe_tiles`)."""
    depth = (len(key) - 2) // 2 + 1
    if len(bids) <= 1 or depth > MAX_SPLIT_DEPTH or estimate(key, bids) <= budget:
        return [(tuple(key), list(bids))]
    side = tile_m / 2 ** depth
    quarters: dict[tuple, list] = {}
    for b in bids:
        i, j = np.floor(np.asarray(centre_of(b), dtype=np.float64) / side).astype(np.int64).tolist()
        quarters.setdefault((i % 2, j % 2), []).append(b)
    parts = []
    for q in sorted(quarters):
        parts += split_tile(tuple(key) + q, quarters[q], centre_of, tile_m, estimate, budget)
    return parts


def _halo(settings, geometry) -> float:
    """How far beyond a tile's buildings its descriptors read (m): the surface descriptors'
    region, the feature radius and a first guess of the nearest-neighbour search."""
    h = 1.0001 * settings.radius_m + HALO_STEP_M
    if settings.surface is not None:
        from ..change.surface import region_margin

        h = max(h, region_margin(settings.surface, geometry) + 1.0)
    return h


def _write_graded_cloud(client, path, post_f, origin, crs, footprints, transform, grade_by_building, max_id,
                        chunk_points, folder: Path, progress=None):
    """post_grades.las/.laz of the post-event file's points, aligned as the tiles saw them,
    with every attribute of the file, building ID and grade: the workers make the point
    records of the file's parts (`tasks.graded_part`, as the tiling's parts), the client puts
    them behind one header in order (and compresses them for .laz) — the bytes one process
    writes. `progress` counts the points made, as the stage "graded cloud"."""
    import laspy
    from dask.distributed import as_completed

    from ..results.graded_cloud import grade_header, source_extra_dims, write_grade_records
    from .tasks import graded_part

    empty_own_subfolder(folder, ClassifyError)
    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    bounds = part_bounds(post_f.n, n_workers, chunk_points)
    grades = {int(b): (None if g is None else int(g)) for b, g in grade_by_building.items()}
    token = run_token()
    futures = {client.submit(graded_part, str(folder / f"{k}.bin"), post_f.to_json(), origin.tolist(), a, b,
                             footprints, transform, grades, max_id, chunk_points, pure=False,
                             key=f"graded-{k}-{token}"): b - a
               for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))}
    done = 0
    try:
        for fut in as_completed(list(futures)):
            fut.result()
            done += futures[fut]
            if progress:
                progress(done, post_f.n, "graded cloud")
    finally:
        client.cancel([f for f in futures if not f.done()])
    with laspy.open(post_f.path) as reader:
        header = grade_header(path, origin, crs, max_id, source_extra_dims(reader.header))
    dtype = header.point_format.dtype()

    def records():
        for k in range(len(bounds) - 1):
            with open(folder / f"{k}.bin", "rb") as fh:
                while True:
                    array = np.fromfile(fh, dtype=dtype, count=chunk_points)
                    if not len(array):
                        break
                    yield laspy.PackedPointRecord(array, header.point_format)

    write_grade_records(path, header, origin, records())
    remove_own_subfolder(folder)


__all__ = ["BLOCK_CELLS", "DaskEngine", "classify_distributed", "split_tile", "tile_memory_bytes",
           "tile_memory_budget"]
