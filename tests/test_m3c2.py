"""M3C2 distances and levels of detection against closed-form answers (core/change/m3c2.py)."""
import math

import numpy as np
import pytest

from quakescan.change.features import compute_features
from quakescan.change.m3c2 import (
    ColumnGrid,
    M3C2Error,
    M3C2Result,
    M3C2Settings,
    curvature_lod,
    curvature_standard_error,
    cylinder_radius,
    m3c2,
    orient_normals,
    voxel_core_points,
)


def noisy_plane(rng, density, sigma, size=20.0, z0=0.0):
    n = rng.poisson(density * size * size)
    xy = rng.uniform(0, size, (n, 2))
    return np.column_stack([xy, z0 + rng.normal(0, sigma, n)])


def grid_cores(size=20.0, margin=2.0, step=1.0, z=0.0):
    g = np.arange(margin, size - margin + 1e-9, step)
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)])


def run(pre, post, cores, normals, radius, **kw):
    s = M3C2Settings(**kw)
    return m3c2(cores, normals, ColumnGrid(pre, radius), ColumnGrid(post, radius), s, radius)


@pytest.mark.parametrize("statistic, efficiency", [("mean", 1.0), ("median", math.sqrt(math.pi / 2))])
def test_two_noisy_planes_give_the_closed_form_lod_and_five_percent_false_positives(statistic, efficiency):
    """Lague et al.'s LoD, 1.96 sqrt(s1²/n1 + s2²/n2), for means; medians scatter sqrt(pi/2)
    times as much on normal noise, and the robust spread (1.4826 MAD) estimates s."""
    rng = np.random.default_rng(0)
    rho1, s1, rho2, s2, r = 100.0, 0.02, 25.0, 0.05, 0.5
    pre, post = noisy_plane(rng, rho1, s1), noisy_plane(rng, rho2, s2)
    cores = grid_cores(step=0.6)
    res = run(pre, post, cores, np.tile([0, 0, 1.0], (len(cores), 1)), r, statistic=statistic)
    n1, n2 = math.pi * r * r * rho1, math.pi * r * r * rho2
    assert np.median(res.n_pre) == pytest.approx(n1, rel=0.05)
    assert np.median(res.n_post) == pytest.approx(n2, rel=0.08)
    from scipy.stats import t

    k = 32 if statistic == "median" else np.inf  # medians come from a sample of at most 32 points
    m1, m2 = min(n1, k), min(n2, k)
    v1, v2 = s1 ** 2 / m1, s2 ** 2 / m2
    scale = 0.37 if statistic == "median" else 1.0  # a MAD is worth 37 % of the points of a std
    df = (v1 + v2) ** 2 / (v1 ** 2 / (scale * (m1 - 1)) + v2 ** 2 / (scale * (m2 - 1)))  # Welch-Satterthwaite
    expected_lod = t.ppf(0.975, df) * efficiency * math.sqrt(v1 + v2)
    assert np.median(res.lod) == pytest.approx(expected_lod, rel=0.1)
    assert abs(np.mean(res.distance)) < 0.003
    # a 95 % test flags ~5 % of an unchanged surface: that is what "significant" means
    assert 0.02 < res.significant.mean() < 0.09
    assert not res.lost.any()


def test_an_offset_larger_than_the_lod_is_detected_everywhere_and_measured():
    rng = np.random.default_rng(1)
    pre, post = noisy_plane(rng, 50, 0.02), noisy_plane(rng, 50, 0.02, z0=0.25)
    cores = grid_cores()
    res = run(pre, post, cores, np.tile([0, 0, 1.0], (len(cores), 1)), 0.5)
    assert res.significant.all()
    assert np.median(res.distance) == pytest.approx(0.25, abs=0.005)


def test_registration_error_widens_the_lod_as_lague_et_al():
    rng = np.random.default_rng(2)
    pre, post = noisy_plane(rng, 50, 0.02), noisy_plane(rng, 50, 0.02)
    cores = grid_cores()
    normals = np.tile([0, 0, 1.0], (len(cores), 1))
    a = run(pre, post, cores, normals, 0.5)
    b = run(pre, post, cores, normals, 0.5, registration_error_m=0.05)
    np.testing.assert_allclose(b.lod - a.lod, 1.96 * 0.05)
    assert b.significant.sum() <= a.significant.sum()


