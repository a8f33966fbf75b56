"""Close the open shells of real city-model buildings with walls under their open roof edges.

Real LoD2 models often leave wall polygons out (a facade the mapping did not capture, a wall
dropped as a party wall although the neighbour is lower). Every sensor QuakeScan simulates
then looks through the gap into the building: the photogrammetry's oblique cameras
reconstruct the terrain under the roof, a laser's oblique pulses reach it, and two sensors
that see through the gap at different angles read an intact building as one with its roof
fallen in (Rotterdam building 15: 25 % of its post-event returns 15 m below the pre-event
roof between a laser and a photo flight). A real building is closed; a scene models it so.

An **open edge** is an edge of a roof or wall triangle that no other triangle of the
building shares, or a roof edge that only walls rising from it share (a storey's wall strip
on a lower part's outer roof edge, no facade under it). Vertices are merged at `MERGE_M`, and
slivers thinner than `SLIVER_M` share no edge (a triangulation leaves them along a straight
outline with extra vertices; one on Rotterdam building 6's roof edge made it look inner).
It is a roof's edge with no wall under it, or the
bottom of a wall that stops in mid-air (3D BAG-style models keep only the strip of a party
wall above the neighbour's roof; a subset without that neighbour leaves the facade open).
It is closed by a vertical wall from the edge down to the building's lowest vertex unless

- a wall of the building already stands under it (a T-junction of the model's polygons: the
  wall's top edge is split where the roof edge is not), tested `PROBE_DROP_M` below points
  along the edge; or
- for a roof edge, a roof of the building continues beyond it (two roof planes joined
  without a shared edge), tested `PROBE_OUT_M` outside the edge; for a wall's bottom edge, a
  roof of the building lies just under it (within `STANDS_ON_M`, `PROBE_OUT_M` to either side:
  the wall stands on a lower roof part); or
- it lies within `BASE_BAND_M` of the building's base, or is (nearly) vertical.

Walls inside the building (under a higher part's edge over a lower part) are hidden from
every sensor and change nothing it sees.
"""
from __future__ import annotations

import numpy as np

from .scene import ROOF, WALL

MERGE_M = 1e-3
# a triangle whose height over its longest edge is below this is a sliver: it covers nothing
SLIVER_M = 0.01
# probes: this far below an edge for a wall under it, this far outside it for a roof beyond it
PROBE_DROP_M = 0.3
PROBE_OUT_M = 0.1
PROBE_FRACTIONS = (0.25, 0.5, 0.75)
# how close a probe must lie to a wall's plane to stand on it
ON_PLANE_M = 0.05
# a wall's bottom edge stands on a roof of the building at most this far below it
STANDS_ON_M = 0.5
BASE_BAND_M = 0.5
MIN_EDGE_XY_M = 0.05


def close_open_edges(verts: np.ndarray, tris: np.ndarray, surface: np.ndarray):
    """One building's mesh (`verts` (n, 3) float64, `tris` (k, 3), `surface` (k,)) with walls
    added under its open edges → (verts, tris, surface, added wall area m²)."""
    if not len(tris):
        return verts, tris, surface, 0.0
    edges, of_roof = _open_edges(verts, tris, surface)
    if not len(edges):
        return verts, tris, surface, 0.0
    a, b, third = verts[edges[:, 0]], verts[edges[:, 1]], verts[edges[:, 2]]
    z_base = float(verts[np.unique(tris), 2].min())
    keep = (np.minimum(a[:, 2], b[:, 2]) > z_base + BASE_BAND_M) \
        & (np.linalg.norm((b - a)[:, :2], axis=1) >= MIN_EDGE_XY_M)
    a, b, third, of_roof = a[keep], b[keep], third[keep], of_roof[keep]
    if not len(a):
        return verts, tris, surface, 0.0
    wall_tris = verts[tris[surface == WALL]]
    roof_tris = verts[tris[surface == ROOF]]
    outward = _outward(a, b, third)
    closed = np.ones(len(a), bool)
    up = np.array([0.0, 0.0, 1.0])
    for t in PROBE_FRACTIONS:
        p = a + t * (b - a)
        z = p[:, 2]
        # covered at a probe: a wall stands under the edge; a roof goes on beyond a roof edge;
        # a wall's bottom edge stands on a roof
        covered = _on_a_wall(p - PROBE_DROP_M * up, wall_tris)
        beyond = _roof_between(p + PROBE_OUT_M * outward, roof_tris, z - 0.05, np.inf)
        stands = (_roof_between(p + PROBE_OUT_M * outward, roof_tris, z - STANDS_ON_M, z + 0.01)
                  | _roof_between(p - PROBE_OUT_M * outward, roof_tris, z - STANDS_ON_M, z + 0.01))
        covered |= np.where(of_roof, beyond, stands)
        closed &= ~covered
    a, b = a[closed], b[closed]
    if not len(a):
        return verts, tris, surface, 0.0
    a0, b0 = a.copy(), b.copy()
    a0[:, 2] = b0[:, 2] = z_base
    n = len(verts)
    m = len(a)
    new_v = np.concatenate([verts, a, b, b0, a0])
    ia, ib, ib0, ia0 = (n + np.arange(m) + k * m for k in range(4))
    new_t = np.concatenate([tris, np.column_stack([ia, ia0, ib0]), np.column_stack([ia, ib0, ib])])
    keep_t = _area(new_v, new_t[len(tris):]) > 1e-8
    added = new_t[len(tris):][keep_t]
    area = float(_area(new_v, added).sum())
    return (new_v, np.concatenate([tris, added]),
            np.concatenate([surface, np.full(len(added), WALL, surface.dtype)]), area)


