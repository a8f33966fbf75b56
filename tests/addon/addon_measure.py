"""Measures on meshes for the add-on tests (numpy; closed-form comparisons)."""
import math

import numpy as np

GROUND, ROOF, WALL, DEBRIS, INTERIOR = 0, 1, 2, 3, 4


def tri_areas(v, t):
    a = v[t[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a), axis=1)


def tri_normals(v, t):
    a = v[t[:, 0]]
    n = np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def area(v, t, mask):
    return float(tri_areas(v, t)[mask].sum())


def hf_volume(v, t, mask, base_z=0.0):
    """Volume under the selected triangles above z = base_z (signed by facing)."""
    tt = t[mask]
    a, b, c = v[tt[:, 0]], v[tt[:, 1]], v[tt[:, 2]]
    axy = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))
    return float((axy * ((a[:, 2] + b[:, 2] + c[:, 2]) / 3 - base_z)).sum())


def tilt_deg(normal):
    n = np.asarray(normal, dtype=float)
    return math.degrees(math.acos(min(1.0, abs(n[2]) / np.linalg.norm(n))))


def check_valid(v, t, surf, bid, building_id=None):
    """The scene contract's mesh rules: finite, no degenerate faces, codes 0..4."""
    assert np.isfinite(v).all(), "NaN/inf vertex"
    if len(t):
        assert tri_areas(v, t).min() > 1e-10, "degenerate face"
    assert surf.max(initial=0) <= 4
    if building_id is not None:
        assert set(np.unique(bid).tolist()) <= {building_id}
