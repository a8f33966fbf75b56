"""Debris: height-field heaps, aprons and fans with an exact volume, and small fragments.

A height field is a triangulated grid whose vertices sit `h >= 0` above a base plane; its
volume (projected area × mean height per triangle) is scaled to the requested volume, so
"solid fraction × bulking × collapsed volume" holds exactly for the faces created.
"""
from __future__ import annotations

import math

import numpy as np

from . import poly2d
from .mesh import DEBRIS, P_DEBRIS, Labels

MIN_HEIGHT = 0.03  # triangles lower than this everywhere are dropped (they would lie on the ground)


def debris_volume(solid_fraction: float, bulking: float, collapsed_volume: float) -> float:
    return float(solid_fraction) * float(bulking) * float(collapsed_volume)


def value_noise(rng, X, Y, scale=2.0, octaves=2) -> np.ndarray:
    """Smooth random field in [-1, 1] over node positions (bilinear value noise)."""
    out = np.zeros_like(X, dtype=np.float64)
    amp, tot = 1.0, 0.0
    x0, y0 = float(X.min()), float(Y.min())
    for o in range(octaves):
        s = scale / (2 ** o)
        gx = int(math.ceil((X.max() - x0) / s)) + 2
        gy = int(math.ceil((Y.max() - y0) / s)) + 2
        g = rng.uniform(-1, 1, (gy, gx))
        fx = (X - x0) / s
        fy = (Y - y0) / s
        ix = np.clip(np.floor(fx).astype(int), 0, gx - 2)
        iy = np.clip(np.floor(fy).astype(int), 0, gy - 2)
        tx = fx - ix
        ty = fy - iy
        tx = tx * tx * (3 - 2 * tx)
        ty = ty * ty * (3 - 2 * ty)
        v = (g[iy, ix] * (1 - tx) * (1 - ty) + g[iy, ix + 1] * tx * (1 - ty)
             + g[iy + 1, ix] * (1 - tx) * ty + g[iy + 1, ix + 1] * tx * ty)
        out += amp * v
        tot += amp
        amp *= 0.5
    return out / tot


def smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _grid(origin, u, v, umin, umax, vmin, vmax, cell):
    nu = max(2, int(math.ceil((umax - umin) / cell)) + 1)
    nv = max(2, int(math.ceil((vmax - vmin) / cell)) + 1)
    us = np.linspace(umin, umax, nu)
    vs = np.linspace(vmin, vmax, nv)
    U, V = np.meshgrid(us, vs)
    X = origin[0] + U * u[0] + V * v[0]
    Y = origin[1] + U * u[1] + V * v[1]
    return U, V, X, Y


def _tris(ny, nx):
    idx = np.arange(ny * nx).reshape(ny, nx)
    a = idx[:-1, :-1].ravel()
    b = idx[:-1, 1:].ravel()
    c = idx[1:, 1:].ravel()
    d = idx[1:, :-1].ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


class Field:
    """Grid nodes (X, Y) with raw heights; `scaled(volume)` fixes the amplitude."""

    def __init__(self, X, Y, h_raw):
        self.X, self.Y = X, Y
        self.h_raw = np.maximum(np.nan_to_num(h_raw), 0.0)
        ny, nx = X.shape
        self.tris = _tris(ny, nx)
        xy = np.column_stack([X.ravel(), Y.ravel()])
        a, b, c = xy[self.tris[:, 0]], xy[self.tris[:, 1]], xy[self.tris[:, 2]]
        signed = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))
        flip = signed < 0  # grids in a left-handed (u, v) frame: make every triangle face up
        self.tris[flip] = self.tris[flip][:, ::-1]
        self.tri_area = np.abs(signed)

    def scaled(self, volume, min_h=MIN_HEIGHT):
        """(h, kept triangle mask) with the kept triangles' volume exactly `volume`."""
        h = self.h_raw.ravel()
        th = h[self.tris]
        v_raw = float((self.tri_area * th.mean(axis=1)).sum())
        if volume <= 0 or v_raw <= 0:
            return np.zeros_like(h), np.zeros(len(self.tris), bool)
        h = h * (volume / v_raw)
        th = h[self.tris]
        keep = (th.max(axis=1) >= min_h) & (self.tri_area > 1e-9)
        v_kept = float((self.tri_area[keep] * th[keep].mean(axis=1)).sum())
        if v_kept <= 0:
            return np.zeros_like(h), np.zeros(len(self.tris), bool)
        return h * (volume / v_kept), keep

    def peak(self, volume):
        h, keep = self.scaled(volume)
        return float(h.max()) if keep.any() else 0.0


def emit(bm, lab: Labels, bid: int, field: Field, volume: float, base_z, surface=DEBRIS, part=P_DEBRIS):
    """Create the field's triangles in `bm`; returns (faces, measured volume, peak height).
    `base_z` is a number or a (ny, nx) array."""
    h, keep = field.scaled(volume)
    if not keep.any():
        return [], 0.0, 0.0
    X, Y = field.X.ravel(), field.Y.ravel()
    B = np.broadcast_to(np.asarray(base_z, dtype=np.float64), field.X.shape).ravel()
    tris = field.tris[keep]
    used = np.unique(tris)
    verts = {}
    for i in used.tolist():
        verts[i] = bm.verts.new((float(X[i]), float(Y[i]), float(B[i] + h[i])))
    faces = []
    ls, lb, lp, lst, le = lab.surface, lab.bid, lab.part, lab.storey, lab.elem
    for a, b, c in tris.tolist():
        f = bm.faces.new((verts[a], verts[b], verts[c]))
        f[ls] = surface
        f[lb] = bid
        f[lp] = part
        f[lst] = -1
        f[le] = 0
        faces.append(f)
    vol = float((field.tri_area[keep] * h[tris].mean(axis=1)).sum())
    return faces, vol, float(h[used].max())


