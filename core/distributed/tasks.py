"""What a Dask worker runs: one block's roof-cell counts, one tile's building rows.

Plain functions of plain arguments (paths, lists, dicts, settings as JSON): a task pickles
in a few hundred bytes and a worker reads its points from the stored blocks itself, so no
point cloud ever travels through the scheduler.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..grid.density import DENSITY_CELL_M
from .block_store import block_runs, read_runs, stored_points
from .reading import read_box, read_records
from .streaming import EpochFile, worker_footprints

# the eight neighbours a roof cell needs occupied to count as interior (roof_cell_density)
NEIGHBOURS = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]


class TileReachError(Exception):
    """A tile's descriptors read points beyond the halo it was given (a nearest post-event
    point farther than the halo): the client describes the tile again with `needed_m`."""

    def __init__(self, needed_m: float):
        super().__init__(f"the tile's descriptors reach {needed_m:.1f} m beyond its buildings")
        self.needed_m = float(needed_m)


# A square of blocks (with an alignment, the ring of blocks around it) is counted at once up
# to this many points (about 0.5 GB of records, cells and heights; a 200 m square of building
# points at 200 points/m²); a denser one is counted a block at a time, as the worker's memory
# allows.
SQUARE_POINTS = 8_000_000


def group_roof_cells(folder: str, keys, block_cells: int, building_only: bool = True, transform=None,
                     square_cells: int | None = None) -> list:
    """`block_roof_cells` of several blocks in one task: with an alignment, whose points cross
    block edges, the ring of blocks around the group is read once for all of them (a 4 × 4
    group reads 6 × 6 blocks, where one block at a time read 3 × 3 for each); from a COPC
    file, the group's box is read once.

    `square_cells`: the blocks all lie in one square of this many density cells (a multiple
    of `block_cells`), which is counted as one block of that size: one part instead of one a
    block. Only cells on a part's rim go back to the client undecided, as Python lists it
    merges alone."""
    keys = [(int(k[0]), int(k[1])) for k in keys]
    f = EpochFile(**_epoch_file_args(folder))
    square = None
    if square_cells is not None:
        per = int(square_cells) // int(block_cells)
        squares = {(k[0] // per, k[1] // per) for k in keys}
        if per * int(block_cells) != int(square_cells) or len(squares) > 1:
            raise ValueError(f"blocks {keys} of {block_cells} cells do not lie in one square of {square_cells} cells")
        square = squares.pop() if squares else (0, 0)
    if transform is None and not f.copc:
        runs = block_runs(Path(folder), keys, building_only) if square is not None else None
        if square is None or runs[:, 2].sum() > SQUARE_POINTS:
            return [block_roof_cells(folder, k, block_cells, building_only) for k in keys]
        return [_stored_roof_cells(folder, f, runs, square, int(square_cells))]
    from .block_store import block_of

    # a COPC epoch: the group's box read from the file once (its coarse octree levels span every block)
    ring = keys if transform is None else sorted({(k[0] + dx, k[1] + dy) for k in keys
                                                  for dx in (-1, 0, 1) for dy in (-1, 0, 1)})
    if (transform is not None and not f.copc and len(keys) > 1
            and stored_points(Path(folder), ring, building_only) > SQUARE_POINTS):
        # a ring too dense to hold at once: each block with its own 3 × 3 ring
        return [block_roof_cells(folder, k, block_cells, building_only, transform) for k in keys]
    rec = read_records(Path(folder), ring, buildings_only=building_only, in_file_order=False)
    xyz = f.local_xyz(rec["X"], rec["Y"], rec["Z"], np.asarray(_origin(folder)))
    if transform is not None:
        from ..change.align import apply_transform

        xyz = apply_transform(transform, xyz)
    moved = block_of(xyz[:, :2], block_cells)
    if square is not None:  # the points now in one of the group's blocks
        wanted = np.array(keys, dtype=np.int64).reshape(-1, 2)
        inside = (np.isin(moved[:, 0] * (1 << 32) + moved[:, 1], wanted[:, 0] * (1 << 32) + wanted[:, 1])
                  if len(xyz) else np.zeros(0, bool))
        return [_roof_cells(xyz[inside], square, int(square_cells))]
    if not len(xyz):
        return [_roof_cells(xyz, k, block_cells) for k in keys]
    # each block's moved points in file order: one stable sort by block, a slice a block
    lo = moved.min(axis=0)
    span = int(moved[:, 1].max() - lo[1]) + 1
    flat = (moved[:, 0] - lo[0]) * span + (moved[:, 1] - lo[1])
    order = np.argsort(flat, kind="stable")
    flat = flat[order]
    out = []
    for k in keys:
        want = (k[0] - lo[0]) * span + (k[1] - lo[1])
        inside = 0 <= k[1] - lo[1] < span
        a, b = (np.searchsorted(flat, want), np.searchsorted(flat, want, side="right")) if inside else (0, 0)
        out.append(_roof_cells(xyz[order[a:b]], k, block_cells))
    return out


def block_roof_cells(folder: str, key, block_cells: int, building_only: bool = True, transform=None) -> dict:
    """One block's share of `quakescan.grid.density.planimetric_density`.

    Per density cell of the block (its points with a building ID, or all points): the
    number of points within ROOF_BAND_M of the cell's highest one. Cells whose eight
    neighbours lie in the block are decided here (a histogram of the interior cells'
    counts); cells on the block's edge are returned with the neighbours the block cannot
    see, for the client to decide (`merge_roof_cells`)."""
    key = (int(key[0]), int(key[1]))
    if transform is not None:  # the alignment moves points across block edges (by less than a block)
        return group_roof_cells(folder, [key], block_cells, building_only, transform)[0]
    f = EpochFile(**_epoch_file_args(folder))
    if f.copc:
        rec = read_records(Path(folder), [key], buildings_only=building_only, in_file_order=False)
        return _roof_cells(f.local_xyz(rec["X"], rec["Y"], rec["Z"], np.asarray(_origin(folder))), key, block_cells)
    return _stored_roof_cells(folder, f, block_runs(Path(folder), [key], building_only), key, block_cells)


def _stored_roof_cells(folder: str, f: EpochFile, runs: np.ndarray, square, square_cells: int) -> dict:
    """`block_roof_cells` of the square `square` of `square_cells` cells from the stored runs
    `runs` (`block_store.block_runs` of the blocks in it): each record's cell and height in one
    compiled loop, no coordinates made."""
    from ._record_kernels import cells_and_heights

    rec, _ = read_runs(Path(folder), runs)
    n = len(rec)
    ci, cj, z = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)
    span = np.array([np.iinfo(np.int64).max] * 2 + [np.iinfo(np.int64).min] * 2, dtype=np.int64)
    scales, shifts = f.frame(np.asarray(_origin(folder)))
    cells_and_heights(rec, scales, shifts, DENSITY_CELL_M, ci, cj, z, 0, span)
    return _roof_cells_of(ci, cj, z, span, square, square_cells)


def _roof_cells(xyz: np.ndarray, key, block_cells: int) -> dict:
    """`block_roof_cells` of the points `xyz` (local frame) that lie in block `key`."""
    if not len(xyz):
        return _roof_cells_of(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), None, key, block_cells)
    cells = np.floor(xyz[:, :2] / DENSITY_CELL_M).astype(np.int64)
    span = np.concatenate([cells.min(axis=0), cells.max(axis=0)])
    return _roof_cells_of(cells[:, 0], cells[:, 1], xyz[:, 2], span, key, block_cells)


def _roof_cells_of(ci, cj, z, span, key, block_cells: int) -> dict:
    """`block_roof_cells` of points given by their density cells (ci, cj) and heights z
    (`span`: the cells' min i, min j, max i, max j): the block's cells as a dense grid, each
    cell's top-band count compiled (`roof_band_counts`), its neighbours looked up by
    shifting the grid."""
    from ..grid.density import roof_band_counts

    out = {"key": list(key), "hist": {}, "edge": [], "sum": 0, "cells": 0, "occupied_edge": []}
    if not len(z):
        return out
    b0 = np.asarray(key, dtype=np.int64) * int(block_cells)
    b1 = b0 + int(block_cells) - 1
    span = np.asarray(span, dtype=np.int64)
    lo = np.minimum(span[:2], b0)  # a block's points lie in its cells; the grid holds any that do not
    sx, sy = (np.maximum(span[2:], b1) - lo + 1).tolist()
    counts = roof_band_counts((ci - lo[0]) * sy + (cj - lo[1]), z, sx * sy)
    counts = counts.reshape(sx, sy)
    occupied = counts > 0
    gi, gj = np.arange(sx) + lo[0], np.arange(sy) + lo[1]
    in_block = ((gi >= b0[0]) & (gi <= b1[0]))[:, None] & ((gj >= b0[1]) & (gj <= b1[1]))[None, :]
    occ_p, in_p = np.pad(occupied, 1), np.pad(in_block, 1)
    ok = occupied.copy()  # every neighbour inside the block occupied
    outside_any = np.zeros_like(occupied)
    for dx, dy in NEIGHBOURS:
        nb_in = in_p[1 + dx:1 + dx + sx, 1 + dy:1 + dy + sy]
        ok &= ~nb_in | occ_p[1 + dx:1 + dx + sx, 1 + dy:1 + dy + sy]
        outside_any |= ~nb_in
    values, n = np.unique(counts[ok & ~outside_any], return_counts=True)
    out["hist"] = dict(zip(values.tolist(), n.tolist()))
    for a, b in zip(*np.nonzero(ok & outside_any)):
        i, j = int(gi[a]), int(gj[b])
        outside = [(i + dx, j + dy) for dx, dy in NEIGHBOURS
                   if not (b0[0] <= i + dx <= b1[0] and b0[1] <= j + dy <= b1[1])]
        out["edge"].append([i, j, int(counts[a, b]), outside])
    out["sum"], out["cells"] = int(counts[occupied].sum()), int(occupied.sum())
    rim = np.isin(gi, (b0[0], b1[0]))[:, None] | np.isin(gj, (b0[1], b1[1]))[None, :]
    out["occupied_edge"] = [[int(gi[a]), int(gj[b])] for a, b in zip(*np.nonzero(occupied & rim))]
    return out


def stream_part(folder: str, epoch_json: dict, origin: list, part: int, start: int, stop: int, block_cells: int,
                footprints: dict | None, with_hulls: bool, sample, map_step: int | None, chunk_points: int,
                pair_bytes: int | None = None):
    """Points start..stop of an epoch's file streamed into the file and index of `part` under
    `folder` (`quakescan.distributed.streaming.stream_epoch`): one of the tasks that tile an
    epoch in parallel. `footprints`: {"path", "id_field"} read here (building IDs by
    footprint), or None (the file's building_id). `pair_bytes`: both epochs' file sizes,
    which decide on the worker's own machine whether the streamed pages are dropped from its
    page cache (`streaming.page_cache_cannot_hold`). Returns the part's EpochStats."""
    from .streaming import page_cache_cannot_hold, stream_epoch

    fp = None if footprints is None else worker_footprints(footprints["path"], footprints.get("id_field"))
    return stream_epoch(EpochFile(**epoch_json), np.asarray(origin, dtype=np.float64), Path(folder),
                        block_cells=block_cells, footprints=fp, with_hulls=with_hulls,
                        sample=None if sample is None else tuple(sample), map_step=map_step,
                        chunk_points=chunk_points, part=part, start=start, stop=stop,
                        drop_read_pages=page_cache_cannot_hold(pair_bytes))


def graded_part(out_file: str, epoch_json: dict, origin: list, start: int, stop: int, footprints: dict | None,
                transform, grade_by_building: dict, max_id: int, chunk_points: int) -> int:
    """Points start..stop of the post-event file as point records of the graded cloud
    (`quakescan.results.graded_cloud.grade_records`: every attribute of the file, aligned as the
    tiles saw them, building ID, grade and colour), appended raw to `out_file` (written under
    a temporary name, complete or absent); the client puts the parts' records behind one
    header. Returns the number of points."""
    import laspy

    from ..change.align import apply_transform
    from ..formats.footprints import assign_buildings
    from ..formats.pointcloud import noise_mask
    from ..results.graded_cloud import grade_header, grade_records, source_chunks_format7, source_extra_dims
    from ..runtime.atomic import open_replacing

    f = EpochFile(**epoch_json)
    origin = np.asarray(origin, dtype=np.float64)
    fp = None if footprints is None else worker_footprints(footprints["path"], footprints.get("id_field"))
    n = 0
    with laspy.open(f.path) as reader, open_replacing(Path(out_file), "wb") as out:
        # the records' layout only: the client writes the header
        header = grade_header(Path(out_file), origin, None, max_id, source_extra_dims(reader.header))
        for raw, kept in source_chunks_format7(reader, chunk_points, start, stop):
            xyz = f.local_xyz(raw.array["X"], raw.array["Y"], raw.array["Z"], origin)
            if fp is None:
                from ..formats.pointcloud import checked_building_ids

                ids = np.asarray(checked_building_ids(raw["building_id"], f.path), dtype=np.int64)
            else:  # IDs from the unaligned points, as the tiles got them
                ids = assign_buildings(xyz[:, 0] + origin[0], xyz[:, 1] + origin[1], fp)
            ids[noise_mask(raw.classification)] = 0  # noise is in no building, as in the tiles
            if transform is not None:
                xyz = apply_transform(transform, xyz)
            records = grade_records(out_file, header, origin, grade_by_building, xyz, ids, kept)
            if records is not None:
                out.write(records.array.tobytes())
                n += len(records)
    return n


def merge_roof_cells(parts: list[dict]) -> float:
    """The epoch's planimetric density from every block's `block_roof_cells`: equal to
    `planimetric_density` of the whole epoch (the interquartile mean of integer counts is
    the same whatever order they come in; their sum is exact in float64)."""
    from scipy.stats import trim_mean

    occupied = set()
    for p in parts:
        occupied.update((i, j) for i, j in p.get("occupied_edge", []))
    hist: dict[int, int] = {}
    for p in parts:
        for c, k in p["hist"].items():
            hist[int(c)] = hist.get(int(c), 0) + int(k)
        for i, j, c, outside in p["edge"]:
            if all((a, b) in occupied for a, b in outside):
                hist[int(c)] = hist.get(int(c), 0) + 1
    if hist:
        values = np.repeat(np.array(sorted(hist), dtype=np.int64), [hist[c] for c in sorted(hist)])
        return float(trim_mean(values, 0.25)) / DENSITY_CELL_M ** 2
    cells = sum(p["cells"] for p in parts)
    if not cells:
        return 0.0
    # np.mean of integer counts, as planimetric_density takes it: an exact sum over the cells
    return float(sum(p["sum"] for p in parts) / cells) / DENSITY_CELL_M ** 2


def describe_tile_task(store: str, tile: dict, settings_json: dict, geometry: dict | None, alignment: list | None,
                       workers: int = -1, facing_counts=None) -> dict:
    """The rows of one tile's buildings, read from the block files of both epochs.

    `tile`: {"bids": [...], "box": [[x, y], [x, y]] the x/y box of everything the tile's
    buildings' descriptors may read, "block_cells": int}. Raises TileReachError when a
    nearest post-event point lies beyond the box (the client widens it and asks again).

    One part of a tile split to fit the worker's memory is described twice: first for its
    share of the counts lost walls are judged by (`tile["count_facing"]`: returns them as
    "facing_counts", no rows), then with `facing_counts` the whole tile's sum of them, so its
    rows are those of the whole tile. `workers`: threads of the descriptor kernels (the client
    asks for one: a Dask worker runs one task a thread, the cluster's processes are the
    parallelism)."""
    from ..change.pipeline import describe_tile
    from ..change.settings import PipelineSettings
    from ..change.surface import SurfaceGeometry
    from ..formats.pointcloud import Epoch, without_noise

    settings = PipelineSettings.from_json(settings_json)
    box = np.asarray(tile["box"], dtype=np.float64)
    epochs = []
    for name in ("pre", "post"):
        folder = Path(store) / name
        f = EpochFile(**_epoch_file_args(folder))
        origin = np.asarray(_origin(folder))
        grow = float(tile.get("read_margin", 0.0)) if name == "post" else 0.0  # alignment moves points this far
        rec, xyz = read_box(folder, f, origin, box + np.array([[-grow], [grow]]), int(tile["block_cells"]))
        if name == "post" and alignment is not None:
            from ..change.align import apply_transform

            xyz = apply_transform(alignment, xyz)
            inside = np.all((xyz[:, :2] >= box[0]) & (xyz[:, :2] <= box[1]), axis=1)
            rec, xyz = rec[inside], xyz[inside]
        epochs.append(without_noise(Epoch(xyz, origin, rec["classification"], building_id=rec["building_id"],
                                          source=f.path)))  # as `describe_pair` leaves it out
    pre, post = epochs
    geom = None if geometry is None else SurfaceGeometry(**geometry)
    reach: dict = {}
    counted: dict = {}
    rows = describe_tile(pre, post, tile["bids"], settings, geom, workers=workers, reach=reach,
                         facing_counts=facing_counts, facing_out=counted)
    _check_reach(reach, box, settings, tile.get("whole_post_box"))
    if tile.get("count_facing"):
        return {"key": tile["key"], "facing_counts": counted["facing_counts"].tolist()}
    return {"key": tile["key"], "rows": rows}


def registration_task(store: str, settings_json: dict, align, names: dict, post_bounds, workers: int = -1) -> dict:
    """`quakescan.change.registration.register_samples` in a worker: the registration
    check's ICP is the run's longest single step, and in a worker it runs beside the tiles
    instead of holding up the client (a laptop, often). Returns the record, the
    alignment (or None) and the check's log messages, for the client to show: a worker's log
    is not the user's console. The epochs' samples are read from the stats the tiling saved
    under `store` ("pre.npz", "post.npz"), not sent as data: data scattered to a worker is lost
    with it, a task of files is redone elsewhere. `workers`: the ICP's threads (the client asks
    for one, as for a tile)."""
    import logging

    from ..change import registration
    from ..change.settings import PipelineSettings

    class Keep(logging.Handler):
        def __init__(self):
            super().__init__(logging.INFO)
            self.messages = []

        def emit(self, record):
            self.messages.append((record.levelno, record.getMessage()))

    keep = Keep()
    loggers = [logging.getLogger(registration.__name__), logging.getLogger("quakescan.change.align")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.addHandler(keep)
        lg.setLevel(min(lg.getEffectiveLevel(), logging.INFO))
    summary = dict(names)
    pre_sample, post_sample = (stable_sample(Path(store) / f"{name}.npz") for name in ("pre", "post"))
    try:
        record = registration.register_samples(pre_sample, post_sample, None, PipelineSettings.from_json(settings_json),
                                               align, summary, post_bounds=np.asarray(post_bounds, dtype=np.float64),
                                               workers=workers)
    finally:
        for lg, level in zip(loggers, levels):
            lg.removeHandler(keep)
            lg.setLevel(level)
    return {"record": record, "alignment": summary.get("alignment"), "messages": keep.messages}


def stable_sample(path: Path) -> np.ndarray:
    """The registration check's points of an epoch from its saved stats (only that array is read)."""
    with np.load(path) as arrays:
        return arrays["stable_sample"]


def add_facing_counts(*parts: dict) -> list:
    """The whole tile's counts from its parts' (integers: the same sum in any order)."""
    return np.sum([np.asarray(p["facing_counts"], dtype=np.int64) for p in parts], axis=0).tolist()


def _check_reach(reach: dict, box: np.ndarray, settings, whole_post_box) -> None:
    """The paper's descriptors map each query point to its nearest post-event point and read
    that point's neighbourhood: both must lie inside the box, or the tile is described again."""
    if not reach:
        return
    if whole_post_box is not None:
        w = np.asarray(whole_post_box, dtype=np.float64)
        if np.all(box[0] <= w[0]) and np.all(box[1] >= w[1]):
            return  # the box holds the whole post-event epoch: nothing lies beyond it
    q_lo, q_hi = np.asarray(reach["queries_box"][0]), np.asarray(reach["queries_box"][1])
    clearance = float(min((q_lo - box[0]).min(), (box[1] - q_hi).min()))
    needed = reach["max_distance_m"] + 1.0001 * settings.radius_m
    if needed > clearance:
        raise TileReachError(needed)


def _epoch_file_args(folder) -> dict:
    import json

    return json.loads((Path(folder) / "epoch.json").read_text())["file"]


def _origin(folder) -> list:
    import json

    return json.loads((Path(folder) / "epoch.json").read_text())["origin"]


__all__ = ["TileReachError", "add_facing_counts", "block_roof_cells", "describe_tile_task", "group_roof_cells",
           "merge_roof_cells", "registration_task", "stream_part"]
