"""The DIM simulator's mesh pieces and their cameras (step 2 of the model in
`quakescan.acquisition.dim`): the mesh cut into pieces of at most TILE_M metres, and per
piece the cameras that may see it ranked by their sampling interval on its surface
(compiled), which sets the piece's sampling grid; then runs of pieces as work chunks."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .dim_cameras import Cameras
from .dim_settings import PhotoSurvey

# Mesh pieces are at most this long (m): density and camera ranking are set per piece.
TILE_M = 8.0
# Grid cells per work chunk (memory and thread granularity; does not change the output).
CHUNK_CELLS = 1 << 19


def _split_long_triangles(a, b, c, parent, max_edge):
    """4-way midpoint splits until no edge is longer than `max_edge` (coplanar pieces)."""
    done = []
    while len(a):
        e = np.maximum(np.maximum(np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1)),
                       np.linalg.norm(a - c, axis=1))
        small = e <= max_edge
        done.append((a[small], b[small], c[small], parent[small]))
        a, b, c, parent = a[~small], b[~small], c[~small], parent[~small]
        if not len(a):
            break
        ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        a, b, c, parent = (np.concatenate([a, ab, ca, ab]), np.concatenate([ab, b, bc, bc]),
                           np.concatenate([ca, bc, c, ca]), np.tile(parent, 4))
    out = [np.concatenate(x) for x in zip(*done)]
    # keep mesh order: by parent face, stable
    order = np.argsort(out[3], kind="stable")
    return [x[order] for x in out]


@dataclass
class Pieces:
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    face: np.ndarray  # parent face
    normal: np.ndarray
    rank: np.ndarray  # (n, K) camera indices, -1 = none, best first
    h: np.ndarray  # grid spacing (m); inf = not sampled


def interval(survey, cams: Cameras, idx, d, cos_t):
    """Sampling interval on the surface (m) of cameras idx at distance d, incidence cos."""
    pitch = survey.pixel_pitch_um * 1e-6
    return survey.point_step_px * pitch * d / (cams.focal_m[idx] * np.sqrt(cos_t))


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _rank_kernel(centre, normal, radius, pos, rot, tan_w, tan_h, focal, cos_max, k, min_views):
    """Per piece the k cameras with the smallest d / (f · sqrt(cos θ)) among those that may
    see it (frame and incidence tested at its centre with a margin of its radius); ties
    keep the lower camera index. best = that value of the first camera, inf when fewer
    than min_views cameras qualify."""
    n, m = centre.shape[0], pos.shape[0]
    rank = np.full((n, k), -1, np.int64)
    best = np.full(n, np.inf)
    for i in prange(n):
        sc = np.full(k, np.inf)
        ix = np.full(k, -1, np.int64)
        r = radius[i]
        for c in range(m):
            rx = centre[i, 0] - pos[c, 0]
            ry = centre[i, 1] - pos[c, 1]
            rz = centre[i, 2] - pos[c, 2]
            qz = rot[c, 2, 0] * rx + rot[c, 2, 1] * ry + rot[c, 2, 2] * rz
            if qz <= r:
                continue
            qx = rot[c, 0, 0] * rx + rot[c, 0, 1] * ry + rot[c, 0, 2] * rz
            if abs(qx) > qz * tan_w[c] + 1.5 * r:
                continue
            qy = rot[c, 1, 0] * rx + rot[c, 1, 1] * ry + rot[c, 1, 2] * rz
            if abs(qy) > qz * tan_h[c] + 1.5 * r:
                continue
            d = math.sqrt(rx * rx + ry * ry + rz * rz)
            cs = abs(normal[i, 0] * rx + normal[i, 1] * ry + normal[i, 2] * rz) / d
            if cs < cos_max - r / d:
                continue
            score = d / (focal[c] * math.sqrt(max(cs, cos_max)))
            if score < sc[k - 1]:
                j = k - 1
                while j > 0 and score < sc[j - 1]:
                    sc[j] = sc[j - 1]
                    ix[j] = ix[j - 1]
                    j -= 1
                sc[j] = score
                ix[j] = c
        for j in range(k):
            rank[i, j] = ix[j]
        if ix[min_views - 1] >= 0:
            best[i] = sc[0]
    return rank, best


def rank_cameras(survey: PhotoSurvey, cams: Cameras, centre, normal, radius):
    """Per piece: the `max_candidate_views` cameras that may see it, best interval first,
    and the grid spacing of the best one (inf: fewer than min_views cameras)."""
    cos_max = math.cos(math.radians(survey.max_incidence_deg))
    k = min(survey.max_candidate_views, len(cams))
    rank, best = _rank_kernel(np.ascontiguousarray(centre), np.ascontiguousarray(normal), radius,
                              cams.position, np.ascontiguousarray(cams.rotation), cams.tan_half_w,
                              cams.tan_half_h, cams.focal_m, cos_max, k, min(survey.min_views, k))
    if k < survey.min_views:
        best[:] = np.inf
    return rank, survey.point_step_px * survey.pixel_pitch_um * 1e-6 * best


def make_pieces(survey, cams, verts, faces) -> Pieces:
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    keep = area2 > 2e-10
    a, b, c, parent = _split_long_triangles(a[keep], b[keep], c[keep], np.flatnonzero(keep), TILE_M)
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    centre = (a + b + c) / 3
    radius = np.max(np.stack([np.linalg.norm(p - centre, axis=1) for p in (a, b, c)]), axis=0)
    rank, h = rank_cameras(survey, cams, centre, n, radius)
    return Pieces(a, b, c, parent, n, rank, h)


def work_chunks(pieces: Pieces):
    """Deterministic runs of pieces with about CHUNK_CELLS grid cells each."""
    ab = np.linalg.norm(pieces.b - pieces.a, axis=1)
    e1 = (pieces.b - pieces.a) / ab[:, None]
    e2 = np.cross(pieces.normal, e1)
    cx, cy = np.einsum("ij,ij->i", pieces.c - pieces.a, e1), np.einsum("ij,ij->i", pieces.c - pieces.a, e2)
    w = np.maximum(ab, cx) - np.minimum(0, cx)
    hh = np.abs(cy)
    with np.errstate(invalid="ignore", divide="ignore"):
        cells = np.where(np.isfinite(pieces.h), (np.ceil(w / pieces.h) + 1) * (np.ceil(hh / pieces.h) + 1), 0)
    sampled = np.flatnonzero(cells > 0)
    bounds, acc, start = [], 0, 0
    for i, n in zip(sampled, cells[sampled]):
        acc += n
        if acc >= CHUNK_CELLS:
            bounds.append((start, i + 1))
            start, acc = i + 1, 0
    if acc or not bounds:
        bounds.append((start, len(pieces.h)))
    return [(s, e) for s, e in bounds if s < e], e1, e2, cx, cy, ab
