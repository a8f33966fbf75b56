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

Only the point features that the descriptors (and the split) need are computed.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError
from ..formats.pointcloud import Epoch, without_noise
from ..grid.cells import row_bounds
from ..runtime.progress import ProgressCallback
from . import descriptors as registry
from .features import FEATURES, compute_features
from .split import STATISTICS, SplitSettings, building_changes, nearest_neighbours
from .surface import SURFACE_DESCRIPTORS, SurfaceSettings

log = logging.getLogger(__name__)

# The paper's robust change features (planarity, surface variation, point density, number
# of neighbours, surface density, volume density, roughness, z rank, z range, normal).
PAPER_FEATURES = ("planarity", "surface_variation", "point_density", "num_neighbours", "surface_density",
                  "volume_density", "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z")
# Changes that are not point features but are described like them.
EXTRA_CHANGES = ("height", "distance")
DEFAULT_RADIUS_M = 1.5
GROUND_CLASS = 2
# what a per-point level of detection of the curvature change needs of both neighbourhoods
LOD_FEATURES = ("eigenvalue1", "eigenvalue2", "eigenvalue3", "num_neighbours")


# The feature radius a model may use. Below 0.5 m a neighbourhood at UAV spacing (~0.1 m)
# holds too few points for stable eigenvalues; above 10 m it spans whole buildings and
# its cost grows with r². The paper uses 1.0-4.0 m.
RADIUS_RANGE_M = (0.5, 10.0)


def radius_problem(r) -> str | None:
    """What is wrong with a neighbourhood radius (settings, a model file), or None: the one rule."""
    if isinstance(r, bool) or not isinstance(r, (int, float, np.integer, np.floating)) or not (
            math.isfinite(r) and RADIUS_RANGE_M[0] <= r <= RADIUS_RANGE_M[1]):
        return f"must lie in [{RADIUS_RANGE_M[0]:g}, {RADIUS_RANGE_M[1]:g}] m, got {r!r}"
    return None
MAX_MIN_POINTS = 1_000_000
MAX_TILE_M = 10_000.0


class PipelineError(QuakeScanError):
    """A pair of epochs cannot be processed as asked."""