def cell_size(extent: float, target_cells: int = 48, lo: float = 0.35, hi: float = 1.2) -> float:
    return float(np.clip(extent / target_cells, lo, hi))


# --- shapes ----------------------------------------------------------------------------------

def heap_field(rng, poly, spread, plateau=0.5, noise=0.35, cell=None, exclude=None):
    """A heap over polygon `poly` (2D) spreading `spread` metres beyond it; highest in the
    interior (a plateau of `plateau` × the polygon's inner depth), smooth flanks, value
    noise. `exclude`: optional polygon where the heap is zero (e.g. a remaining wing)."""
    poly = np.asarray(poly, dtype=np.float64)
    (x0, y0), (x1, y1) = poly.min(axis=0), poly.max(axis=0)
    ext = max(x1 - x0, y1 - y0) + 2 * spread
    cell = cell or cell_size(ext)
    U, V, X, Y = _grid((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), x0 - spread, x1 + spread, y0 - spread, y1 + spread, cell)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    d = poly2d.signed_distance(poly, pts).reshape(X.shape)
    depth = max(float(-d.min()), 1e-3)
    ramp_in = max(depth * (1.0 - plateau), 0.3)
    t = (spread - d) / (spread + ramp_in)
    h = smoothstep(t)
    if noise > 0:
        h = h * (1.0 + noise * value_noise(rng, X, Y, scale=max(1.5, ext / 8)))
    if exclude is not None:
        inside = poly2d.contains(exclude, pts).reshape(X.shape)
        h = np.where(inside, 0.0, h)
    return Field(X, Y, h)


def apron_field(rng, poly, spread, inner=1.0, noise=0.3, cell=None):
    """A skirt of debris around `poly`: highest on the outline, fading `spread` outward
    and `inner` inward."""
    poly = np.asarray(poly, dtype=np.float64)
    (x0, y0), (x1, y1) = poly.min(axis=0), poly.max(axis=0)
    ext = max(x1 - x0, y1 - y0) + 2 * spread
    cell = cell or cell_size(ext, 64)
    U, V, X, Y = _grid((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), x0 - spread, x1 + spread, y0 - spread, y1 + spread, cell)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    d = poly2d.signed_distance(poly, pts).reshape(X.shape)
    h = np.where(d >= 0, smoothstep(1.0 - d / spread), smoothstep(1.0 + d / inner))
    if noise > 0:
        h = h * (1.0 + noise * value_noise(rng, X, Y, scale=max(1.5, ext / 10)))
    return Field(X, Y, h)


def fan_field(rng, a, b, outward, reach, lateral=None, noise=0.3, cell=None, start=0.03):
    """A debris fan in front of wall segment a→b (2D), thrown `reach` metres outward."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    seg = b - a
    L = float(np.linalg.norm(seg))
    u = seg / L
    n = np.asarray(outward, dtype=np.float64)
    n = n / np.linalg.norm(n)
    lateral = 0.35 * reach if lateral is None else lateral
    cell = cell or cell_size(max(L + 2 * lateral, reach), 40, lo=0.25, hi=0.8)
    U, V, X, Y = _grid(a, u, n, -lateral, L + lateral, start, start + reach, cell)
    along = smoothstep(1.0 - (V - start) / reach) ** 0.8
    across = np.minimum(smoothstep((U + lateral) / max(lateral, 1e-3)),
                        smoothstep((L + lateral - U) / max(lateral, 1e-3)))
    h = along * across
    if noise > 0:
        h = h * (1.0 + noise * value_noise(rng, X, Y, scale=max(1.0, min(L, reach) / 2)))
    return Field(X, Y, h)


def fan_reach_for_height(volume, width, height, lo, hi):
    """Reach giving a fan of peak `height` for `volume` over `width`, clamped to [lo, hi].
    Uses the unit fan's volume-per-reach constant (shape only, no noise)."""
    # For the fan profile without noise, volume = c * peak * reach * (width + 0.35*reach*...)
    # — solved numerically with a few fixed-point steps.
    r = 0.5 * (lo + hi)
    for _ in range(6):
        f = fan_field(None, (0, 0), (width, 0), (0, -1), r, noise=0)
        v1 = float((f.tri_area * f.h_raw.ravel()[f.tris].mean(axis=1)).sum())  # unit-peak volume
        if v1 <= 0:
            break
        peak = volume / v1
        r_new = float(np.clip(r * peak / height, lo, hi))
        if abs(r_new - r) < 1e-3:
            r = r_new
            break
        r = r_new
    return r


def add_box(bm, lab: Labels, bid, center, size, yaw=0.0, pitch=0.0, surface=DEBRIS, part=P_DEBRIS):
    """A closed box (debris fragment); returns its faces."""
    sx, sy, sz = (size, size, size) if np.isscalar(size) else size
    c = np.asarray(center, dtype=np.float64)
    corners = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64) * 0.5 * np.array([sx, sy, sz])
    cy, sy_ = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    Rz = np.array([[cy, -sy_, 0], [sy_, cy, 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    pts = corners @ (Rz @ Rx).T + c
    vs = [bm.verts.new(tuple(map(float, p))) for p in pts]
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    out = []
    for q in quads:
        f = bm.faces.new([vs[i] for i in q])
        lab.set(f, surface, bid, part, -1, 0)
        out.append(f)
    return out
