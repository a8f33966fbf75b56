"""Change between epochs: nearest-neighbour mapping, the changed/unchanged split, descriptors.

Following Zahs et al. ("Object-specific change feature selection", "Coarse extraction of
changed building parts"):
1. every pre-event point is mapped to its nearest post-event point (kd-tree); the change
   of a feature is post value − pre value, the change in height is z_post − z_pre, and
   the distance to the nearest post point is kept too;
2. per building, k-means with k = 2 on (change in curvature, change in height) splits the
   points into changed and unchanged; a level of detection (LoD) gates the split so that
   an undamaged building is not cut into two clusters of noise: a point can only be
   "changed" if its change exceeds the LoD in height or in curvature, and a building
   whose changed cluster holds no such point has no changed points ("no damage");
3. per building, descriptors are statistics of the change features over its changed
   points, plus the share of changed points.

Buildings are processed one at a time: memory is bounded by the largest building.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError

log = logging.getLogger(__name__)

STATISTICS = ("mean", "median", "std", "p10", "p90")
CLIP_LODS = 10.0
MAX_RING = 2  # rings of grid columns searched before a query goes to the kd-tree


class ChangeError(QuakeScanError):
    """Epochs cannot be compared as given."""


LOD_HEIGHT_RANGE_M = (0.0, 3.0)  # (exclusive, inclusive): above 3 m a collapsed storey is "unchanged"
LOD_CURVATURE_RANGE = (0.0, 10.0)  # 1/m; 10 1/m is the curvature of a 0.1 m sphere


def _is_number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)


def morton_order(xyz: np.ndarray, bits: int = 16) -> np.ndarray:
    """Permutation that sorts points along a 3-D Morton (Z-order) curve.

    Queries in this order visit the kd-tree's nodes coherently (2-3× faster than random order
    on a million points)."""
    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    from ..grid.cells import row_bounds

    lo, hi = row_bounds(xyz)
    span = np.maximum(hi - lo, 1e-9)
    q = ((xyz - lo) / span * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(xyz), np.uint64)
    for b in range(bits):
        for k in range(3):
            code |= ((q[:, k] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + k)
    return np.argsort(code, kind="stable")


def nearest_neighbours(pre_xyz: np.ndarray, post_xyz: np.ndarray, workers: int = -1):
    """Index of the nearest post point for every pre point and the distance to it.

    Both in the same local float64 frame. A compiled column-grid search (`_nn_kernels`),
    exact; queries whose neighbour lies beyond MAX_RING rings of columns (collapsed
    parts: metres away) go to a kd-tree over the post points. BENCHMARKS.md compares it
    with `nearest_neighbours_reference`, the kd-tree alone, which the tests check it against."""
    from . import _nn_kernels as K

    pre_xyz = np.ascontiguousarray(pre_xyz, dtype=np.float64)
    post_xyz = np.ascontiguousarray(post_xyz, dtype=np.float64)
    if len(post_xyz) == 0:
        raise ChangeError("the post-event epoch has no points to map to")
    if len(pre_xyz) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    from .features import STACK_COPIES, duplicate_groups

    groups = duplicate_groups(pre_xyz, STACK_COPIES) if len(pre_xyz) > 1 else None
    if groups is not None:  # coincident queries share their answer: duplicates must not cost n² scans
        first, inverse = groups
        i, d = nearest_neighbours(pre_xyz[first], post_xyz, workers)
        return i[inverse], d[inverse]
    bx = K.bounds_xy(post_xyz)
    lo, span = bx[:2], np.maximum(bx[2:] - bx[:2], 1e-9)
    # ~4 points per column on a single surface: few candidates, short rings
    cell = max(math.sqrt(span[0] * span[1] * 4.0 / len(post_xyz)), 1e-6)
    nx, ny = int(span[0] // cell) + 1, int(span[1] // cell) + 1
    while nx * ny > 4 * len(post_xyz) + 1024:  # a long thin cloud: keep the column table small
        cell *= 2
        nx, ny = int(span[0] // cell) + 1, int(span[1] // cell) + 1
    from ..runtime.workers import kernel_threads

    with kernel_threads(workers):
        order, starts = K.counting_sort(K.column_index(post_xyz, lo[0], lo[1], cell, nx, ny), nx * ny)
        px, py, pz = K.sort_columns_by_z(order, starts, post_xyz)
        # queries in their own order: scans are coherent along scan lines already
        idx = np.empty(len(pre_xyz), np.int64)
        dist = np.empty(len(pre_xyz))
        K.nearest(pre_xyz, px, py, pz, order, starts, lo[0], lo[1], cell, nx, ny, MAX_RING, idx, dist)
    q = pre_xyz
    far = np.flatnonzero(idx < 0)
    if len(far):
        idx[far], dist[far] = nearest_neighbours_reference(q[far], post_xyz, workers=workers)
    return idx, dist


def nearest_neighbours_reference(pre_xyz: np.ndarray, post_xyz: np.ndarray, workers: int = -1):
    """The same with scipy's kd-tree, queries in Morton order (the previous implementation)."""
    from scipy.spatial import cKDTree

    if len(post_xyz) == 0:
        raise ChangeError("the post-event epoch has no points to map to")
    tree = cKDTree(post_xyz, balanced_tree=False, compact_nodes=False)
    order = morton_order(pre_xyz)
    dist = np.empty(len(pre_xyz))
    idx = np.empty(len(pre_xyz), np.int64)
    d, i = tree.query(pre_xyz[order], k=1, workers=workers)
    dist[order], idx[order] = d, i
    return idx, dist


