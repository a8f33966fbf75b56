"""Rigid motions of the whole building: tilt and overturn about a base edge."""
from __future__ import annotations

import math

import numpy as np

from .common import edge, exposed_hull_edges, hull_edges
from .mesh import INTERIOR, P_BASE, Labels, add_polygon, rotation_matrix, transform_verts


def _rotation_about_edge(spec, i, angle_deg, lean_out: bool):
    """Rotation about footprint edge i at z = 0. lean_out: the building leans out over the
    edge (its top moves outward); otherwise the far side sinks."""
    a, b, d, n, L = edge(spec, i)
    axis = np.array([d[0], d[1], 0.0])
    pivot = np.array([a[0], a[1], 0.0])
    R = rotation_matrix(axis, math.radians(angle_deg))
    top = np.array([a[0] - n[0], a[1] - n[1], 1.0])  # a point above the inside
    moved = R @ (top - pivot) + pivot
    outward = float(np.dot(moved[:2] - top[:2], n))
    if (outward > 0) != lean_out:
        R = rotation_matrix(axis, -math.radians(angle_deg))
    return R, pivot


def tilt(bm, spec, rng, building_id, angle=2.0):
    """The whole building rotates `angle` degrees about a base edge, the far side sinking
    (foundation failure)."""
    hinges = hull_edges(spec)
    i = hinges[int(rng.integers(0, len(hinges)))]
    R, pivot = _rotation_about_edge(spec, i, angle, lean_out=False)
    transform_verts(list(bm.verts), rot=R, pivot=pivot)
    bm.normal_update()
    return {"angle": angle, "hinge_edge": i}


def overturn(bm, spec, rng, building_id, angle=60.0):
    """The whole building overturns `angle` degrees over a base edge (lands within its
    height of the footprint); its underside becomes visible."""
    lab = Labels(bm)
    hinges = exposed_hull_edges(spec)
    i = hinges[int(rng.integers(0, len(hinges)))]
    add_polygon(bm, lab, [(float(x), float(y), 0.0) for x, y in spec.poly[::-1]], INTERIOR, building_id, P_BASE, 0, 0)
    R, pivot = _rotation_about_edge(spec, i, angle, lean_out=True)
    transform_verts(list(bm.verts), rot=R, pivot=pivot)
    bm.normal_update()
    return {"angle": angle, "hinge_edge": i}
