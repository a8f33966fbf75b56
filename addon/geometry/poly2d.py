"""Plane polygon helpers (numpy only, no bpy): areas, containment, distances, clipping.

Polygons are (n, 2) arrays, counter-clockwise unless said otherwise, implicitly closed.
"""
from __future__ import annotations

import math

import numpy as np


def area(poly) -> float:
    """Signed shoelace area: > 0 for counter-clockwise."""
    p = np.asarray(poly, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def ccw(poly) -> np.ndarray:
    p = np.asarray(poly, dtype=np.float64)
    return p if area(p) >= 0 else p[::-1].copy()


def centroid(poly) -> np.ndarray:
    p = np.asarray(poly, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = cross.sum() / 2
    if abs(a) < 1e-12:
        return p.mean(axis=0)
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6 * a)


def contains(poly, pts) -> np.ndarray:
    """Even-odd point-in-polygon for (m, 2) points → (m,) bool."""
    p = np.asarray(poly, dtype=np.float64)
    q = np.atleast_2d(np.asarray(pts, dtype=np.float64))
    x, y = q[:, 0][:, None], q[:, 1][:, None]
    x0, y0 = p[:, 0][None, :], p[:, 1][None, :]
    x1, y1 = np.roll(p[:, 0], -1)[None, :], np.roll(p[:, 1], -1)[None, :]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    hit = crosses & (x < xi)
    return (hit.sum(axis=1) % 2) == 1


def boundary_distance(poly, pts) -> np.ndarray:
    """Unsigned distance from (m, 2) points to the polygon outline."""
    p = np.asarray(poly, dtype=np.float64)
    q = np.atleast_2d(np.asarray(pts, dtype=np.float64))
    a = p
    b = np.roll(p, -1, axis=0)
    ab = b - a  # (k, 2)
    ab2 = np.maximum((ab ** 2).sum(axis=1), 1e-18)
    aq = q[:, None, :] - a[None, :, :]  # (m, k, 2)
    t = np.clip((aq * ab[None]).sum(axis=2) / ab2[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    d = np.sqrt(((q[:, None, :] - closest) ** 2).sum(axis=2))
    return d.min(axis=1)


def signed_distance(poly, pts) -> np.ndarray:
    """Distance to the outline, negative inside."""
    d = boundary_distance(poly, pts)
    return np.where(contains(poly, pts), -d, d)


def convex_overlap(a, b, tol) -> bool:
    """Convex polygons a and b overlap by more than `tol` (separating-axis test: no edge normal
    of either separates them with `tol` to spare)."""
    for poly in (a, b):
        for k in range(len(poly)):
            e = poly[(k + 1) % len(poly)] - poly[k]
            n = np.array([-e[1], e[0]]) / (np.linalg.norm(e) + 1e-12)
            pa, pb = a @ n, b @ n
            if pa.max() <= pb.min() + tol or pb.max() <= pa.min() + tol:
                return False
    return True


def clip_halfplane(poly, point, normal) -> np.ndarray:
    """Part of a (convex or concave) polygon where dot(x - point, normal) <= 0
    (Sutherland–Hodgman; exact for convex, a valid outline for simple concave cases used here)."""
    p = np.asarray(poly, dtype=np.float64)
    point = np.asarray(point, dtype=np.float64)
    normal = np.asarray(normal, dtype=np.float64)
    out = []
    n = len(p)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        da, db = float(np.dot(a - point, normal)), float(np.dot(b - point, normal))
        if da <= 0:
            out.append(a)
        if (da < 0 < db) or (db < 0 < da):
            t = da / (da - db)
            out.append(a + t * (b - a))
    if len(out) < 3:
        return np.zeros((0, 2))
    return _dedupe(np.array(out))


def _dedupe(p, tol=1e-9):
    keep = [0]
    for i in range(1, len(p)):
        if np.linalg.norm(p[i] - p[keep[-1]]) > tol:
            keep.append(i)
    if len(keep) > 1 and np.linalg.norm(p[keep[-1]] - p[keep[0]]) <= tol:
        keep.pop()
    return p[keep]


def line_segments_inside(poly, origin, direction) -> list[tuple[float, float]]:
    """Parameter intervals [t0, t1] of the line origin + t*direction inside the polygon."""
    p = np.asarray(poly, dtype=np.float64)
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    ts = []
    n = len(p)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        e = b - a
        den = d[0] * e[1] - d[1] * e[0]
        if abs(den) < 1e-12:
            continue
        w = a - o
        t = (w[0] * e[1] - w[1] * e[0]) / den
        s = (w[0] * d[1] - w[1] * d[0]) / den
        if -1e-12 <= s < 1 - 1e-12:
            ts.append(t)
    ts.sort()
    out = []
    for i in range(0, len(ts) - 1, 2):
        if ts[i + 1] - ts[i] > 1e-6:
            out.append((ts[i], ts[i + 1]))
    return out


def perimeter(poly) -> float:
    p = np.asarray(poly, dtype=np.float64)
    return float(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum())


def irregular_polygon(rng, target_area: float, n_min=5, n_max=9, jitter=0.3) -> np.ndarray:
    """A star-shaped irregular polygon centred at the origin with exactly `target_area`."""
    k = int(rng.integers(n_min, n_max + 1))
    # keep angular gaps below pi so the centre stays inside and the outline simple
    ang = (np.arange(k) + rng.uniform(-0.35, 0.35, k)) * (2 * math.pi / k) + rng.uniform(0, 2 * math.pi)
    r = 1.0 + rng.uniform(-jitter, jitter, k)
    poly = np.column_stack([r * np.cos(ang), r * np.sin(ang)])
    a = area(poly)
    return poly * math.sqrt(target_area / a)


def rect(x0, y0, x1, y1) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
