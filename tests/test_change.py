"""Change mapping and the changed/unchanged split on scans with known change."""
import numpy as np
import pytest

from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import preset
from quakescan.change.split import (ChangeError, SplitSettings, building_changes, feature_changes, lod_from_noise,
                         morton_order, nearest_neighbours, nearest_neighbours_reference, split_changed)
from quakescan.formats.pointcloud import read_epoch
from quakescan.formats.synthetic import box_city


def test_nearest_neighbours_match_brute_force():
    rng = np.random.default_rng(1)
    pre = rng.uniform(0, 10, (500, 3))
    post = rng.uniform(0, 10, (400, 3))
    idx, dist = nearest_neighbours(pre, post)
    d_all = np.linalg.norm(pre[:, None, :] - post[None, :, :], axis=2)
    np.testing.assert_array_equal(idx, d_all.argmin(axis=1))
    np.testing.assert_allclose(dist, d_all.min(axis=1))
    assert sorted(morton_order(pre)) == list(range(500))


@pytest.mark.parametrize("case", ["flat post, queries off the grid", "mm grid with ties", "far: collapse",
                                  "one column", "duplicates"])
def test_grid_nearest_neighbours_are_exact(case):
    """The column-grid search finds a point at the brute-force minimum distance in the
    cases that stress it (far queries go through the kd-tree fallback, which may pick
    another of several equally near points)."""
    rng = np.random.default_rng(7)
    pre = rng.uniform(0, 10, (2000, 3))
    post = rng.uniform(0, 10, (1500, 3))
    if case == "flat post, queries off the grid":
        post[:, 2] = 0.0
        pre[:500, 0] += 30.0
        pre[500:1000, 1] -= 25.0
    elif case == "mm grid with ties":
        post, pre = np.round(post, 1), np.round(pre, 1)
    elif case == "far: collapse":
        pre[:, 2] += 12.0  # every neighbour metres away: beyond the rings
    elif case == "one column":
        post[:, :2] = 5.0
    elif case == "duplicates":
        post[750:] = post[:750]
    idx, dist = nearest_neighbours(pre, post)
    d2 = ((pre[:, None, :] - post[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(d2[np.arange(len(pre)), idx], d2.min(axis=1))
    if case != "far: collapse":
        near = np.sqrt(d2.min(axis=1)) < 0.5  # resolved inside the grid: lower index wins ties
        np.testing.assert_array_equal(idx[near], d2.argmin(axis=1)[near])
    np.testing.assert_allclose(dist, np.sqrt(d2.min(axis=1)), rtol=1e-12)
    ref_i, ref_d = nearest_neighbours_reference(pre, post)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-12)



@pytest.mark.parametrize("case", ["uniform", "mm grid with ties", "one column", "duplicates"])
def test_nn_kernels_match_their_numpy_reference(case):
    """Each compiled step of the grid search against `quakescan.change._nn_reference`, exactly: the same
    grid, the same column and z order, the same nearest point (lower index on ties)."""
    from quakescan.change import _nn_kernels as K
    from quakescan.change import _nn_reference as R

    rng = np.random.default_rng(8)
    pre = rng.uniform(-1, 11, (700, 3))
    post = rng.uniform(0, 10, (900, 3))
    if case == "mm grid with ties":
        post, pre = np.round(post, 1), np.round(pre, 1)
    elif case == "one column":
        post[:, :2] = 5.0
    elif case == "duplicates":
        post[450:] = post[:450]
    bx = K.bounds_xy(post)
    np.testing.assert_array_equal(bx, R.bounds_xy(post))
    cell = 0.7
    nx, ny = int((bx[2] - bx[0]) // cell) + 1, int((bx[3] - bx[1]) // cell) + 1
    col = K.column_index(post, bx[0], bx[1], cell, nx, ny)
    np.testing.assert_array_equal(col, R.column_index(post, bx[0], bx[1], cell, nx, ny))
    order, starts = K.counting_sort(col, nx * ny)
    ref_order, ref_starts = R.counting_sort(col, nx * ny)
    np.testing.assert_array_equal(order, ref_order)
    np.testing.assert_array_equal(starts, ref_starts)
    sorted_xyz = K.sort_columns_by_z(order, starts, post)
    for a, b in zip(sorted_xyz, R.sort_columns_by_z(ref_order, ref_starts, post)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(order, ref_order)
    want_i, want_d = np.empty(len(pre), np.int64), np.empty(len(pre))
    R.nearest(pre, *sorted_xyz, order, want_i, want_d)
    for max_ring, whole_grid in ((1, False), (nx + ny, True)):
        idx, dist = np.empty(len(pre), np.int64), np.empty(len(pre))
        K.nearest(pre, *sorted_xyz, order, starts, bx[0], bx[1], cell, nx, ny, max_ring, idx, dist)
        found = idx >= 0  # with few rings the far queries are left to the kd-tree
        assert found.all() if whole_grid else found.any()
        np.testing.assert_array_equal(idx[found], want_i[found])
        np.testing.assert_array_equal(dist[found], want_d[found])

def test_nearest_neighbours_at_utm_coordinates_match_the_local_frame():
    rng = np.random.default_rng(3)
    pre = rng.uniform(0, 50, (3000, 3))
    post = pre + rng.normal(0, 0.01, pre.shape)
    shift = np.array([500000.0, 5000000.0, 0.0])
    a = nearest_neighbours(pre, post)
    b = nearest_neighbours(pre + shift, post + shift)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], atol=1e-9)


def test_empty_post_epoch_is_an_error():
    with pytest.raises(ChangeError, match="no points"):
        nearest_neighbours(np.zeros((3, 3)), np.zeros((0, 3)))


def test_lod_from_noise_closed_form():
    assert lod_from_noise(0.0, 0.1) == pytest.approx(1.96 * 0.05)
    assert lod_from_noise(0.05, 0.0) == pytest.approx(1.96 * np.sqrt(2) * 0.05)


def _epochs(tmp_path, heights_post, seed_post):
    heights_pre = (9.0, 12.0, 9.0, 12.0)
    s = preset("paper").replace(pulse_rate_hz=100_000.0)
    pre_scene = box_city(rows=2, cols=2, height=heights_pre, origin=(500000.0, 5000000.0, 0.0))
    post_scene = box_city(rows=2, cols=2, height=heights_post, origin=(500000.0, 5000000.0, 0.0), epoch="post")
    scan(pre_scene, s, tmp_path / "pre.las", seed=1)
    scan(post_scene, s, tmp_path / "post.las", seed=seed_post)
    pre = read_epoch(tmp_path / "pre.las")
    post = read_epoch(tmp_path / "post.las", origin=pre.origin)
    return pre, post


def _run(pre, post):
    idx, dist = nearest_neighbours(pre.xyz, post.xyz)
    zeros = {"curvature": np.zeros(len(pre))}
    changes = feature_changes(zeros, {"curvature": np.zeros(len(post))}, idx)
    d_height = post.xyz[idx, 2] - pre.xyz[:, 2]
    return building_changes(pre.building_id, post.building_id, changes, d_height, dist, SplitSettings())


def test_identical_city_rescanned_has_no_changed_building(tmp_path):
    pre, post = _epochs(tmp_path, (9.0, 12.0, 9.0, 12.0), seed_post=2)  # new range noise only
    result = _run(pre, post)
    assert len(result) == 4
    for b in result:
        assert b.share_changed == 0.0 and not b.changed.any()
        assert b.descriptors["height_mean"] == 0.0


def test_collapsed_building_is_found_changed(tmp_path):
    pre, post = _epochs(tmp_path, (9.0, 4.0, 9.0, 12.0), seed_post=2)  # building 2 loses 8 m
    result = {b.building_id: b for b in _run(pre, post)}
    assert result[2].share_changed > 0.3
    assert result[2].descriptors["height_median"] < -5.0
    for bid in (1, 3, 4):
        assert result[bid].share_changed < 0.02


def test_split_is_gated_by_the_lod():
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 0.02, 1000)
    s = SplitSettings()
    assert not split_changed(np.zeros(1000), noise, s).any()  # two clusters of noise: nothing changed
    d_h = noise.copy()
    d_h[:100] -= 3.0
    changed = split_changed(np.zeros(1000), d_h, s)
    assert changed[:100].all() and not changed[100:].any()
