"""Compiled neighbour loops over one building's core points (numba) for
`quakescan.change.surface`: the patches changed core points form and how many of each point's
adjacent core points are valid and changed.

The points are keyed by voxel (`voxel_keys`); a neighbour at a voxel offset is the first
point of that voxel in the keys' sorted order, as `np.searchsorted` finds it. numpy looked
each of the 124 offsets of a patch (points up to two voxels apart) up over every point in
turn, a tenth of a tile's time; these loops ask the same questions of the same sorted keys,
so the patches and counts are the same. `quakescan.change._patch_reference` is the numpy
version the tests compare them with.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..grid.cells import row_bounds
from ._feature_kernels import _lower_bound

_JIT = dict(nogil=True, cache=True, error_model="numpy")


# the voxels of a building's box are looked up in a table while it is at most this many
# entries a point (8 bytes each); a few points scattered far apart search the sorted keys
TABLE_PER_POINT = 64


@dataclass
class VoxelKeys:
    """Core points keyed by voxel: `key` per point, `sorted_key` and the `order` that sorts
    them (numpy's default argsort, whose first point of a voxel is the neighbour numpy's
    lookup found), and `first`: the position in the sorted keys of each voxel's first point
    (-1: empty), or an empty table when the box holds too many voxels."""

    key: np.ndarray
    sorted_key: np.ndarray
    order: np.ndarray
    first: np.ndarray
    dims: tuple

    def offsets_within(self, reach: int) -> np.ndarray:
        """Key offsets of the voxels at most `reach` away on every axis (not the voxel itself)."""
        d = range(-reach, reach + 1)
        _, d1, d2 = self.dims
        return np.array([(dx * d1 + dy) * d2 + dz for dx in d for dy in d for dz in d if not dx == dy == dz == 0],
                        np.int64)


def voxel_keys(xyz: np.ndarray, spacing: float) -> VoxelKeys:
    ijk = np.floor((xyz - row_bounds(xyz)[0]) / spacing).astype(np.int64)
    dims = row_bounds(ijk)[1] + 5  # two voxels of margin each side: no offset leaves the box or wraps
    key = ((ijk[:, 0] + 2) * dims[1] + ijk[:, 1] + 2) * dims[2] + ijk[:, 2] + 2
    order = np.argsort(key)
    sorted_key = key[order]
    n_voxels = int(dims[0]) * int(dims[1]) * int(dims[2])
    first = (_first_positions(sorted_key, n_voxels) if n_voxels <= TABLE_PER_POINT * len(key) + 4096
             else np.zeros(0, np.int64))
    return VoxelKeys(key, sorted_key, order, first, tuple(int(d) for d in dims))


@njit(**_JIT)
def _first_positions(sorted_key, n_voxels):
    first = np.full(n_voxels, -1, np.int64)
    for p in range(sorted_key.shape[0] - 1, -1, -1):
        first[sorted_key[p]] = p
    return first


@njit(**_JIT)
def _search(sorted_key, k):
    """Position of the first point of voxel k in the sorted keys, -1 if it holds none."""
    p = _lower_bound(sorted_key, 0, sorted_key.shape[0], k)
    if p < sorted_key.shape[0] and sorted_key[p] == k:
        return p
    return -1


@njit(**_JIT)
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(**_JIT)
def _join(parent, i, j):
    a = _root(parent, i)
    b = _root(parent, j)
    if a != b:
        parent[max(a, b)] = min(a, b)


# the table or the search is chosen in the loop, not in a helper both call: with the branch
# inside a called function numba's loop ran ten times slower
@njit(**_JIT)
def patch_roots(key, sorted_key, order, first, changed, offsets):
    """Per point, a representative of the patch it belongs to: changed points joined to the
    changed neighbour that each offset finds (union-find). Unchanged points are their own."""
    n = key.shape[0]
    parent = np.arange(n)
    table = first.shape[0] > 0
    for i in range(n):
        if not changed[i]:
            continue
        for o in offsets:
            p = first[key[i] + o] if table else _search(sorted_key, key[i] + o)
            if p >= 0 and changed[order[p]]:
                _join(parent, i, order[p])
    for i in range(n):
        parent[i] = _root(parent, i)
    return parent


@njit(**_JIT)
def neighbour_counts(key, sorted_key, order, first, valid, changed, offsets):
    """Per point, how many of the neighbours the offsets find are valid and how many changed."""
    n = key.shape[0]
    n_valid = np.zeros(n, np.int64)
    n_changed = np.zeros(n, np.int64)
    table = first.shape[0] > 0
    for i in range(n):
        for o in offsets:
            p = first[key[i] + o] if table else _search(sorted_key, key[i] + o)
            if p >= 0:
                n_valid[i] += valid[order[p]]
                n_changed[i] += changed[order[p]]
    return n_valid, n_changed