def test_tilted_plane_offset_along_its_normal_at_utm_coordinates():
    rng = np.random.default_rng(3)
    tilt = math.radians(35)
    normal = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    u = np.array([math.cos(tilt), 0.0, -math.sin(tilt)])
    v = np.array([0.0, 1.0, 0.0])

    def plane(offset, sigma):
        st = rng.uniform(0, 20, (8000, 2))
        return st[:, :1] * u + st[:, 1:] * v + (offset + rng.normal(0, sigma, (len(st), 1))) * normal

    origin = np.array([500_000.0, 5_000_000.0, 300.0])
    pre, post = plane(0.0, 0.01) + origin, plane(0.4, 0.01) + origin
    st = np.stack(np.meshgrid(np.arange(3, 17.0), np.arange(3, 17.0)), -1).reshape(-1, 2)
    cores = st[:, :1] * u + st[:, 1:] * v + origin
    res = run(pre, post, cores, np.tile(normal, (len(cores), 1)), 0.6)
    assert res.significant.all()
    np.testing.assert_allclose(res.distance, 0.4, atol=0.02)  # medians of 32-point samples: sd ~4 mm


def test_a_roof_hole_is_lost_where_the_floor_below_shows_through_and_unseen_where_nothing_does():
    rng = np.random.default_rng(4)
    pre = noisy_plane(rng, 50, 0.01, z0=10.0)
    hole = (np.abs(pre[:, 0] - 10) < 3) & (np.abs(pre[:, 1] - 10) < 3)
    post = pre[~hole].copy()
    post[:, 2] += rng.normal(0, 0.01, len(post))
    floor = noisy_plane(rng, 50, 0.01, z0=4.0)  # the storey below, 6 m down, seen through the hole
    seen_floor = floor[(floor[:, 0] > 10) & (np.abs(floor[:, 0] - 10) < 3) & (np.abs(floor[:, 1] - 10) < 3)]
    cores = grid_cores(z=10.0)
    res = run(pre, np.vstack([post, seen_floor]), cores, np.tile([0, 0, 1.0], (len(cores), 1)), 0.5,
              max_depth_m=2.0)
    inside = (np.abs(cores[:, 0] - 10) < 2.4) & (np.abs(cores[:, 1] - 10) < 2.4)
    east = cores[:, 0] > 10.6
    assert (res.lost & res.seen_through)[inside & east].all()  # gone: the floor below shows through
    west = inside & (cores[:, 0] < 9.4)
    assert res.lost[west].all() and not res.seen_through[west].any()  # nothing in front or behind
    assert res.unseen[west].all()
    assert not res.lost[~inside & ((np.abs(cores[:, 0] - 10) > 3.6) | (np.abs(cores[:, 1] - 10) > 3.6))].any()
    # a vertical wall x = 5 pushed out by 0.3 m: horizontal normals measure it
    yz = rng.uniform(0, 10, (6000, 2))
    wall_pre = np.column_stack([np.full(len(yz), 5.0) + rng.normal(0, 0.01, len(yz)), yz])
    wall_post = wall_pre + [0.3, 0, 0]
    wc = np.column_stack([np.full(16, 5.0), np.linspace(2, 8, 16), np.linspace(2, 8, 16)])
    normals = orient_normals(np.tile([-1.0, 0, 0], (16, 1)), wc[:, :2], np.array([0.0, 5.0]))
    assert np.all(normals[:, 0] == 1.0)  # turned away from the centre at x = 0
    w = run(wall_pre, wall_post, wc, normals, 0.5)
    np.testing.assert_allclose(w.distance, 0.3, atol=0.01)


