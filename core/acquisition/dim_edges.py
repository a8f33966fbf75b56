"""Edges and corners of DIM clouds (step 5 of the model in `quakescan.acquisition.dim`): the
mesh's creases, and the smoothing of points near them as window-based matching does."""
from __future__ import annotations

import math

import numpy as np


def crease_segments(verts, faces, face_building, crease_deg):
    """Mesh edges that are creases (dihedral > crease_deg) or open edges of building faces.

    Vertices are welded at 1 mm first, so triangle soups find their shared edges."""
    key = np.round(verts / 1e-3).astype(np.int64)
    _, weld = np.unique(key, axis=0, return_inverse=True)
    weld = weld.ravel()
    f = weld[faces]
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1)
    good = ln > 2e-10
    n = n / np.where(good, ln, 1.0)[:, None]
    fi = np.flatnonzero(good)
    e = np.concatenate([f[fi][:, [0, 1]], f[fi][:, [1, 2]], f[fi][:, [2, 0]]])
    ef = np.tile(fi, 3)
    ev = np.concatenate([faces[fi][:, [0, 1]], faces[fi][:, [1, 2]], faces[fi][:, [2, 0]]])
    e_sorted = np.sort(e, axis=1)
    order = np.lexsort((e_sorted[:, 1], e_sorted[:, 0]))
    es, ef, ev = e_sorted[order], ef[order], ev[order]
    start = np.ones(len(es), bool)
    start[1:] = np.any(es[1:] != es[:-1], axis=1)
    group = np.cumsum(start) - 1
    size = np.bincount(group)
    first = np.flatnonzero(start)
    cos_lim = math.cos(math.radians(crease_deg))
    crease = np.zeros(len(first), bool)
    # open edges of buildings
    crease |= (size == 1) & (face_building[ef[first]] > 0)
    # pairs (and beyond: any face of the edge against the first one); two-sided
    for k in range(1, int(size.max()) if len(size) else 1):
        has = size > k
        fa, fb = ef[first[has]], ef[first[has] + k]
        cosang = np.abs(np.einsum("ij,ij->i", n[fa], n[fb]))
        crease[np.flatnonzero(has)[cosang < cos_lim]] = True
    seg = ev[first[crease]]
    return verts[seg[:, 0]], verts[seg[:, 1]]


def smooth(points, p0, p1, radius, piece_centre=None, piece_radius=None, piece=None):
    """Pull points near crease segments towards the mean of their neighbours within
    `radius` (in place), by a weight 1 - distance to the crease / radius. Only pieces
    (centre, radius; `piece` = each point's piece) that reach the creases are searched.
    Returns the number of points moved."""
    from scipy.spatial import cKDTree

    if radius <= 0 or not len(p0) or not len(points):
        return 0
    # samples along the creases, spaced radius/4: the nearest sample is within radius/8 of
    # the nearest point on the segment
    ln = np.linalg.norm(p1 - p0, axis=1)
    k = np.maximum(1, np.ceil(ln / (radius / 4)).astype(np.int64))
    seg = np.repeat(np.arange(len(ln)), k + 1)
    tt = (np.arange(int((k + 1).sum())) - np.repeat(np.cumsum(k + 1) - (k + 1), k + 1)) / np.repeat(k, k + 1)
    samples = p0[seg] + (p1 - p0)[seg] * tt[:, None]
    tree = cKDTree(samples)
    cand = np.arange(len(points))
    if piece_centre is not None:
        # a piece reaches a crease when its centre lies within its radius + 2 radius of a sample
        dc, _ = tree.query(piece_centre, k=1, workers=-1)
        reach = dc <= piece_radius + 2 * radius + radius / 8
        cand = np.flatnonzero(reach[piece])
    dist = np.full(len(points), np.inf)
    dist[cand], _ = tree.query(points[cand], k=1, distance_upper_bound=2 * radius, workers=-1)
    band = np.flatnonzero(np.isfinite(dist))
    if not len(band):
        return 0
    near = band[dist[band] < radius]
    if not len(near):
        return 0
    ptree = cKDTree(points[band])
    dd, nb = ptree.query(points[near], k=16, distance_upper_bound=radius, workers=-1)
    valid = np.isfinite(dd)
    nbp = points[band][np.where(valid, nb, 0)]
    cnt = valid.sum(axis=1)
    mean = (nbp * valid[..., None]).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    w = np.clip(1.0 - dist[near] / radius, 0.0, 1.0)[:, None]
    points[near] += w * (mean - points[near])
    return len(near)
