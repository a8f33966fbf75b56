"""From a pre-/post-event pair of point clouds to one row of change descriptors per building.

The steps of Zahs et al. in the order they run here:

1. buildings are grouped into square tiles by the centre of their pre-event points, so a
   city-size pair is processed a tile at a time: memory holds the two epochs' coordinates
   and one tile's neighbourhoods, never a city's worth of features;
2. per tile: features of the pre-event building points (neighbourhoods taken from *all*
   pre-event points near them, ground included, as CloudCompare does on a whole cloud),
   the nearest post-event point of each (exact: a point whose neighbour could lie outside
   the searched box is searched again in a box that surely holds it), features of those
   post-event points, and the change of each feature, of height and the distance;
3. per building: the LoD-gated k-means split into changed/unchanged points and the
   descriptors of the changed points (`core.change`).

Only the point features that the descriptors (and the split) need are computed.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .change import STATISTICS, SplitSettings, building_changes, nearest_neighbours
from .errors import QuakeScanError
from .features import FEATURES, compute_features
from .pointcloud import Epoch

log = logging.getLogger(__name__)

# The paper's robust change features (planarity, surface variation, point density, number
# of neighbours, surface density, volume density, roughness, z rank, z range, normal).
PAPER_FEATURES = ("planarity", "surface_variation", "point_density", "num_neighbours", "surface_density",
                  "volume_density", "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z")
# Changes that are not point features but are described like them.
EXTRA_CHANGES = ("height", "distance")
DEFAULT_RADIUS_M = 1.5
GROUND_CLASS = 2


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

    def __post_init__(self):
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise PipelineError(f"radius must be a positive number of metres, got {self.radius_m!r}")
        unknown = [f for f in self.point_features if f not in FEATURES]
        if unknown:
            raise PipelineError(f"unknown point features {unknown}; known: {', '.join(FEATURES)}")
        if not self.tile_m > 2 * self.radius_m:
            raise PipelineError(f"tile size {self.tile_m} m must exceed twice the radius {self.radius_m} m")
        k = self.core_point_step
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise PipelineError(f"core point step must be a positive integer (1 = every point), got {k!r}")

    @property
    def computed_features(self) -> tuple:
        """Point features to compute: the described ones and the split's curvature."""
        names = list(self.point_features)
        if self.split.curvature_feature not in names:
            names.append(self.split.curvature_feature)
        return tuple(names)

    def descriptor_names(self) -> list[str]:
        """Columns of the descriptor table, in the order a model is trained on."""
        cols = ["share_changed"]
        for name in (*self.point_features, *EXTRA_CHANGES):
            cols += [f"{name}_{s}" for s in STATISTICS]
        return cols

    def to_json(self) -> dict:
        return {"radius_m": self.radius_m, "point_features": list(self.point_features),
                "split": self.split.to_json(), "min_points_pre": self.min_points_pre,
                "min_points_post": self.min_points_post, "tile_m": self.tile_m,
                "core_point_step": int(self.core_point_step)}

    @classmethod
    def from_json(cls, d: dict) -> PipelineSettings:
        try:
            return cls(radius_m=float(d["radius_m"]), point_features=tuple(d["point_features"]),
                       split=SplitSettings(**d["split"]), min_points_pre=int(d["min_points_pre"]),
                       min_points_post=int(d["min_points_post"]), tile_m=float(d.get("tile_m", 150.0)),
                       core_point_step=int(d.get("core_point_step", 1)))  # absent in older models
        except (KeyError, TypeError, ValueError) as e:
            raise PipelineError(f"incomplete pipeline settings ({e!r}): {d}") from None