@dataclass
class PipelineSettings:
    """Everything that decides the descriptors; a model stores it and classification reuses it."""

    radius_m: float = DEFAULT_RADIUS_M
    point_features: tuple = PAPER_FEATURES
    split: SplitSettings = field(default_factory=SplitSettings)
    min_points_pre: int = 50   # fewer pre-event points: not assessable
    min_points_post: int = 10  # fewer post-event points: not covered by the post-event flight
    tile_m: float = 150.0
    # > 1: changes only at every k-th pre-event point of each building (neighbourhoods, nearest
    # neighbours and the point counts still use the full clouds): approximate, k times fewer queries
    core_point_step: int = 1
    # The paper's descriptors: statistics of the point features' changes over the changed
    # points of the LoD-gated split (share_changed, <feature>_<statistic>).
    paper_descriptors: bool = True
    # Descriptors of 2.5-D surfaces and M3C2 core points (quakescan.change.surface); None: not computed.
    surface: SurfaceSettings | None = None
    # which surface descriptors are columns (all by default; a model may use fewer)
    surface_descriptors: tuple = SURFACE_DESCRIPTORS
    # The split's levels of detection per point (M3C2 at the nearest core point for the
    # height change, the curvature's standard errors for its change), the split's constants
    # as floors; needs `surface` (its core points). False: the constants alone (the paper).
    per_point_lod: bool = False
    # A building whose sparser epoch is below this planimetric density (pts/m²) or whose
    # footprint the post-event epoch covers less than `min_coverage` is not assessable.
    min_density_pts_m2: float = 0.0
    min_coverage: float = 0.0
    # ... or whose footprint spans fewer raster cells (of the pair's cell size) than this: a shed
    # seen by a sparse epoch gives a handful of cells, where one chance patch is 10 % "change"
    min_cells: int = 0

    def __post_init__(self):
        problem = radius_problem(self.radius_m)
        if problem:
            raise PipelineError(f"radius {problem}")
        if not isinstance(self.split, SplitSettings):
            raise PipelineError(f"split settings must be SplitSettings, got {self.split!r}")
        for name in ("min_points_pre", "min_points_post"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= MAX_MIN_POINTS:
                raise PipelineError(f"{name} must be an integer in [1, {MAX_MIN_POINTS}], got {v!r}")
        if not (isinstance(self.tile_m, (int, float)) and math.isfinite(self.tile_m) and self.tile_m <= MAX_TILE_M):
            raise PipelineError(f"tile size must be a number of metres <= {MAX_TILE_M:g}, got {self.tile_m!r}")
        unknown = [f for f in self.point_features if f not in FEATURES]
        if unknown:
            raise PipelineError(f"unknown point features {unknown}; known: {', '.join(FEATURES)}")
        if not self.tile_m > 2 * self.radius_m:
            raise PipelineError(f"tile size {self.tile_m} m must exceed twice the radius {self.radius_m} m")
        k = self.core_point_step
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise PipelineError(f"core point step must be a positive integer (1 = every point), got {k!r}")
        if isinstance(self.surface, dict):
            self.surface = SurfaceSettings.from_json(self.surface)
        self.surface_descriptors = tuple(self.surface_descriptors)
        known = registry.names()
        unknown = [c for c in self.surface_descriptors if c not in known]
        if unknown:
            raise PipelineError(f"unknown surface descriptors {unknown}; known: {', '.join(known)}")
        if self.per_point_lod and self.surface is None:
            raise PipelineError("per-point levels of detection need the surface settings (their M3C2 core points)")
        if not self.paper_descriptors and self.surface is None:
            raise PipelineError("no descriptors asked for: enable the paper's descriptors or the surface ones")
        if not (math.isfinite(self.min_density_pts_m2) and self.min_density_pts_m2 >= 0):
            raise PipelineError(f"minimum density must be >= 0 pts/m², got {self.min_density_pts_m2!r}")
        if not 0 <= self.min_coverage <= 1:
            raise PipelineError(f"minimum coverage must be a share in [0, 1], got {self.min_coverage!r}")
        if isinstance(self.min_cells, bool) or not isinstance(self.min_cells, (int, np.integer)) or self.min_cells < 0:
            raise PipelineError(f"minimum raster cells must be an integer >= 0, got {self.min_cells!r}")

    @property
    def computed_features(self) -> tuple:
        """Point features to compute: the described ones, the split's curvature and, with
        per-point levels of detection, the eigenvalues and counts they need."""
        if not self.paper_descriptors:
            return ()
        names = list(self.point_features)
        extra = [self.split.curvature_feature] + (list(LOD_FEATURES) if self.per_point_lod else [])
        names += [f for f in extra if f not in names]
        return tuple(names)

    def descriptor_names(self) -> list[str]:
        """Columns of the descriptor table, in the order a model is trained on."""
        cols = []
        if self.paper_descriptors:
            cols.append("share_changed")
            for name in (*self.point_features, *EXTRA_CHANGES):
                cols += [f"{name}_{s}" for s in STATISTICS]
        if self.surface is not None:
            cols += list(self.surface_descriptors)
        return cols

    def to_json(self) -> dict:
        d = {"radius_m": self.radius_m, "point_features": list(self.point_features),
             "split": self.split.to_json(), "min_points_pre": self.min_points_pre,
             "min_points_post": self.min_points_post, "tile_m": self.tile_m,
             "core_point_step": int(self.core_point_step)}
        if self.surface is not None or not self.paper_descriptors or self.per_point_lod:
            # keys older QuakeScans never wrote: only when they differ from those versions
            d.update(paper_descriptors=self.paper_descriptors, per_point_lod=self.per_point_lod,
                     surface=None if self.surface is None else self.surface.to_json(),
                     surface_descriptors=list(self.surface_descriptors))
        if self.min_density_pts_m2 or self.min_coverage:
            d.update(min_density_pts_m2=self.min_density_pts_m2, min_coverage=self.min_coverage)
        if self.min_cells:
            d["min_cells"] = int(self.min_cells)
        return d

    @classmethod
    def from_json(cls, d: dict) -> PipelineSettings:
        try:
            return cls(radius_m=float(d["radius_m"]), point_features=tuple(d["point_features"]),
                       split=SplitSettings(**d["split"]), min_points_pre=int(d["min_points_pre"]),
                       min_points_post=int(d["min_points_post"]), tile_m=float(d.get("tile_m", 150.0)),
                       core_point_step=int(d.get("core_point_step", 1)),  # absent in older models
                       **_newer_keys(d))
        except (KeyError, TypeError, ValueError) as e:
            raise PipelineError(f"incomplete pipeline settings ({e!r}): {d}") from None
        except QuakeScanError as e:
            raise PipelineError(str(e)) from None


def _newer_keys(d: dict) -> dict:
    """Settings that older model files do not hold, with the values those versions used."""
    surface = d.get("surface")
    return {"paper_descriptors": bool(d.get("paper_descriptors", True)),
            "per_point_lod": bool(d.get("per_point_lod", False)),
            "surface": None if surface is None else SurfaceSettings.from_json(surface),
            "surface_descriptors": tuple(d.get("surface_descriptors", SURFACE_DESCRIPTORS)),
            "min_density_pts_m2": float(d.get("min_density_pts_m2", 0.0)),
            "min_coverage": float(d.get("min_coverage", 0.0)),
            "min_cells": int(d.get("min_cells", 0))}


DESCRIPTOR_SETS = ("paper", "surface", "both")


def training_settings(descriptors: str = "surface", *, radius_m: float = 1.5,
                      point_features: Sequence[str] | None = None, split: SplitSettings | None = None,
                      per_point_lod: bool = False) -> PipelineSettings:
    """Settings of a model to train: the paper's descriptors (point features and the split's
    changed share), the density-free surface descriptors of the shipped model, or both.
    `per_point_lod` gates the paper's split by each point's level of detection."""
    if descriptors not in DESCRIPTOR_SETS:
        raise PipelineError(f"descriptors must be one of {DESCRIPTOR_SETS}, got {descriptors!r}")
    surface = None
    extra = {}
    if descriptors in ("surface", "both") or per_point_lod:
        from .surface import NOISE_FREE_DESCRIPTORS

        surface = SurfaceSettings()
        extra["surface_descriptors"] = NOISE_FREE_DESCRIPTORS if descriptors in ("surface", "both") else ()
    return PipelineSettings(radius_m=radius_m, point_features=tuple(point_features or PAPER_FEATURES),
                            split=split or SplitSettings(), paper_descriptors=descriptors in ("paper", "both"),
                            surface=surface, per_point_lod=per_point_lod and descriptors != "surface", **extra)


def settings_for_descriptors(names: Sequence[str], radius_m: float, split: dict | None = None,
                             stored: dict | None = None, **kw) -> PipelineSettings:
    """Settings that produce the descriptor columns `names` (those a model was trained on);
    `stored`: the model's stored pipeline settings (surface settings, per-point LoD, ...).

    Refuses a column that no point feature or change produces: a model for other features."""
    feats, bad = [], []
    known = registry.names()
    surface_cols = [c for c in names if c in known]
    for col in names:
        if col == "share_changed" or col in known:
            continue
        base, _, stat = col.rpartition("_")
        if stat not in STATISTICS or not (base in FEATURES or base in EXTRA_CHANGES):
            bad.append(col)
        elif base in FEATURES and base not in feats:
            feats.append(base)
    if bad:
        raise PipelineError(f"the model asks for descriptors {bad} that this QuakeScan cannot compute "
                            f"(point features: {', '.join(FEATURES)}; statistics: {', '.join(STATISTICS)}; "
                            f"surface descriptors: {', '.join(known)})")
    newer = _newer_keys(stored or {})
    newer["paper_descriptors"] = "share_changed" in names
    newer["surface_descriptors"] = tuple(surface_cols)  # none: surface settings only for per-point LoDs
    if surface_cols and newer["surface"] is None:
        newer["surface"] = SurfaceSettings()
    if not surface_cols and not newer["per_point_lod"]:
        newer["surface"] = None
    for key in list(newer):
        if key in kw:
            newer.pop(key)
    try:
        split_settings = SplitSettings(**(split or {}))
    except TypeError as e:  # a key this QuakeScan does not know
        raise PipelineError(f"split settings {split!r}: {e}") from None
    except QuakeScanError as e:
        raise PipelineError(str(e)) from None
    return PipelineSettings(radius_m=radius_m, point_features=tuple(feats), split=split_settings, **newer, **kw)


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


def _box(xy: np.ndarray, margin: float) -> np.ndarray:
    lo, hi = row_bounds(xy)
    return np.array([lo - margin, hi + margin])


def _exact_nearest(pre_q: np.ndarray, post: Epoch, post_index: GridIndex, box: np.ndarray, workers: int):
    """Nearest post point (global index) and distance for every query, exact although searched
    in a box: a query whose neighbour is farther than the box's edge is searched again in a
    box grown by that distance, until none is left (at worst the whole cloud)."""
    pxy = post.xyz[:, :2]
    idx = np.full(len(pre_q), -1, np.int64)
    dist = np.full(len(pre_q), np.inf)
    todo = np.arange(len(pre_q))
    grow = 0.0
    while len(todo):
        b = np.array([box[0] - grow, box[1] + grow])
        covers_all = bool(np.all(b[0] <= post_index.lo) and np.all(b[1] >= post_index.hi))
        cand = post_index.query(pxy, b)
        if len(cand) == 0:
            if covers_all:
                raise PipelineError(f"{post.source}: the post-event epoch has no points to map to")
            grow = max(2 * grow, 10.0)
            continue
        i, d = nearest_neighbours(pre_q[todo], post.xyz[cand], workers=workers)
        idx[todo], dist[todo] = cand[i], d
        if covers_all:
            break
        q = pre_q[todo, :2]
        edge = np.minimum(np.min(q - b[0], axis=1), np.min(b[1] - q, axis=1))
        todo = todo[d > edge]
        grow = max(2 * grow, float(dist[todo].max()) if len(todo) else 0.0, 10.0)
    return idx, dist


def _features_at(epoch: Epoch, index: GridIndex, at: np.ndarray, settings: PipelineSettings,
                 workers: int) -> dict:
    """Features of the points `at` (global indices) with neighbourhoods from the whole epoch."""
    r = settings.radius_m
    xy = epoch.xyz[:, :2]
    cloud_idx = index.query(xy, _box(xy[at], r * 1.0001))
    pos = np.searchsorted(cloud_idx, at)
    return compute_features(epoch.xyz[cloud_idx], r, settings.computed_features, query_index=pos, workers=workers)


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


def tile_key(lo_xy, hi_xy, tile_m: float) -> tuple[int, int]:
    """The tile of a building: the square of side `tile_m` holding the centre of its
    pre-event points' x/y box. Minimum and maximum are exact in whatever order or chunks the
    points are read (a mean is not), so a streamed, distributed run groups the buildings
    into the same tiles as this process does, and gives the same descriptors."""
    centre = (np.asarray(lo_xy, dtype=np.float64) + np.asarray(hi_xy, dtype=np.float64)) / 2
    return tuple(np.floor(centre / tile_m).astype(np.int64).tolist())


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
        box = _box(pre.xyz[allpts, :2], region_margin(settings.surface, geometry))
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
        for b, d in _paper_descriptors(pre, post, pre_index, post_index, bids, members, settings, cores,
                                       workers, reach).items():
            descriptors[b].update(d)
    return [BuildingRow(b, 0, 0, True, "", descriptors[b], quality=quality[b]) for b in bids]


def _paper_descriptors(pre, post, pre_index, post_index, bids, members, settings: PipelineSettings, cores,
                       workers, reach: dict | None = None) -> dict:
    """The paper's descriptors: point features, nearest-neighbour changes, the LoD-gated split."""
    # every k-th point of each building (its indices ascend: `order` is a stable sort), so no
    # building is left without query points whatever k
    k = settings.core_point_step
    q = np.sort(np.concatenate([members[b][::k] for b in bids])).astype(np.int64)
    pre_f = _features_at(pre, pre_index, q, settings, workers)
    box = _box(pre.xyz[q, :2], settings.radius_m)
    nn, dist = _exact_nearest(pre.xyz[q], post, post_index, box, workers)
    if reach is not None and len(q):
        reach["queries_box"] = _box(pre.xyz[q, :2], 0.0).tolist()
        reach["max_distance_m"] = float(dist.max())
    uniq_nn, inv = np.unique(nn, return_inverse=True)
    post_f = _features_at(post, post_index, uniq_nn, settings, workers)
    changes = {name: post_f[name][inv] - pre_f[name] for name in settings.computed_features}
    d_height = post.xyz[nn, 2] - pre.xyz[q, 2]
    lod_h = lod_c = None
    if settings.per_point_lod:
        d_height, lod_h, lod_c = _per_point_lods(pre.xyz[q], pre.building_id[q], d_height, pre_f, post_f, inv,
                                                 cores)
    wanted = set(settings.descriptor_names())
    out = {}
    for bc in building_changes(pre.building_id[q], post.building_id[nn], changes, d_height, dist, settings.split,
                               lod_height=lod_h, lod_curvature=lod_c):
        out[bc.building_id] = {k: v for k, v in bc.descriptors.items() if k in wanted}
    return out


def _per_point_lods(q_xyz, q_bid, d_height_nn, pre_f, post_f, inv, cores):
    """Surface change and levels of detection per query point.

    The height change is the M3C2 distance of the nearest core point of the same building
    (its surface's change, not a neighbour's height) with that core's level of detection;
    where the core's cylinders are not comparable (the surface left the cylinder) the
    point-to-point change stays, with the floor as LoD (NaN here). The curvature's LoD comes
    from both neighbourhoods' standard errors (quakescan.change.m3c2.curvature_standard_error)."""
    from scipy.spatial import cKDTree

    from .m3c2 import curvature_lod, curvature_standard_error

    d_height = d_height_nn.copy()
    lod_h = np.full(len(q_xyz), np.nan)
    for b, cc in cores.items():
        sel = np.flatnonzero(q_bid == b)
        if len(sel) == 0 or len(cc.xyz) == 0:
            continue
        _, j = cKDTree(cc.xyz).query(q_xyz[sel])
        use = cc.comparable[j]
        d_height[sel[use]] = cc.distance[j[use]]
        lod_h[sel[use]] = cc.lod[j[use]]
    se_pre = curvature_standard_error(pre_f["eigenvalue1"], pre_f["eigenvalue2"], pre_f["eigenvalue3"],
                                      pre_f["num_neighbours"])
    se_post = curvature_standard_error(post_f["eigenvalue1"], post_f["eigenvalue2"], post_f["eigenvalue3"],
                                       post_f["num_neighbours"])[inv]
    # np.maximum with the floor keeps NaN: a NaN level is replaced by the floor in split_changed
    return d_height, np.nan_to_num(lod_h, nan=0.0), np.nan_to_num(curvature_lod(se_pre, se_post), nan=0.0)


def descriptor_matrix(rows: Sequence[BuildingRow], names: Sequence[str]) -> np.ndarray:
    """(n, len(names)) float64 of the assessable rows' descriptors, in the model's column order."""
    return np.array([[r.descriptors[n] for n in names] for r in rows], dtype=np.float64).reshape(len(rows),
                                                                                                 len(names))