def test_undefined_normals_and_empty_epochs_are_not_comparable():
    rng = np.random.default_rng(5)
    pre = noisy_plane(rng, 20, 0.01)
    cores = grid_cores()[:5]
    normals = np.tile([0, 0, 1.0], (5, 1))
    normals[0] = np.nan
    res = m3c2(cores, normals, ColumnGrid(pre, 0.5), ColumnGrid(np.zeros((0, 3)), 0.5), M3C2Settings())
    assert not res.comparable.any() and not res.significant.any()
    assert res.lost[1:].all() and not res.lost[0] and not res.seen_through.any()
    assert res.unseen.all()  # nothing observed after: unknown
    assert not res.lost_beyond_chance(0.0).any()  # a post-event flight that sees nothing there
    with pytest.raises(M3C2Error, match="shape"):
        m3c2(cores, normals[:3], ColumnGrid(pre, 0.5), ColumnGrid(pre, 0.5), M3C2Settings())
    with pytest.raises(M3C2Error, match="max_depth_m"):
        M3C2Settings(max_depth_m=0)


def test_cylinder_radius_grows_for_sparse_epochs():
    s = M3C2Settings(cylinder_radius_m=0.5, min_points=6)
    assert cylinder_radius(s, 250.0) == 0.5
    r = cylinder_radius(s, 3.0)
    assert math.pi * r * r * 3.0 == pytest.approx(6.0)
    assert cylinder_radius(s, 0.0) == 0.5


def test_voxel_core_points_are_one_per_voxel_whatever_the_density():
    rng = np.random.default_rng(6)
    dense, sparse = noisy_plane(rng, 400, 0.0), noisy_plane(rng, 16, 0.0)
    a, b = voxel_core_points(dense, 1.0), voxel_core_points(sparse, 1.0)
    assert len(a) == 400 and abs(len(b) - 400) < 8  # 1 m voxels on a 20 x 20 m plane
    assert np.all(np.diff(a) > 0)
    assert len(voxel_core_points(np.zeros((0, 3)), 1.0)) == 0


def test_curvature_standard_error_matches_the_spread_of_fitted_curvature_on_noisy_planes():
    """|H| of a noisy plane is the absolute value of a normal variable with the predicted
    standard error: its mean is SE * sqrt(2/pi)."""
    rng = np.random.default_rng(7)
    sigma, r = 0.03, 1.5
    cloud = noisy_plane(rng, 30, sigma, size=40)
    q = np.flatnonzero((np.abs(cloud[:, 0] - 20) < 15) & (np.abs(cloud[:, 1] - 20) < 15))[::7]
    f = compute_features(cloud, r, ("curvature", "eigenvalue1", "eigenvalue2", "eigenvalue3", "num_neighbours"),
                         query_index=q)
    se = curvature_standard_error(f["eigenvalue1"], f["eigenvalue2"], f["eigenvalue3"], f["num_neighbours"])
    closed_form = sigma * math.sqrt(48 / (30 * math.pi * r * r)) / r ** 2
    assert np.median(se) == pytest.approx(closed_form, rel=0.1)
    assert np.mean(f["curvature"]) == pytest.approx(np.median(se) * math.sqrt(2 / math.pi), rel=0.15)
    lod = curvature_lod(se, se)
    assert np.mean(np.abs(f["curvature"][1:] - f["curvature"][:-1]) > lod[1:]) < 0.06
    assert np.isnan(curvature_standard_error(1.0, 0.0, 0.0, 10))


def test_sparse_cylinders_keep_the_false_positive_rate_near_five_percent():
    """Five or six points per cylinder (an airborne archive's density): their spread is itself
    uncertain; with Student's quantile for the Welch-Satterthwaite degrees of freedom an
    unchanged surface stays near the nominal 5 %, where the normal quantile flags far more."""
    rng = np.random.default_rng(8)
    pre, post = noisy_plane(rng, 7, 0.03, size=60), noisy_plane(rng, 7, 0.03, size=60)
    cores = grid_cores(size=60, step=1.5)
    normals = np.tile([0, 0, 1.0], (len(cores), 1))
    res = run(pre, post, cores, normals, 0.5, min_comparable=4, statistic="mean")
    assert np.median(res.n_pre[res.comparable]) <= 7
    rate = res.significant[res.comparable].mean()
    assert rate < 0.08
    z_only = res.comparable & (np.abs(res.distance) > 1.96 * np.sqrt(res.std_pre ** 2 / res.n_pre
                                                                      + res.std_post ** 2 / res.n_post))
    assert z_only[res.comparable].mean() > rate + 0.02


