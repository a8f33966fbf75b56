"""The paper's descriptors of a tile (Zahs et al.): point features of the pre-event building
points (neighbourhoods from *all* pre-event points near them, ground included, as CloudCompare
does on a whole cloud), the nearest post-event point of each (exact: a point whose neighbour
could lie outside the searched box is searched again in a box that surely holds it), features
of those post-event points, the change of each feature, of height and the distance, and per
building the LoD-gated k-means split into changed/unchanged points and the statistics of the
changed points (`quakescan.change.split`).
"""
from __future__ import annotations

import numpy as np

from ..formats.pointcloud import Epoch
from .features import compute_features
from .settings import PipelineError, PipelineSettings
from .split import building_changes, nearest_neighbours
from .tiling import GridIndex, box_of


def paper_descriptors(pre, post, pre_index, post_index, bids, members, settings: PipelineSettings, cores,
                       workers, reach: dict | None = None) -> dict:
    """The paper's descriptors: point features, nearest-neighbour changes, the LoD-gated split."""
    # every k-th point of each building (its indices ascend: `order` is a stable sort), so no
    # building is left without query points whatever k
    k = settings.core_point_step
    q = np.sort(np.concatenate([members[b][::k] for b in bids])).astype(np.int64)
    pre_f = features_at(pre, pre_index, q, settings, workers)
    box = box_of(pre.xyz[q, :2], settings.radius_m)
    nn, dist = exact_nearest(pre.xyz[q], post, post_index, box, workers)
    if reach is not None and len(q):
        reach["queries_box"] = box_of(pre.xyz[q, :2], 0.0).tolist()
        reach["max_distance_m"] = float(dist.max())
    uniq_nn, inv = np.unique(nn, return_inverse=True)
    post_f = features_at(post, post_index, uniq_nn, settings, workers)
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


def exact_nearest(pre_q: np.ndarray, post: Epoch, post_index: GridIndex, box: np.ndarray, workers: int):
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


def features_at(epoch: Epoch, index: GridIndex, at: np.ndarray, settings: PipelineSettings,
                 workers: int) -> dict:
    """Features of the points `at` (global indices) with neighbourhoods from the whole epoch."""
    r = settings.radius_m
    xy = epoch.xyz[:, :2]
    cloud_idx = index.query(xy, box_of(xy[at], r * 1.0001))
    pos = np.searchsorted(cloud_idx, at)
    return compute_features(epoch.xyz[cloud_idx], r, settings.computed_features, query_index=pos, workers=workers)
