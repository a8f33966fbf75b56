"""Each compiled loop of the scanner (`_scan_kernels`) against its numpy reference of the same
name (`_scan_reference`), on arrays made to reach every branch: misses, grazing rays, hits
beyond the range, pulses at scan-line and FOV edges, echoes that merge and that are too weak.
Whole scans of both paths are compared byte for byte in tests/test_scan.py."""
import math

import numpy as np
import pytest

from quakescan.acquisition import _scan_kernels as K
from quakescan.acquisition import _scan_reference as R


def unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_the_two_modules_offer_the_same_loops_of_the_general_path():
    for name in ("pulse_rays", "refine_hits", "fov_pulses", "flag_discontinuities_rows", "sub_rays", "form_returns"):
        assert callable(getattr(K, name)) and callable(getattr(R, name)), name
    assert R.loops(True) is K and R.loops(False) is R


def test_pulse_rays():
    rng = np.random.default_rng(0)
    t, theta = np.sort(rng.uniform(10, 11, 500)), rng.uniform(-1, 1, 500)
    args = (10.0, np.array([5.0, -3.0, 80.0]), np.array([8.0, 0.5, 0.0]), np.array([0.1, 0.0, -0.995]),
            np.array([0.0, -1.0, 0.0]))
    for a, b in zip(K.pulse_rays(t, theta, *args), R.pulse_rays(t, theta, *args)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_refine_hits_drops_grazing_rays_and_hits_beyond_the_range():
    rng = np.random.default_rng(1)
    n = 400
    normals = unit(rng.normal(size=(50, 3)))
    plane_d = rng.uniform(-20, 20, 50)
    origins = rng.uniform(-10, 10, (n, 3))
    directions = unit(rng.normal(size=(n, 3)))
    face = rng.integers(-1, 50, n)
    # grazing: exactly parallel to the face's plane
    directions[:20] = unit(np.cross(normals[face[:20].clip(0)], rng.normal(size=(20, 3))))
    fk, fr = face.copy(), face.copy()
    tk = K.refine_hits(origins, directions, fk, normals, plane_d, 15.0)
    tr = R.refine_hits(origins, directions, fr, normals, plane_d, 15.0)
    np.testing.assert_array_equal(fk, fr)
    # the kernel sums the dot products in its own order: equal to the last bits, which LAS
    # coordinates (millimetres) never see - whole scans are compared byte for byte
    np.testing.assert_allclose(tk, tr, rtol=1e-12, atol=0)
    assert (fk == -1).sum() > (face == -1).sum()  # some hits were dropped (behind, beyond or grazing)
    assert np.isinf(tk[fk < 0]).all() and (tk[fk >= 0] <= 15.0).all()


@pytest.mark.parametrize("oscillating", [False, True])
def test_fov_pulses_at_line_and_fov_edges(oscillating):
    prr, rate, g0 = 50_000.0, 80.0, 3.2
    half_sweep = math.radians(165.0) if not oscillating else math.radians(37.5)
    half_fov = math.radians(30.0) + 1e-12
    lo = np.array([0, 700, 5_000], np.int64)
    hi = np.array([400, 2_000, 4_999], np.int64)  # the last run is empty
    for aim in ((-math.inf, math.inf), (-0.2, 0.35)):
        k = K.fov_pulses(lo, hi, 100.0, prr, rate, g0, half_sweep, half_fov, oscillating, *aim)
        r = R.fov_pulses(lo, hi, 100.0, prr, rate, g0, half_sweep, half_fov, oscillating, *aim)
        for a, b in zip(k[:-1], r[:-1]):
            np.testing.assert_array_equal(a, b)
        assert k[-1] == r[-1]
        if aim[0] == -math.inf:  # every pulse inside the FOV kept; some end a scan line or the FOV
            assert len(k[0]) == k[-1] and k[4].any() and not k[4].all()
        else:
            assert 0 < len(k[0]) < k[-1]


def test_flag_discontinuities_rows_over_segments_with_gaps():
    """Nadir pulses over a flat roof (face 0) with a raised block (face 1, 5 m higher) and
    misses: only pulses next to a step or a miss are flagged; pulses not cast count as misses."""
    rng = np.random.default_rng(2)
    n_ext = 300
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    segments = []
    start = 0
    for size in (90, 120, 60):
        pos = np.sort(rng.choice(np.arange(start, start + size), size - 3, replace=False))  # 3 not cast
        m = len(pos)
        face = np.where((pos // 25) % 4 == 1, 1, 0)
        face[rng.random(m) < 0.02] = -1
        t = np.where(face == 1, 45.0, 50.0) + rng.normal(0, 0.01, m)
        t[face < 0] = 0.0
        origins = np.column_stack([pos * 0.1, np.zeros(m), np.full(m, 50.0)])
        segments.append((pos.astype(np.int64), origins, np.tile([0.0, 0.0, -1.0], (m, 1)), t, face))
        start += size
    offsets = np.array([1, 2, 17], np.int64)
    fk = K.flag_discontinuities_rows(n_ext, tuple(segments), offsets, normals, 0.5)
    fr = R.flag_discontinuities_rows(n_ext, segments, offsets, normals, 0.5)
    for a, b in zip(fk, fr):
        np.testing.assert_array_equal(a, b)
    flagged = np.concatenate(fk).mean()
    assert 0.1 < flagged < 0.9


def test_sub_rays():
    rng = np.random.default_rng(3)
    dirs = unit(rng.normal(size=(200, 3)))
    plane_normal = np.array([1.0, 0.0, 0.0])
    offsets = rng.normal(0, 2e-4, (7, 2))
    np.testing.assert_allclose(K.sub_rays(dirs, plane_normal, offsets), R.sub_rays(dirs, plane_normal, offsets),
                               rtol=0, atol=1e-15)


def test_form_returns_merges_close_echoes_and_drops_weak_ones():
    rng = np.random.default_rng(4)
    n, k = 300, 7
    t = rng.choice([50.0, 50.1, 53.0, 58.0, np.inf], size=(n, k)) + rng.normal(0, 0.02, (n, k))
    face = np.where(np.isfinite(t), rng.integers(0, 9, (n, k)), -1)
    w = rng.uniform(0.5, 1.5, k)
    w /= w.sum()
    for max_returns in (1, 3):
        a = K.form_returns(t, face, w, 0.8, 0.15, max_returns)
        b = R.form_returns(t, face, w, 0.8, 0.15, max_returns)
        for x, y in zip(a, b):
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
        assert a[3].max() == min(max_returns, 3)  # 50.0 and 50.1 merge: at most three echoes
