"""Plain numpy reference of `quakescan.change._patch_kernels`, for the tests that compare the
two; nothing in production calls it. Each voxel offset is looked up over every point with
`np.searchsorted` and the links go to scipy's connected components."""
from __future__ import annotations

import numpy as np


def patch_sizes(xyz, changed, spacing) -> np.ndarray:
    """`core_points.patch_sizes`."""
    sizes = np.zeros(len(xyz), np.int64)
    if not changed.any():
        return sizes
    labels, _ = patches(xyz, changed, spacing)
    sizes[changed] = np.bincount(labels)[labels]
    return sizes


def patches(xyz, changed, spacing):
    """Connected-component label of every changed point (joined up to two voxels apart)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    neighbour = voxel_lookup(xyz, spacing)
    idx = np.flatnonzero(changed)
    remap = np.full(len(xyz), -1)
    remap[idx] = np.arange(len(idx))
    a, b = [], []
    for dx in range(-2, 3):
        for dy in range(-2, 3):
            for dz in range(-2, 3):
                if dx == dy == dz == 0:
                    continue
                hit, j = neighbour(dx, dy, dz)
                link = hit & changed & changed[j]
                a.append(remap[np.flatnonzero(link)])
                b.append(remap[j[link]])
    a, b = np.concatenate(a), np.concatenate(b)
    _, labels = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(len(idx), len(idx))),
                                     directed=False)
    return labels, len(idx)


def voxel_lookup(xyz, spacing):
    """Keys of the core points' voxels and a lookup from a key offset to neighbour indices."""
    ijk = np.floor((xyz - xyz.min(axis=0)) / spacing).astype(np.int64)
    dims = ijk.max(axis=0) + 5
    key = ((ijk[:, 0] + 2) * dims[1] + ijk[:, 1] + 2) * dims[2] + ijk[:, 2] + 2
    order = np.argsort(key)
    skey = key[order]

    def neighbour(dx, dy, dz):
        nk = key + (dx * dims[1] + dy) * dims[2] + dz
        pos = np.minimum(np.searchsorted(skey, nk), len(skey) - 1)
        return skey[pos] == nk, order[pos]

    return neighbour


def coherence(xyz, changed, valid, spacing):
    """`core_points.coherence`."""
    if not changed.any():
        return np.zeros(len(xyz), bool), 0
    neighbour = voxel_lookup(xyz, spacing)
    n_valid = np.zeros(len(xyz), np.int64)
    n_changed = np.zeros(len(xyz), np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                hit, j = neighbour(dx, dy, dz)
                n_valid += hit & valid[j]
                n_changed += hit & changed[j]
    coherent = changed & (n_valid >= 3) & (2 * n_changed >= n_valid)
    labels, _ = patches(xyz, changed, spacing)
    return coherent, int(np.bincount(labels).max())