@dataclass
class SplitSettings:
    """Changed/unchanged split. LoDs in the units of the change (metres for height, 1/m for
    curvature).

    Defaults measured on the paper's generic city (112 buildings) scanned twice with the
    paper's survey (new range noise, same buildings) and against its heavy-damage scene
    (tests/test_pipeline.py holds the small version): |Δheight| p99.9 = 0.04 m, |Δcurvature|
    at r = 1.5 m p99.9 = 0.13 1/m (roof edges, where two samplings of a corner fit
    different quadrics). A building whose changed points are fewer than
    `min_changed_share` of its points is unchanged: scattered points beyond the LoD are
    sampling noise. Measured trade-off (undamaged rescans flagged / heavy buildings with no
    change found, of 112 each): share 0: 62 / 3; 0.002: 1 / 12; 0.003: 0 / 17;
    0.005: 0 / 29; 0.01: 0 / 47.
    """

    lod_height_m: float = 0.3
    lod_curvature: float = 0.2
    curvature_feature: str = "curvature"
    min_changed_share: float = 0.003
    seed: int = 0

    def __post_init__(self):
        # A level of detection above a storey's height (or a curvature of a 10 cm sphere) calls a
        # collapsed storey unchanged: every building would be "no damage". Beyond these ranges a
        # value is a typo or an edited model file, never a measurement (`quakescan.change.lod` measures them).
        for name, value, (low, high), unit in (("lod_height_m", self.lod_height_m, LOD_HEIGHT_RANGE_M, "m"),
                                               ("lod_curvature", self.lod_curvature, LOD_CURVATURE_RANGE, "1/m")):
            if not (_is_number(value) and low < value <= high):
                raise ChangeError(f"level of detection {name} must lie in ({low:g}, {high:g}] {unit}, got {value!r}")
        if not (_is_number(self.min_changed_share) and 0 <= self.min_changed_share < 1):
            raise ChangeError(f"min_changed_share must be a share in [0, 1), got {self.min_changed_share!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2 ** 32:
            raise ChangeError(f"split seed must be an integer in [0, 2**32), got {self.seed!r}")
        from .features import FEATURES

        if self.curvature_feature not in FEATURES:
            raise ChangeError(f"curvature_feature {self.curvature_feature!r} is not a point feature")

    def to_json(self) -> dict:
        return dict(self.__dict__)


@dataclass
class BuildingChange:
    building_id: int
    n_pre: int
    n_post: int
    changed: np.ndarray  # (n_pre,) bool, per pre point of the building
    share_changed: float
    descriptors: dict = field(default_factory=dict)


def split_changed(d_curv: np.ndarray, d_height: np.ndarray, settings: SplitSettings,
                  lod_height=None, lod_curvature=None) -> np.ndarray:
    """Changed mask for one building's points from k-means (k = 2) and the LoD gate.

    Features are scaled by their LoDs, so "one LoD" weighs the same in both. The cluster
    whose centre lies farther from zero change is the changed one; only its points that
    exceed an LoD count as changed. `lod_height`/`lod_curvature` (per point, optional) are
    levels of detection that the points' own neighbourhoods give (`quakescan.change.m3c2`); the
    settings' constants stay as floors."""
    from sklearn.cluster import KMeans

    n = len(d_height)
    lh = settings.lod_height_m if lod_height is None else np.maximum(lod_height, settings.lod_height_m)
    lc = settings.lod_curvature if lod_curvature is None else np.maximum(lod_curvature, settings.lod_curvature)
    with np.errstate(invalid="ignore"):
        beyond = (np.abs(d_height) > lh) | (np.abs(d_curv) > lc)
    if n < 2 or not beyond.any():
        return np.zeros(n, bool)
    x = np.column_stack([d_curv / lc, d_height / lh])
    # Beyond CLIP_LODS a change is a change for sure; clipping keeps a handful of extreme
    # values (curvature fitted to rubble reaches hundreds of LoDs) from taking a cluster of
    # their own and leaving the bulk of a collapsed building "unchanged".
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0), -CLIP_LODS, CLIP_LODS)
    if np.ptp(x, axis=0).max() == 0:
        return np.zeros(n, bool)
    km = KMeans(n_clusters=2, n_init=4, random_state=settings.seed).fit(x)
    centre_norm = np.linalg.norm(km.cluster_centers_, axis=1)
    changed_label = int(np.argmax(centre_norm))
    changed = (km.labels_ == changed_label) & beyond
    if changed.sum() < settings.min_changed_share * n:
        return np.zeros(n, bool)
    return changed