def settings_for_descriptors(names: Sequence[str], radius_m: float, split: dict | None = None,
                             **kw) -> PipelineSettings:
    """Settings that produce the descriptor columns `names` (those a model was trained on).

    Refuses a column that no point feature or change produces: a model for other features."""
    feats, bad = [], []
    for col in names:
        if col == "share_changed":
            continue
        base, _, stat = col.rpartition("_")
        if stat not in STATISTICS or not (base in FEATURES or base in EXTRA_CHANGES):
            bad.append(col)
        elif base in FEATURES and base not in feats:
            feats.append(base)
    if bad:
        raise PipelineError(f"the model asks for descriptors {bad} that this QuakeScan cannot compute "
                            f"(point features: {', '.join(FEATURES)}; statistics: {', '.join(STATISTICS)})")
    return PipelineSettings(radius_m=radius_m, point_features=tuple(feats),
                            split=SplitSettings(**(split or {})), **kw)


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
        self.lo, self.hi = xy.min(axis=0), xy.max(axis=0)
        ij = np.floor((xy - self.lo) / self.cell).astype(np.int64)
        self.dims = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
        key = ij[:, 0] * self.dims[1] + ij[:, 1]
        dtype = np.int32 if len(xy) < 2 ** 31 else np.int64  # halves the index of a city-size cloud
        self.order = np.argsort(key, kind="stable").astype(dtype)
        self.starts = np.searchsorted(key[self.order], np.arange(self.dims[0] * self.dims[1] + 1))

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
    return np.array([xy.min(axis=0) - margin, xy.max(axis=0) + margin])


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
                  progress: Callable[[int, int], None] | None = None, done: dict | None = None,
                  on_tile: Callable[[list], None] | None = None) -> list[BuildingRow]:
    """Descriptor rows of every building of the pair (IDs > 0 in either epoch), tile by tile.

    `done` holds rows of tiles finished by an interrupted run (they are not redone);
    `on_tile` receives the rows of each tile when it is finished (for a checkpoint).

    Both epochs must carry `building_id` (from the file or from footprints) and share one
    local frame (read the post epoch with the pre epoch's origin)."""
    for e, name in ((pre, "pre"), (post, "post")):
        if e.building_id is None:
            raise PipelineError(f"{e.source}: the {name}-event epoch has no building IDs "
                                "(no building_id dimension and no footprints given)")
    if not np.array_equal(pre.origin, post.origin):
        raise PipelineError(f"{post.source}: epochs are in different local frames; read the post epoch "
                            "with the pre epoch's origin")
    pre_ids, post_ids = pre.building_id, post.building_id
    uniq_pre, n_pre = np.unique(pre_ids, return_counts=True)
    uniq_post, n_post = np.unique(post_ids, return_counts=True)
    n_pre_of = dict(zip(uniq_pre.tolist(), n_pre.tolist()))
    n_post_of = dict(zip(uniq_post.tolist(), n_post.tolist()))
    all_ids = sorted(i for i in set(n_pre_of) | set(n_post_of) if i > 0)
    if not all_ids:
        raise PipelineError(f"{pre.source}: no point belongs to a building (all building IDs are 0)")

    rows: dict[int, BuildingRow] = {}
    ok = []
    for bid in all_ids:
        a, b = n_pre_of.get(bid, 0), n_post_of.get(bid, 0)
        if a < settings.min_points_pre:
            rows[bid] = BuildingRow(bid, a, b, False, f"{a} pre-event points < {settings.min_points_pre}")
        elif b < settings.min_points_post:
            rows[bid] = BuildingRow(bid, a, b, False, f"{b} post-event points < {settings.min_points_post} "
                                    "(not covered by the post-event cloud?)")
        else:
            ok.append(bid)

    order = np.argsort(pre_ids, kind="stable")
    starts = np.searchsorted(pre_ids[order], uniq_pre)
    ends = starts + n_pre
    where = {int(b): (s, t) for b, s, t in zip(uniq_pre, starts, ends)}
    centres = {}
    for bid in ok:
        s, t = where[bid]
        centres[bid] = pre.xyz[order[s:t], :2].mean(axis=0)
    tiles: dict[tuple, list[int]] = {}
    for bid in ok:
        key = tuple(np.floor(centres[bid] / settings.tile_m).astype(np.int64).tolist())
        tiles.setdefault(key, []).append(bid)

    pre_index = GridIndex(pre.xyz[:, :2], settings.tile_m / 4)
    post_index = GridIndex(post.xyz[:, :2], settings.tile_m / 4)
    total = len(ok)
    done = done or {}
    finished = 0
    for key in sorted(tiles):
        bids = tiles[key]
        if all(b in done for b in bids):
            for b in bids:
                rows[b] = done[b]
            finished += len(bids)
            if progress:
                progress(finished, total)
            continue
        # every k-th point of each building (its indices ascend: `order` is a stable sort), so no
        # building is left without query points whatever k
        k = settings.core_point_step
        q = np.sort(np.concatenate([order[where[b][0]:where[b][1]:k] for b in bids])).astype(np.int64)
        pre_f = _features_at(pre, pre_index, q, settings, workers)
        box = _box(pre.xyz[q, :2], settings.radius_m)
        nn, dist = _exact_nearest(pre.xyz[q], post, post_index, box, workers)
        uniq_nn, inv = np.unique(nn, return_inverse=True)
        post_f = _features_at(post, post_index, uniq_nn, settings, workers)
        changes = {name: post_f[name][inv] - pre_f[name] for name in settings.computed_features}
        d_height = post.xyz[nn, 2] - pre.xyz[q, 2]
        wanted = set(settings.descriptor_names())
        tile_rows = []
        for bc in building_changes(pre_ids[q], post_ids[nn], changes, d_height, dist, settings.split):
            desc = {k: v for k, v in bc.descriptors.items() if k in wanted}
            tile_rows.append(BuildingRow(bc.building_id, n_pre_of.get(bc.building_id, 0),
                                         n_post_of.get(bc.building_id, 0), True, "", desc,
                                         tuple(centres[bc.building_id].tolist())))
        for r in tile_rows:
            rows[r.building_id] = r
        if on_tile:
            on_tile(tile_rows)
        finished += len(bids)
        if progress:
            progress(finished, total)
    return [rows[b] for b in all_ids]


def descriptor_matrix(rows: Sequence[BuildingRow], names: Sequence[str]) -> np.ndarray:
    """(n, len(names)) float64 of the assessable rows' descriptors, in the model's column order."""
    return np.array([[r.descriptors[n] for n in names] for r in rows], dtype=np.float64).reshape(len(rows),
                                                                                                 len(names))