def _open_edges(verts, tris, surface):
    """(e, 3): the two vertices of each roof or wall triangle's edge used by no other triangle,
    and the triangle's third vertex (which side it lies on); (e,) whether of a roof. Slivers
    (`_slivers`) neither share an edge nor have one."""
    solid = ~_slivers(verts, tris)
    tris, surface = tris[solid], surface[solid]
    keys = np.floor(verts / MERGE_M + 0.5).astype(np.int64)
    _, canon = np.unique(keys, axis=0, return_inverse=True)
    canon = canon.reshape(-1)
    c = canon[tris]
    pairs = np.concatenate([c[:, [0, 1]], c[:, [1, 2]], c[:, [2, 0]]])
    und = np.sort(pairs, axis=1)
    _, inverse, uses = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    once = uses[inverse] == 1
    k = len(tris)
    tri_of = np.tile(np.arange(k), 3)
    corner = np.repeat(np.arange(3), k)
    # A roof edge is open too where only walls rising from it share it: a wall strip standing on
    # the roof's outer edge (the storey above a lower part) leaves the facade under it open.
    third_z = verts[tris[tri_of, (corner + 2) % 3], 2]
    edge_z = 0.5 * (verts[tris[tri_of, corner], 2] + verts[tris[tri_of, (corner + 1) % 3], 2])
    is_roof = surface[tri_of] == ROOF
    down = (surface[tri_of] == WALL) & (third_z < edge_z - MERGE_M)
    roofs_at = np.bincount(inverse, weights=is_roof, minlength=len(uses))
    walls_down_at = np.bincount(inverse, weights=down, minlength=len(uses))
    lone_roof = is_roof & (roofs_at[inverse] == 1) & (walls_down_at[inverse] == 0)
    pick = (once | lone_roof) & np.isin(surface[tri_of], (ROOF, WALL))
    t, j = tri_of[pick], corner[pick]
    return np.column_stack([tris[t, j], tris[t, (j + 1) % 3], tris[t, (j + 2) % 3]]), surface[t] == ROOF


def _outward(a, b, third) -> np.ndarray:
    """Unit horizontal direction perpendicular to each edge, away from its roof triangle."""
    d = (b - a)[:, :2]
    perp = np.column_stack([-d[:, 1], d[:, 0]])
    perp /= np.maximum(np.linalg.norm(perp, axis=1, keepdims=True), 1e-12)
    towards_roof = np.einsum("ij,ij->i", perp, (third - a)[:, :2]) > 0
    perp[towards_roof] *= -1
    return np.column_stack([perp, np.zeros(len(perp))])


def _on_a_wall(p: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Whether each point lies within ON_PLANE_M of a wall triangle ((w, 3, 3)) and inside it."""
    if not len(walls) or not len(p):
        return np.zeros(len(p), bool)
    a, b, c = walls[:, 0], walls[:, 1], walls[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    rel = p[:, None, :] - a[None]
    dist = np.einsum("pwk,wk->pw", rel, n)
    q = p[:, None, :] - dist[..., None] * n[None]
    return (_inside_triangle(q, a, b, c, n) & (np.abs(dist) <= ON_PLANE_M)).any(axis=1)


def _roof_between(p: np.ndarray, roofs: np.ndarray, z_lo, z_hi) -> np.ndarray:
    """Whether a roof triangle ((r, 3, 3)) passes over each point's x/y at a height in
    (z_lo, z_hi]."""
    if not len(roofs) or not len(p):
        return np.zeros(len(p), bool)
    a, b, c = roofs[:, 0], roofs[:, 1], roofs[:, 2]
    ab, ac = (b - a)[:, :2], (c - a)[:, :2]
    det = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    ok = np.abs(det) > 1e-12
    rel = p[:, None, :2] - a[None, :, :2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (rel[..., 0] * ac[:, 1] - rel[..., 1] * ac[:, 0]) / det
        v = (ab[:, 0] * rel[..., 1] - ab[:, 1] * rel[..., 0]) / det
        inside = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
        z = a[:, 2] + u * (b - a)[:, 2] + v * (c - a)[:, 2]
    lo, hi = np.broadcast_to(z_lo, len(p))[:, None], np.broadcast_to(z_hi, len(p))[:, None]
    return (inside & (z > lo) & (z <= hi)).any(axis=1)


def _inside_triangle(q, a, b, c, n) -> np.ndarray:
    """(p, w) whether the points q (p, w, 3), on the triangles' planes, lie inside them."""
    tol = 1e-6

    def side(u, v):
        return np.einsum("pwk,wk->pw", np.cross(v[None] - u[None], q - u[None]), n)
    return (side(a, b) >= -tol) & (side(b, c) >= -tol) & (side(c, a) >= -tol)


def _slivers(v, t) -> np.ndarray:
    """(k,) whether each triangle is thinner than SLIVER_M: twice its area over its longest edge."""
    if not len(t):
        return np.zeros(0, bool)
    longest = np.max([np.linalg.norm(v[t[:, (j + 1) % 3]] - v[t[:, j]], axis=1) for j in range(3)], axis=0)
    return 2.0 * _area(v, t) < SLIVER_M * longest


def _area(v, t) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