def feature_changes(pre: dict, post: dict, nn: np.ndarray) -> dict:
    """Change of every feature both epochs have: post[nn] − pre, (n_pre,) each."""
    out = {}
    for name, values in pre.items():
        if name in post:
            out[name] = np.asarray(post[name])[nn] - np.asarray(values)
    return out


def building_changes(pre_ids: np.ndarray, post_ids: np.ndarray, changes: dict, d_height: np.ndarray,
                     distance: np.ndarray, settings: SplitSettings, min_points: int = 1,
                     lod_height=None, lod_curvature=None) -> list[BuildingChange]:
    """Split and describe every building with pre-event points (ID > 0); `lod_height` and
    `lod_curvature` are optional per-point levels of detection (see `split_changed`)."""
    if settings.curvature_feature not in changes:
        raise ChangeError(f"the split needs the change of {settings.curvature_feature!r}; "
                          f"available: {sorted(changes)}")
    d_curv = changes[settings.curvature_feature]
    order = np.argsort(pre_ids, kind="stable")
    ids_sorted = pre_ids[order]
    uniq, starts = np.unique(ids_sorted, return_index=True)
    ends = np.append(starts[1:], len(order))
    post_counts = dict(zip(*np.unique(post_ids, return_counts=True)))
    result = []
    for bid, a, b in zip(uniq, starts, ends):
        if bid <= 0:
            continue
        rows = order[a:b]
        if len(rows) < min_points:
            continue
        changed = split_changed(d_curv[rows], d_height[rows], settings,
                                None if lod_height is None else lod_height[rows],
                                None if lod_curvature is None else lod_curvature[rows])
        share = float(changed.mean()) if len(rows) else 0.0
        desc = {"share_changed": share}
        sel = rows[changed]
        columns = dict(changes)
        columns["height"] = d_height
        columns["distance"] = distance
        for name, values in columns.items():
            v = values[sel]
            v = v[np.isfinite(v)]
            for stat in STATISTICS:
                desc[f"{name}_{stat}"] = _stat(v, stat)
        result.append(BuildingChange(int(bid), len(rows), int(post_counts.get(bid, 0)), changed, share, desc))
    return result


def _stat(v: np.ndarray, stat: str) -> float:
    """A statistic of the changed points; 0 when there are none (no change = no damage)."""
    if len(v) == 0:
        return 0.0
    if stat == "mean":
        return float(v.mean())
    if stat == "median":
        return float(np.median(v))
    if stat == "std":
        return float(v.std())
    if stat == "p10":
        return float(np.percentile(v, 10))
    if stat == "p90":
        return float(np.percentile(v, 90))
    raise ValueError(stat)


def lod_from_noise(sigma_registration_m: float, spacing_m: float, k: float = 1.96) -> float:
    """Level of detection in height from the registration error and the sampling: two epochs
    each sampled at `spacing_m` (a surface point is matched to a neighbour up to ~half the
    spacing away) and misregistered by σ: k·√(2σ² + (spacing/2)²)."""
    return k * math.sqrt(2 * sigma_registration_m ** 2 + (spacing_m / 2) ** 2)
