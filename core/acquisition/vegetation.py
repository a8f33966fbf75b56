"""Vegetation in the laser scanner: porous tree crowns, and the LAS class of vegetation faces.

Transmission model. A tree crown is a closed low-poly surface whose faces are marked
porous (PLY face property `porous`, `Scene.face_porous`). Every time a laser ray (the
single beam's ray, a sub-ray of the full beam) hits a porous face, one Bernoulli trial
decides: with probability 1 - t the ray is returned there, with probability t it passes
and is cast again from `STEP_M` beyond the hit, towards the next surface (the crown's far
side, a branch of another crown, the roof or the ground below). t is the scene's
`transmission` (scene.json `"vegetation": {"transmission": t}`, default
`quakescan.formats.scene.DEFAULT_TRANSMISSION` = 0.5). A nadir ray through a crown therefore returns
on its upper side with probability 1 - t, on its lower side with t(1 - t) and reaches what
lies below with t². The full beam's sub-rays decide independently, so one pulse returns
from the crown and from the roof or ground under it: multiple returns where the beam
model forms them. After `MAX_CROSSINGS` passes a ray is returned at the next porous face
(t = 0.5 makes that 0.4 % of the rays that enter a crown). Trunks, hedges and everything
else are opaque.

Why this and not a volume of leaves: the classifier sees crowns as what a scanner records
of them - returns scattered over the crown's outer and inner surfaces and some ground and
roof under them - and a per-crossing probability is one documented number that gives the
known closed-form shares above (tests/test_scan.py checks them).

Draws are a counter-based hash of (seed, flight line, pulse, sub-ray, crossing): the same
seed gives the same returns whatever the threads and batches, and the central ray of a
pulse makes the same draws in every beam model. Scenes without porous faces never reach
this module (no cost).

The DIM simulator (`quakescan.acquisition.dim`) casts without ray identities and so treats crowns as
opaque: photogrammetry reconstructs a crown's outer surface, not what lies under it.
"""
from __future__ import annotations

import numpy as np

from ..formats.pointcloud import HIGH_VEGETATION_CLASS, LOW_VEGETATION_CLASS

MAX_CROSSINGS = 8  # passes through porous faces per ray; then the next porous face returns it
STEP_M = 1e-3  # a passed ray starts again this far beyond its hit (float32 Embree needs a gap)
LOW_VEGETATION_HEIGHT_M = 2.0  # an opaque vegetation piece lower than this is low vegetation (hedges)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64 of a uint64 array (wrapping arithmetic)."""
    z = z + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


class RayIds:
    """Identities of a batch of rays for the transmission draws: ray r is sub-ray r % k of
    pulse j[r // k] of flight line `line` (k = 1: central rays only)."""

    __slots__ = ("seed", "line", "j", "k")

    def __init__(self, seed: int, line: int, j: np.ndarray, k: int = 1):
        self.seed, self.line, self.j, self.k = int(seed), int(line), np.asarray(j, np.int64), int(k)

    def uniforms(self, rays: np.ndarray, crossing: int) -> np.ndarray:
        """Uniform [0, 1) draws of the given rays at their `crossing`-th porous hit."""
        rays = np.asarray(rays, np.int64)
        h = _mix(np.full(len(rays), self.seed & 0xFFFFFFFFFFFFFFFF, np.uint64))
        h = _mix(h ^ np.uint64(self.line))
        h = _mix(h ^ self.j[rays // self.k].astype(np.uint64))
        h = _mix(h ^ (rays % self.k).astype(np.uint64))
        h = _mix(h ^ np.uint64(crossing))
        return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def pass_porous(caster, origins, directions, face: np.ndarray, max_range: float, ids: RayIds) -> np.ndarray:
    """Faces where the rays stop once porous hits may pass (see the module docstring).

    `origins`, `directions`: float64 rays in the caster's local frame, as arrays or as one
    function of ray indices returning both (so that a caller without float64 rays builds
    them only for the few rays that hit a crown); `face`: Embree's first hit per ray (-1 =
    none), changed in place and returned. Ranges are not returned: every stop lies on the
    original ray, so the caller refines the distance to the final face's plane from the
    original origin as for any hit."""
    porous, t_pass = caster.face_porous, caster.transmission
    rays_of = origins if callable(origins) else (lambda idx: (origins[idx], directions[idx]))
    rays = np.flatnonzero(porous[face] & (face >= 0))  # porous[-1] is read, then masked
    for crossing in range(MAX_CROSSINGS):
        if crossing:
            rays = rays[porous[face[rays]] & (face[rays] >= 0)]
        if not len(rays):
            break
        rays = rays[ids.uniforms(rays, crossing) < t_pass]
        if not len(rays):
            break
        f = face[rays]
        o, d = rays_of(rays)
        nrm = caster.normals[f]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hit = (caster.plane_d[f] - np.einsum("ij,ij->i", nrm, o)) / np.einsum("ij,ij->i", nrm, d)
        # a grazing hit has no defined point to go on from: it stays a return there
        ok = np.isfinite(t_hit) & (t_hit >= 0) & (t_hit + STEP_M < max_range)
        face[rays[~ok & np.isfinite(t_hit) & (t_hit + STEP_M >= max_range)]] = -1
        rays, t_hit, o, d = rays[ok], t_hit[ok], o[ok], d[ok]
        if not len(rays):
            break
        start = o + d * (t_hit + STEP_M)[:, None]
        face[rays] = caster.embree_faces(start.astype(np.float32), d.astype(np.float32),
                                         (max_range - t_hit - STEP_M).astype(np.float32))
    return face


def vegetation_face_classes(vertices: np.ndarray, faces: np.ndarray, is_vegetation: np.ndarray,
                            porous: np.ndarray | None) -> np.ndarray:
    """ASPRS class of every vegetation face (others get 0): low vegetation (3) when its
    connected piece of vegetation mesh is opaque and lower than LOW_VEGETATION_HEIGHT_M
    (hedges), else high vegetation (5: crowns, trunks)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    out = np.zeros(len(faces), np.uint8)
    veg = np.flatnonzero(is_vegetation)
    if not len(veg):
        return out
    f = faces[veg]
    # faces joined through shared vertices: a graph on vertices, one component per piece
    n = len(vertices)
    graph = coo_matrix((np.ones(2 * len(f)), (np.concatenate([f[:, 0], f[:, 0]]),
                                              np.concatenate([f[:, 1], f[:, 2]]))), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    piece = label[f[:, 0]]
    z = vertices[f][:, :, 2]
    _, piece = np.unique(piece, return_inverse=True)
    top = np.full(piece.max() + 1, -np.inf)
    bottom = np.full(piece.max() + 1, np.inf)
    np.maximum.at(top, piece, z.max(axis=1))
    np.minimum.at(bottom, piece, z.min(axis=1))
    any_porous = np.zeros(piece.max() + 1, bool)
    if porous is not None:
        np.logical_or.at(any_porous, piece, porous[veg])
    low = ~any_porous & (top - bottom < LOW_VEGETATION_HEIGHT_M)
    out[veg] = np.where(low[piece], LOW_VEGETATION_CLASS, HIGH_VEGETATION_CLASS)
    return out
