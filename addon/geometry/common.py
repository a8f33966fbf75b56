"""Small helpers shared by the damage patterns."""
from __future__ import annotations

import math

import numpy as np

from . import poly2d


class PatternNotApplicable(ValueError):
    """The building lacks what the pattern needs (e.g. no gable, no chimney)."""


def edge(spec, i):
    """Footprint edge i: (a, b, unit direction, outward normal, length), 2D arrays."""
    p = spec.poly
    a, b = p[i], p[(i + 1) % len(p)]
    d = b - a
    L = float(np.linalg.norm(d))
    d = d / L
    n = np.array([d[1], -d[0]])  # outward for a counter-clockwise footprint
    return a, b, d, n, L


def hull_edges(spec) -> list[int]:
    """Footprint edges the whole footprint lies behind (edges of its convex hull): a
    building can hinge about them."""
    p = spec.poly
    out = []
    for i in range(len(p)):
        a, _, _, n, _ = edge(spec, i)
        if float(np.max((p - a) @ n)) <= 1e-6:
            out.append(i)
    return out


def exposed_hull_edges(spec) -> list[int]:
    """Hull edges facing a street or yard when there are any, else all hull edges."""
    hull = hull_edges(spec)
    ex = [i for i in hull if i in spec.exposed_edges()]
    return ex or hull


def interval_planes(a, d, t0, t1):
    """Two vertical planes bounding the slab of space a + d*t, t in [t0, t1]."""
    p0 = (float(a[0] + d[0] * t0), float(a[1] + d[1] * t0), 0.0)
    p1 = (float(a[0] + d[0] * t1), float(a[1] + d[1] * t1), 0.0)
    return [(p0, (float(-d[0]), float(-d[1]), 0.0)), (p1, (float(d[0]), float(d[1]), 0.0))]


def z_above(z):
    return ((0.0, 0.0, float(z)), (0.0, 0.0, -1.0))


def z_below(z):
    return ((0.0, 0.0, float(z)), (0.0, 0.0, 1.0))


def half_space_x(xc, keep_greater: bool):
    """Plane selecting x > xc (keep_greater) or x < xc."""
    return ((float(xc), 0.0, 0.0), (-1.0, 0.0, 0.0) if keep_greater else (1.0, 0.0, 0.0))


def split_for_fraction(spec, fraction, from_high: bool):
    """x position cutting off `fraction` of the footprint area at the high-x (or low-x) end."""
    p = spec.poly
    x0, _, x1, _ = spec.bbox
    total = abs(poly2d.area(p))
    lo, hi = x0, x1
    for _ in range(40):
        xc = 0.5 * (lo + hi)
        part = poly2d.clip_halfplane(p, (xc, 0.0), (-1.0, 0.0) if from_high else (1.0, 0.0))
        frac = abs(poly2d.area(part)) / total if len(part) else 0.0
        if (frac > fraction) == from_high:
            lo = xc
        else:
            hi = xc
    return 0.5 * (lo + hi)


def region_polygon(spec, xc, from_high: bool):
    return poly2d.clip_halfplane(spec.poly, (xc, 0.0), (-1.0, 0.0) if from_high else (1.0, 0.0))


def rnd(x, nd=4):
    """JSON-friendly rounding of floats (and of numpy scalars)."""
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return round(v, nd) if math.isfinite(v) else None
    if isinstance(x, dict):
        return {k: rnd(v, nd) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [rnd(v, nd) for v in x]
    return x


def rng_choice(rng, items):
    return items[int(rng.integers(0, len(items)))]
