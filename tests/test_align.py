"""ICP alignment of the post epoch on stable areas: closed-form answers on a synthetic terrain."""
import json
import logging
import math
import re

import numpy as np
import pytest

from quakescan.change.align import (Alignment, AlignmentError, align_epochs, format_alignment, open3d_threads,
                                    rotation_angle_deg, stable_mask)
from quakescan.errors import QuakeScanError

NOISE_M = 0.01
UTM = np.array([500_000.0, 5_000_000.0, 0.0])


def terrain_z(x, y):
    return 0.5 * np.sin(x / 7.0) + 0.3 * np.cos(y / 5.0)


def make_scene(n_ground=50_000, seed=1):
    """Smooth non-planar terrain on [-40, 40]² plus box-shaped objects (walls and roofs) so
    that x and y are constrained; ~60 k points, local coordinates."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-40, 40, size=(n_ground, 2))
    parts = [np.column_stack([xy, terrain_z(xy[:, 0], xy[:, 1])])]
    for cx, cy, w, d, h in [(-20, -15, 6, 9, 4), (10, 20, 12, 5, 6), (25, -25, 7, 7, 3), (-25, 22, 5, 14, 5),
                            (0, -5, 8, 4, 8)]:
        x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2
        base = terrain_z(cx, cy) - 0.5
        m = 400
        # roof
        parts.append(np.column_stack([rng.uniform(x0, x1, 2 * m), rng.uniform(y0, y1, 2 * m),
                                      np.full(2 * m, base + h)]))
        # four walls
        for fixed, lo, hi, axis in [(x0, y0, y1, 0), (x1, y0, y1, 0), (y0, x0, x1, 1), (y1, x0, x1, 1)]:
            s, z = rng.uniform(lo, hi, m), rng.uniform(base, base + h, m)
            f = np.full(m, fixed)
            parts.append(np.column_stack([f, s, z] if axis == 0 else [s, f, z]))
    return np.concatenate(parts)


def rigid(angle_deg, t):
    a = math.radians(angle_deg)
    m = np.eye(4)
    m[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    m[:3, 3] = t
    return m


def transform(m, xyz):
    return xyz @ m[:3, :3].T + m[:3, 3]


MOVE = rigid(0.5, [0.3, -0.2, 0.1])  # post = MOVE(pre) + noise


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(7)
    truth = make_scene()
    pre = truth + rng.normal(0, NOISE_M, truth.shape)
    post = transform(MOVE, truth) + rng.normal(0, NOISE_M, truth.shape)
    return truth, pre, post


def everything(xyz):
    return np.ones(len(xyz), bool)


@pytest.fixture(scope="module")
def aligned(scene):
    _, pre, post = scene
    return align_epochs(pre, post, everything(pre), everything(post))


def test_recovers_a_known_rigid_transform(scene, aligned):
    truth, _, _ = scene
    a = aligned
    combined = a.transform @ MOVE  # should be the identity
    assert rotation_angle_deg(combined) < 0.02
    assert np.abs(transform(combined, truth) - truth).max() < 0.01
    assert a.transform.dtype == np.float64 and a.transform.shape == (4, 4)
    # two independently noisy epochs: residual std ≈ √2 × noise
    assert 0.5 * NOISE_M < a.std_after_m < 3 * NOISE_M
    assert a.rmse_after_m < a.rmse_before_m
    assert a.rmse_before_m > 0.05
    assert a.fitness > 0.9
    assert a.n_stable_pre == a.n_stable_post == len(truth)
    assert abs(a.rotation_deg - 0.5) < 0.02
    # apply == the matrix, and moves post onto pre
    _, pre, post = scene
    assert np.abs(a.apply(post) - pre).max() < 0.1


def test_utm_coordinates_give_the_same_result(scene, aligned):
    _, pre, post = scene
    b = align_epochs(pre + UTM, post + UTM, everything(pre), everything(post))
    assert np.abs((b.apply(post + UTM) - UTM) - aligned.apply(post)).max() < 1e-3
    assert np.allclose(b.transform[:3, :3], aligned.transform[:3, :3], atol=1e-6)
    for k in ("std_after_m", "rmse_before_m", "rmse_after_m", "fitness"):
        assert getattr(b, k) == pytest.approx(getattr(aligned, k), abs=1e-6)
    assert np.allclose(b.translation_m, aligned.translation_m, atol=1e-3)


def test_identical_epochs_give_the_identity(scene):
    _, pre, _ = scene
    a = align_epochs(pre, pre.copy(), everything(pre), everything(pre))
    assert np.abs(a.transform - np.eye(4)).max() < 1e-6
    assert a.std_after_m < 1e-9 and a.rmse_after_m < 1e-9 and a.rmse_before_m < 1e-9
    assert a.fitness == pytest.approx(1.0)


def test_same_seed_same_transform_when_subsampling(scene):
    _, pre, post = scene
    kw = dict(max_points=20_000)
    a = align_epochs(pre, post, everything(pre), everything(post), seed=3, **kw)
    b = align_epochs(pre, post, everything(pre), everything(post), seed=3, **kw)
    assert np.allclose(a.transform, b.transform, atol=1e-9, rtol=0)
    assert a.std_after_m == pytest.approx(b.std_after_m, abs=1e-12)
    assert a.n_stable_pre == len(pre)  # counts before subsampling
    assert rotation_angle_deg(a.transform @ MOVE) < 0.05


def test_one_thread_gives_the_same_transform_and_restores_open3ds_limit(scene, aligned):
    import open3d as o3d

    _, pre, post = scene
    before = o3d.utility.get_max_threads()
    one = align_epochs(pre, post, everything(pre), everything(post), workers=1)
    assert o3d.utility.get_max_threads() == before
    # the transform is rounded to 1e-12: summing over one thread or several lands on it
    assert np.abs(one.transform - aligned.transform).max() <= 1e-12
    with open3d_threads(1):
        assert o3d.utility.get_max_threads() == 1
        with open3d_threads(-1):  # every core: the limit already set stands
            assert o3d.utility.get_max_threads() == 1
    assert o3d.utility.get_max_threads() == before
    with pytest.raises(RuntimeError), open3d_threads(1):
        raise RuntimeError("restored on the way out")
    assert o3d.utility.get_max_threads() == before


def test_too_few_stable_points(scene):
    _, pre, post = scene
    few = np.zeros(len(post), bool)
    few[:57] = True
    with pytest.raises(AlignmentError, match=r"too few stable points .*: 57 in post\.laz") as e:
        align_epochs(pre, post, everything(pre), few, post_name="post.laz")
    assert isinstance(e.value, QuakeScanError)
    with pytest.raises(AlignmentError, match=r": 0 in the pre-event epoch"):
        align_epochs(pre, post, np.zeros(len(pre), bool), everything(post))


def test_no_overlap(scene):
    _, pre, post = scene
    far = post + [0.0, 0.0, 20.0]
    with pytest.raises(AlignmentError, match=r"do not overlap within max_distance 1\.0 m"):
        align_epochs(pre, far, everything(pre), everything(far))


def test_large_transform_warns(scene, caplog):
    truth, pre, _ = scene
    post = transform(rigid(0.0, [0.0, 0.0, 6.0]), pre)
    with caplog.at_level(logging.WARNING, logger="quakescan.change.align"):
        a = align_epochs(pre, post, everything(pre), everything(post), max_distance_m=8.0)
    assert a.translation_m[2] == pytest.approx(-6.0, abs=0.01)
    assert "likely a wrong match" in caplog.text


def test_stable_mask():
    cls = np.array([2, 1, 6, 2, 5, 6, 1], np.uint8)
    bid = np.array([0, 0, 0, 3, 3, 4, 4])
    # ground always; outside buildings unless classified building; inside buildings never
    assert stable_mask(cls, bid).tolist() == [True, True, False, True, False, False, False]
    # without ids: only ground is trusted
    assert stable_mask(cls, None).tolist() == [True, False, False, True, False, False, False]
    with pytest.raises(AlignmentError):
        stable_mask(cls, bid[:3])
    # vegetation outside buildings (low 3, high 5) moves in the wind: not stable
    assert stable_mask(np.array([3, 5, 1], np.uint8), np.zeros(3, int)).tolist() == [False, False, True]


def test_json_and_summary(aligned):
    d = aligned.to_json()
    assert np.allclose(np.array(d["transform"]), aligned.transform)
    for k in ("rmse_before_m", "rmse_after_m", "std_after_m", "fitness", "n_stable_pre", "n_stable_post",
              "rotation_deg", "translation_m"):
        assert k in d
    json.dumps(d)
    s = format_alignment(aligned)
    assert "\n" not in s and "std 0.01" in s and "fitness 1.00" in s
    assert float(re.search(r"rotation ([0-9.]+)°", s).group(1)) == pytest.approx(0.5, abs=0.01)


def test_apply_is_float64():
    a = Alignment(rigid(90, [1, 0, 0]), 0.0, 0.0, 0.0, 1.0, 100, 100)
    out = a.apply(np.array([[1.0, 0.0, 0.0]], np.float32))
    assert out.dtype == np.float64
    assert np.allclose(out, [[1.0, 1.0, 0.0]])
