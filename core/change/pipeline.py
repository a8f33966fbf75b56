"""From a pre-/post-event pair of point clouds to one row of change descriptors per building.

The steps of Zahs et al. in the order they run here:

1. buildings are grouped into square tiles by the centre of their pre-event points' x/y box,
   so a city-size pair is processed a tile at a time: memory holds the two epochs'
   coordinates and one tile's neighbourhoods, never a city's worth of features (a
   distributed run, `quakescan.distributed`, gives each tile to a worker that holds only
   the points the tile's descriptors read);
2. per tile: features of the pre-event building points (neighbourhoods taken from *all*
   pre-event points near them, ground included, as CloudCompare does on a whole cloud),
   the nearest post-event point of each (exact: a point whose neighbour could lie outside
   the searched box is searched again in a box that surely holds it), features of those
   post-event points, and the change of each feature, of height and the distance;
3. per building: the LoD-gated k-means split into changed/unchanged points and the
   descriptors of the changed points (`quakescan.change.split`).

Only the point features that the descriptors (and the split) need are computed. The tiles and
the grouping by building are `quakescan.change.tiling`, steps 2 and 3
`quakescan.change.paper_descriptors`, the surface descriptors `quakescan.change.surface`,
what decides them all `quakescan.change.settings`.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..formats.pointcloud import Epoch, without_noise
from ..runtime.progress import ProgressCallback
from .paper_descriptors import paper_descriptors
from .settings import PipelineError, PipelineSettings
from .tiling import GridIndex, box_of, grouped_by_id, id_counts, members_by_id, tile_key, tile_threads

log = logging.getLogger(__name__)

GROUND_CLASS = 2


@dataclass
class BuildingRow:
    """One building of a pair: counts, whether it can be assessed, and its descriptors."""

    building_id: int
    n_pre: int
    n_post: int
    assessable: bool
    reason: str = ""
    descriptors: dict = field(default_factory=dict)
    centre_xy: tuple = (math.nan, math.nan)  # local frame
    # density_pre / density_post (pts/m², planimetric, over the building's cells), coverage
    # (share of its cells with post-event points), cells, area_m2 and lowering_lod_m (what
    # `quakescan.change.detectability` reads), where surfaces were described
    quality: dict = field(default_factory=dict)

    @property
    def share_changed(self) -> float | None:
        return self.descriptors.get("share_changed") if self.assessable else None


def describe_pair(pre: Epoch, post: Epoch, settings: PipelineSettings, *, workers: int = -1,
                  progress: ProgressCallback | None = None, done: dict | None = None,
                  on_tile: Callable[[list], None] | None = None) -> list[BuildingRow]:
    """Descriptor rows of every building of the pair (IDs > 0 in either epoch), tile by tile.

    `done` holds rows of tiles finished by an interrupted run (they are not redone);
    `on_tile` receives the rows of each tile when it is finished (for a checkpoint);
    `progress(done, total)` is called once per building described (`total`: the buildings
    with enough points in both epochs), when its tile is finished.

    Both epochs must carry `building_id` (from the file or from footprints) and share one
    local frame (read the post epoch with the pre epoch's origin)."""
    for e, name in ((pre, "pre"), (post, "post")):
        if e.building_id is None:
            raise PipelineError(f"{e.source}: the {name}-event epoch has no building IDs "
                                "(no building_id dimension and no footprints given)")
    if not np.array_equal(pre.origin, post.origin):
        raise PipelineError(f"{post.source}: epochs are in different local frames; read the post epoch "
                            "with the pre epoch's origin")
    pre, post = without_noise(pre), without_noise(post)  # noise is no surface: not counted, not described
    pre_ids, post_ids = pre.building_id, post.building_id
    uniq_pre, n_pre = id_counts(pre_ids)
    uniq_post, n_post = id_counts(post_ids)
    n_pre_of = dict(zip(uniq_pre.tolist(), n_pre.tolist()))
    n_post_of = dict(zip(uniq_post.tolist(), n_post.tolist()))
    all_ids = sorted(i for i in set(n_pre_of) | set(n_post_of) if i > 0)
    if not all_ids:
        raise PipelineError(f"{pre.source}: no point belongs to a building (all building IDs are 0)")
    rows, ok = rows_by_counts(n_pre_of, n_post_of, settings)
    order, starts = grouped_by_id(pre_ids, uniq_pre)
    ends = starts + n_pre
    where = {int(b): (s, t) for b, s, t in zip(uniq_pre, starts, ends)}
    # Points stacked on one spot (a broken export, a sensor stuck on a line) have no geometry:
    # the features of such a building are undefined and "no change" would read as no damage.
    post_order, post_starts = grouped_by_id(post_ids, uniq_post)
    post_start = dict(zip(uniq_post.tolist(), post_starts.tolist()))
    for bid in list(ok):
        s, t = where[bid]
        p0 = post_start[bid]
        why = _degenerate(pre.xyz, order[s:t], post.xyz, post_order[p0:p0 + n_post_of[bid]], settings)
        if why:
            rows[bid] = BuildingRow(bid, n_pre_of[bid], n_post_of[bid], False, why)
            ok.remove(bid)
    del post_order, post_start  # 4 bytes a post-event point, not needed by the tiles
    centres = {}
    tiles: dict[tuple, list[int]] = {}
    for bid in ok:
        s, t = where[bid]
        xy = pre.xyz[order[s:t], :2]
        centres[bid] = xy.mean(axis=0)
        tiles.setdefault(tile_key(xy.min(axis=0), xy.max(axis=0), settings.tile_m), []).append(bid)

    pre_index = GridIndex(pre.xyz[:, :2], settings.tile_m / 4)
    post_index = GridIndex(post.xyz[:, :2], settings.tile_m / 4)
    geometry = _surface_geometry(pre, post, settings)
    total = len(ok)
    done = done or {}
    finished = 0
    todo = []
    for key in sorted(tiles):
        bids = tiles[key]
        if all(b in done for b in bids):
            for b in bids:
                rows[b] = done[b]
            finished = _report_buildings(progress, finished, len(bids), total)
        else:
            todo.append(bids)

    def describe(bids, kernel_workers):
        members = {b: order[where[b][0]:where[b][1]] for b in bids}
        return _describe_tile(pre, post, pre_index, post_index, bids, members, settings, geometry, kernel_workers)

    def finish(tile_rows):
        nonlocal finished
        for r in tile_rows:
            r.n_pre, r.n_post = n_pre_of.get(r.building_id, 0), n_post_of.get(r.building_id, 0)
            r.centre_xy = tuple(centres[r.building_id].tolist())
            rows[r.building_id] = r
        if on_tile:
            on_tile(tile_rows)
        finished = _report_buildings(progress, finished, len(tile_rows), total)

    # Largest tiles first: two threads then finish together instead of one waiting on the
    # last big tile (rows are keyed by building: the order changes nothing else).
    todo.sort(key=lambda bids: -sum(n_pre_of[b] + n_post_of.get(b, 0) for b in bids))
    # The first tile alone, its kernels on every thread asked for: it loads numba's threading
    # layer, which then says whether tiles may run side by side.
    if todo:
        finish(describe(todo[0], workers))
    threads = tile_threads(workers, len(todo) - 1)
    if threads <= 1:
        for bids in todo[1:]:
            finish(describe(bids, workers))
    else:
        # Tiles side by side, one kernel thread each: much of a tile's time is numpy outside
        # the numba kernels, which one thread per tile keeps busy (results do not depend on
        # the order: rows are keyed by building).
        from concurrent.futures import ThreadPoolExecutor, as_completed

        with ThreadPoolExecutor(max_workers=threads) as pool:
            for fut in as_completed([pool.submit(describe, bids, 1) for bids in todo[1:]]):
                finish(fut.result())
    return [quality_gate(rows[b], settings) for b in all_ids]


def rows_by_counts(n_pre_of: dict, n_post_of: dict, settings: PipelineSettings) -> tuple[dict, list]:
    """({building ID: row} of the buildings with too few points to describe, the IDs of the
    others), from each epoch's {building ID: points}; IDs <= 0 are no building."""
    rows: dict[int, BuildingRow] = {}
    ok = []
    for bid in sorted(i for i in set(n_pre_of) | set(n_post_of) if i > 0):
        a, b = n_pre_of.get(bid, 0), n_post_of.get(bid, 0)
        if a < settings.min_points_pre:
            rows[bid] = BuildingRow(bid, a, b, False, f"{a} pre-event points < {settings.min_points_pre}")
        elif b < settings.min_points_post:
            rows[bid] = BuildingRow(bid, a, b, False, f"{b} post-event points < {settings.min_points_post} "
                                    "(not covered by the post-event cloud?)")
        else:
            ok.append(bid)
    return rows, ok


def describe_tile(pre: Epoch, post: Epoch, bids: Sequence[int], settings: PipelineSettings, geometry, *,
                  workers: int = -1, reach: dict | None = None, facing_counts=None,
                  facing_out: dict | None = None) -> list[BuildingRow]:
    """Rows of the buildings `bids` of one tile, from epochs that hold at least every point
    their descriptors read: what a distributed worker runs on its tile's points
    (`quakescan.distributed`). `geometry`: the whole pair's, which one tile cannot know.
    The rows carry centres; counts and the quality gate are the caller's. `reach`, when
    given, receives how far the paper's descriptors read ("queries_box": the x/y box of their
    query points; "max_distance_m": the farthest nearest post-event point), so a caller
    holding only part of the epochs can check that it held enough. `facing_out` and
    `facing_counts`: the counts the surface descriptors judge lost walls by, out of this call
    and into it (`quakescan.change.surface.describe_surfaces`), for a tile described in parts.

    A building whose points coincide (fewer distinct positions than the minimum counts, or
    most of them on one spot: `_degenerate`) is not assessable, as in `describe_pair`; the
    others are described together."""
    pre_ids, post_ids = pre.building_id, post.building_id
    rows, ok, members = [], [], {}
    pre_of, post_of = members_by_id(pre_ids), members_by_id(post_ids)
    for bid in sorted(int(b) for b in bids):
        m, p = pre_of(bid), post_of(bid)
        why = _degenerate(pre.xyz, m, post.xyz, p, settings)
        if why:
            rows.append(BuildingRow(bid, len(m), len(p), False, why))
        else:
            ok.append(bid)
            members[bid] = m
    if ok:
        pre_index = GridIndex(pre.xyz[:, :2], settings.tile_m / 4)
        post_index = GridIndex(post.xyz[:, :2], settings.tile_m / 4)
        for r in _describe_tile(pre, post, pre_index, post_index, ok, members, settings, geometry, workers,
                                reach, facing_counts, facing_out):
            r.centre_xy = tuple(pre.xyz[members[r.building_id], :2].mean(axis=0).tolist())
            rows.append(r)
    return rows


def _report_buildings(progress, finished: int, n: int, total: int) -> int:
    """Count the buildings of a finished tile one by one: progress is in buildings, whatever
    the tiling (a tile's buildings are described together, so they finish together)."""
    for _ in range(n):
        finished += 1
        if progress:
            progress(finished, total)
    return finished


def _degenerate(pre_xyz, pre_members, post_xyz, post_members, settings) -> str:
    """Why a building's points are no surface to describe ("" when they are one): fewer
    distinct positions than the model needs, or most of an epoch's points on one x/y spot."""
    for xyz, members, minimum, name in ((pre_xyz, pre_members, settings.min_points_pre, "pre"),
                                        (post_xyz, post_members, settings.min_points_post, "post")):
        n = len(members)
        distinct = _few_distinct(xyz, members, minimum)
        if distinct is not None:
            return f"{distinct} distinct {name}-event positions < {minimum} (of {n} points, the others coincide)"
        stacked = _stacked_on_one_spot(xyz, members)
        if stacked:
            return (f"{stacked} of its {n} {name}-event points lie on one x/y spot "
                    "(a stuck sensor or a broken export, not a surface)")
    return ""


STACK_CELL_M = 0.01  # points closer than this in x/y are on one spot
STACKED_SHARE = 0.5  # an epoch with more of a building's points on one spot is no survey of it


def _stacked_on_one_spot(xyz: np.ndarray, members: np.ndarray) -> int:
    """The number of `members` on their most common x/y spot when that is more than
    STACKED_SHARE of them, else 0. No scan puts half a roof's returns within a centimetre
    (a wall's returns spread along the wall): such a pile would outweigh the building's real
    returns in every count and raster. An even sample of 1024 decides almost every building."""
    n = len(members)
    if n == 0:
        return 0

    def mode_count(idx):
        cells = np.floor(xyz[idx, :2] / STACK_CELL_M).astype(np.int64)
        return int(np.unique(cells, axis=0, return_counts=True)[1].max())

    if n > 1024:
        sample = members[np.linspace(0, n - 1, 1024).astype(np.int64)]
        if mode_count(sample) <= STACKED_SHARE / 2 * len(sample):
            return 0
    top = mode_count(members)
    return top if top > STACKED_SHARE * n else 0


def _few_distinct(xyz: np.ndarray, members: np.ndarray, minimum: int) -> int | None:
    """The number of distinct positions of the points `members` when it is below `minimum`,
    else None. An even sample of 4 × minimum points decides almost every building at once;
    only a building whose sample repeats itself is counted in full."""
    if len(members) > 4 * minimum:
        sample = members[np.linspace(0, len(members) - 1, 4 * minimum).astype(np.int64)]
        if len(np.unique(xyz[sample], axis=0)) >= minimum:
            return None
    n = len(np.unique(xyz[members], axis=0))
    return n if n < minimum else None


def _surface_geometry(pre: Epoch, post: Epoch, settings: PipelineSettings):
    """Grid and cylinder sizes of the pair, from its epochs' building-point densities
    (`quakescan.distributed` finds the same densities block by block)."""
    if settings.surface is None:
        return None
    from ..grid.density import planimetric_density
    from .surface import SurfaceGeometry

    d_pre = planimetric_density(pre.xyz, pre.building_id > 0)
    d_post = planimetric_density(post.xyz, post.building_id > 0)
    if d_post == 0.0:  # a post-event epoch without building points (all collapsed, or footprints missed)
        d_post = planimetric_density(post.xyz)
    return SurfaceGeometry.for_pair(settings.surface, d_pre, d_post)


def quality_gate(row: BuildingRow, settings: PipelineSettings) -> BuildingRow:
    """Not assessable where the data are sparser or cover less than the model was made for."""
    if not row.assessable or not row.quality:
        return row
    density = min(row.quality.get("density_pre", math.inf), row.quality.get("density_post", math.inf))
    coverage = row.quality.get("coverage", 1.0)
    if density < settings.min_density_pts_m2:
        row.assessable = False
        # rounded down: a density just under the limit never reads as equal to it ("1.9 < 1.9")
        row.reason = f"density {math.floor(density * 100) / 100:.2f} pts/m² < {settings.min_density_pts_m2:g}"
    elif coverage < settings.min_coverage:
        row.assessable = False
        row.reason = f"post-event coverage {100 * coverage:.0f} % < {100 * settings.min_coverage:.0f} %"
    elif row.quality.get("cells", math.inf) < settings.min_cells:
        row.assessable = False
        row.reason = (f"footprint of {row.quality['cells']} raster cells < {settings.min_cells}: "
                      "too small for the sparser epoch's density")
    return row


def _describe_tile(pre, post, pre_index, post_index, bids, members, settings: PipelineSettings, geometry,
                   workers, reach: dict | None = None, facing_counts=None,
                   facing_out: dict | None = None) -> list[BuildingRow]:
    """Descriptor rows of the buildings of one tile (counts and centres are the caller's)."""
    descriptors = {b: {} for b in bids}
    quality = {b: {} for b in bids}
    cores = None
    if settings.surface is not None:
        from .surface import describe_surfaces, region_margin

        allpts = np.concatenate([members[b] for b in bids])
        box = box_of(pre.xyz[allpts, :2], region_margin(settings.surface, geometry))
        pre_r = pre_index.query(pre.xyz[:, :2], box)
        post_r = post_index.query(post.xyz[:, :2], box)
        ground = pre.classification[pre_r] == GROUND_CLASS if pre.classification is not None else None
        surf, cores, qual = describe_surfaces(pre.xyz[pre_r], pre.building_id[pre_r], ground, post.xyz[post_r],
                                              bids, settings.surface, geometry, workers=workers,
                                              quality=True, facing_counts=facing_counts, facing_out=facing_out,
                                              wanted=settings.surface_descriptors,
                                              groups={b: np.searchsorted(pre_r, members[b]) for b in bids})
        for b in bids:
            descriptors[b].update({k: surf[b][k] for k in settings.surface_descriptors})
            quality[b] = qual[b]
    if settings.paper_descriptors:
        for b, d in paper_descriptors(pre, post, pre_index, post_index, bids, members, settings, cores,
                                       workers, reach).items():
            descriptors[b].update(d)
    return [BuildingRow(b, 0, 0, True, "", descriptors[b], quality=quality[b]) for b in bids]


def descriptor_matrix(rows: Sequence[BuildingRow], names: Sequence[str]) -> np.ndarray:
    """(n, len(names)) float64 of the assessable rows' descriptors, in the model's column order."""
    return np.array([[r.descriptors[n] for n in names] for r in rows], dtype=np.float64).reshape(len(rows),
                                                                                                 len(names))
