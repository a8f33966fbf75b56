"""Surface change on core points: which of a building's core points changed, which surfaces
are gone, and the building's `m_*` descriptors from them (`quakescan.change.surface` runs the
M3C2 pass these read; the descriptors' meaning is in its docstring and in
`quakescan.change.descriptors`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CoreChange:
    """Per core point of one building: where, how far the surface moved, and whether it counts."""

    xyz: np.ndarray
    distance: np.ndarray
    lod: np.ndarray
    comparable: np.ndarray
    changed: np.ndarray


FACING_BINS = 8  # walls by the direction they face (45 degree sectors); roofs one more bin


def facing_bins(normals: np.ndarray) -> np.ndarray:
    """Bin of each core point: 0..7 walls by azimuth, 8 roofs (|n_z| >= 0.5), -1 undefined."""
    out = np.full(len(normals), -1, np.int64)
    ok = np.all(np.isfinite(normals), axis=1)
    roof = ok & (np.abs(normals[:, 2]) >= 0.5)
    wall = ok & ~roof
    az = np.arctan2(normals[wall, 1], normals[wall, 0])
    out[wall] = np.floor((az + np.pi) / (2 * np.pi) * FACING_BINS).astype(np.int64) % FACING_BINS
    out[roof] = FACING_BINS
    return out


LOST_ALPHA = 0.01  # an empty post-event cylinder counts only where chance gives it < 1 %


def count_by_facing(res, facing: np.ndarray) -> np.ndarray:
    """(FACING_BINS + 1, 2) integers: post- and pre-event points over the M3C2 cylinders of
    the core points facing each way (integers, so parts add up to the whole exactly)."""
    out = np.zeros((FACING_BINS + 1, 2), dtype=np.int64)
    np.add.at(out[:, 0], facing, np.asarray(res.n_post, dtype=np.int64))
    np.add.at(out[:, 1], facing, np.asarray(res.n_pre, dtype=np.int64))
    return out


def lost_surface(res, facing: np.ndarray, outline: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Core points whose surface is gone, not just unobserved.

    Roofs: lost with the post-event epoch seeing through (points below them: the floor
    through a hole, the rubble of a collapse). Walls: an airborne sensor seldom sees behind a
    wall, so a lost wall point must instead be unlikely to be empty by chance given how well
    the post-event flight saw walls facing the same way in this region (`counts`: the ratio
    of post- to pre-event points over all such cylinders, `count_by_facing`): a facade the
    flight hardly saw is not lost. Either way an empty cylinder must be unlikely by chance
    (`LOST_ALPHA`)."""
    ratio_of = counts[:, 0] / np.maximum(counts[:, 1], 1)
    ratio = ratio_of[facing] if len(facing) else np.zeros(0)
    roof = facing == FACING_BINS
    by_chance = res.lost_beyond_chance(ratio, LOST_ALPHA)
    # at the outline a roof cylinder's "behind" reaches past the eave to the ground beside the
    # building: there seeing through proves nothing, so only interior roof points can be lost
    return np.where(roof, by_chance & res.seen_through & ~outline, by_chance)


def core_change(cxyz, normals, res, lost, seen_through, sl, s, spacing, ground: float):
    """Core-point descriptors of one building from its slice `sl` of the M3C2 result (`s`: the run's
    `SurfaceSettings`)."""
    distance, lod_raw = res.distance[sl], res.lod[sl]
    comparable = res.comparable[sl]
    lod = np.maximum(np.nan_to_num(lod_raw, nan=np.inf), s.lod_floor_m)
    d = np.nan_to_num(distance)
    sig = comparable & (np.abs(d) > lod) & res.displaced[sl]
    changed = sig | lost
    # a 95 % test flags single core points of an unchanged surface at random (on real airborne
    # halves of one scan, isolated points: 33 of 40 buildings with any); damage is areal
    from . import _patch_kernels as K

    keys = K.voxel_keys(cxyz, spacing) if len(cxyz) else None  # both patch passes look up the same voxels
    changed = changed & (patch_sizes(cxyz, changed, spacing, keys) >= s.min_patch_cores)
    sig, lost = sig & changed, lost & changed
    valid = comparable | lost  # the rest was not observed after the event: unknown
    roof = np.abs(normals[:, 2]) >= 0.5
    wall = np.isfinite(normals[:, 2]) & ~roof
    upper = (cxyz[:, 2] - ground) > s.storey_m

    def share(mask, among):
        k = among.sum()
        return float((mask & among).sum() / k) if k else 0.0

    coherent, largest = coherence(cxyz, changed, valid, spacing, keys)
    dist = distance[sig]
    out = {
        "m_changed": share(changed, valid),
        "m_lost": share(lost, valid),
        "m_roof_changed": share(changed, valid & roof),
        "m_wall_changed": share(changed, valid & wall),
        "m_holes": share(lost & seen_through, valid),
        "m_wall_holes": share(lost & seen_through, valid & wall),
        "m_upper_changed": share(changed, valid & upper),
        "m_lower_changed": share(changed, valid & ~upper),
        "m_inward": share(sig & (d < 0), valid),
        "m_outward": share(sig & (d > 0), valid),
        "m_coherent": share(coherent, valid),
        "m_largest_patch": float(largest / valid.sum()) if valid.any() else 0.0,
        "m_distance_p10": float(np.percentile(dist, 10)) if len(dist) else 0.0,
        "m_distance_median": float(np.median(dist)) if len(dist) else 0.0,
        "m_distance_p90": float(np.percentile(dist, 90)) if len(dist) else 0.0,
        "m_lod_median": float(np.median(lod_raw[comparable])) if comparable.any() else 0.0,
    }
    return CoreChange(cxyz, distance, lod_raw, comparable, changed), out


def patch_sizes(xyz, changed, spacing, keys=None) -> np.ndarray:
    """Size of the patch (points joined up to two voxels apart) each changed point belongs to;
    0 for unchanged points. `keys`: `_patch_kernels.voxel_keys` of xyz when already at hand."""
    sizes = np.zeros(len(xyz), np.int64)
    if not changed.any():
        return sizes
    labels = patches(xyz, changed, spacing, keys)
    sizes[changed] = np.bincount(labels)[labels]
    return sizes


def patches(xyz, changed, spacing, keys=None):
    """Patch label of every changed point (changed points joined up to two voxels apart);
    `keys`: `_patch_kernels.voxel_keys` of xyz when already at hand."""
    from . import _patch_kernels as K

    v = K.voxel_keys(xyz, spacing) if keys is None else keys
    roots = K.patch_roots(v.key, v.sorted_key, v.order, v.first, np.ascontiguousarray(changed, bool),
                          v.offsets_within(2))
    return roots[changed]


def coherence(xyz, changed, valid, spacing, keys=None):
    """(changed core points with at least half of their (>= 3) valid adjacent core points
    changed, the size of the largest patch of changed core points). A patch joins changed
    points up to two voxels apart, so that a core point left unobserved in the middle of a
    hole does not cut it in two (sparse epochs leave more such gaps). `keys`: as `patches`."""
    from . import _patch_kernels as K

    if not changed.any():
        return np.zeros(len(xyz), bool), 0
    v = K.voxel_keys(xyz, spacing) if keys is None else keys
    n_valid, n_changed = K.neighbour_counts(v.key, v.sorted_key, v.order, v.first, np.ascontiguousarray(valid, bool),
                                            np.ascontiguousarray(changed, bool), v.offsets_within(1))
    coherent = changed & (n_valid >= 3) & (2 * n_changed >= n_valid)
    return coherent, int(np.bincount(patches(xyz, changed, spacing, v)).max())