def _result(n_pre, near_pre, n_post, near_post, alpha):
    """One significant core point (distance 1 m, LoD 0.1 m) with the given cylinder counts."""
    one = np.ones(1)
    return M3C2Result(one, 0.1 * one, np.array([n_pre]), np.array([n_post]), one, one, 1.0, 4, None,
                      np.array([near_pre]), np.array([near_post]), alpha)


@pytest.mark.parametrize("n_post,near_post,alpha,expected", [
    # 10 post-event points, half of the pre-event ones near the core point: P(X <= 1) = 11/1024
    (10, 1, 0.01, False), (10, 1, 0.02, True), (10, 0, 0.01, True),  # P(X = 0) = 1/1024
    (10, 1, 0.0, True),  # the share rule alone: 0.1 < 0.25 x 0.5
    (10, 2, 0.0, False),  # 0.2 >= 0.125: the surface is still there
    (100, 10, 0.01, True),  # dense: P(X <= 10 | 100, 0.5) ~ 1e-17, the share rule decides
])
def test_a_surface_is_displaced_only_where_chance_does_not_explain_the_missing_points(n_post, near_post, alpha,
                                                                                       expected):
    assert _result(100, 50, n_post, near_post, alpha).displaced.tolist() == [expected]


def test_settings_stored_before_the_chance_test_keep_the_share_rule():
    assert M3C2Settings().displaced_alpha == 0.01
    assert M3C2Settings.from_json({}).displaced_alpha == 0.0
    assert M3C2Settings.from_json(M3C2Settings().to_json()) == M3C2Settings()
    from quakescan.change.surface import SurfaceSettings

    stored = SurfaceSettings().to_json()
    del stored["m3c2"]["displaced_alpha"]
    assert SurfaceSettings.from_json(stored).m3c2.displaced_alpha == 0.0
    with pytest.raises(M3C2Error, match="displaced_alpha"):
        M3C2Settings(displaced_alpha=1.5)


@pytest.mark.parametrize("sample", [8, 32])
def test_cylinder_kernel_matches_the_numpy_reference(sample):
    """`_m3c2_kernels.cylinder_robust` against `quakescan.change._m3c2_reference` on a roof, a wall and
    scattered points, cylinders of every orientation: the kernel's grid and z runs skip only
    points no cylinder can hold, so counts, the reservoir sample (median, spread) and the
    running sums are the reference's to the bit."""
    from quakescan.change import _m3c2_reference as R

    rng = np.random.default_rng(14)
    roof = noisy_plane(rng, 60, 0.03, size=10.0, z0=5.0)
    wall = np.column_stack([rng.uniform(0, 10, 1500), np.full(1500, 4.0) + rng.normal(0, 0.02, 1500),
                            rng.uniform(0, 5, 1500)])
    xyz = np.vstack([roof, wall, rng.uniform(0, 10, (500, 3))])
    grid = ColumnGrid(xyz, 0.5)
    m = 300
    centres = np.column_stack([rng.uniform(0, 10, (m, 2)), rng.choice([5.0, 2.5], m)])
    axes = rng.normal(size=(m, 3))
    axes[:100] = [0, 0, 1.0]
    axes[100:150] = [0, 1.0, 0]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    r, h, hb, hn = rng.uniform(0.2, 0.8, m), np.full(m, 1.0), np.full(m, 6.0), np.full(m, 0.15)
    fast = grid.cylinders(centres, axes, r, h, hb, sample=sample, near_length=0.15)
    count, behind, near = (np.zeros(m, np.int64) for _ in range(3))
    median, spread, mean, var = (np.empty(m) for _ in range(4))
    R.cylinder_robust(*centres.T, *axes.T, r, h, hb, hn, grid.px, grid.py, grid.pz, np.empty((m, sample)),
                      count, median, spread, behind, near, mean, var)
    assert (count > sample).sum() > 50 and (behind > 0).sum() > 20 and (count == 0).any()
    for name, want in (("count", count), ("behind", behind), ("near", near), ("median", median),
                       ("spread", spread), ("mean", mean), ("var", var)):
        np.testing.assert_array_equal(getattr(fast, name), want, err_msg=name)
