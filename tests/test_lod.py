"""Levels of detection measured on two acquisitions of the same undamaged buildings."""
import numpy as np
import pytest

from quakescan.change.lod import CalibrationError, calibrate
from quakescan.change.split import SplitSettings
from quakescan.formats.pointcloud import Epoch, read_epoch
from tests.scenes import HEIGHTS, scan_box_pair

UTM = np.array([500000.0, 5000000.0, 100.0])


def _roof(dz=0.0, origin=UTM, spacing=0.1, size=12.0):
    """A flat 12 m roof sampled on a grid (building 7) on a ground grid (ID 0), lifted by dz."""
    g = np.arange(-size / 2, size / 2 + 1e-9, spacing)
    x, y = np.meshgrid(g, g)
    roof = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 9.0 + dz)])
    gg = np.arange(-15.0, 15.0 + 1e-9, 0.5)
    gx, gy = np.meshgrid(gg, gg)
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    xyz = np.vstack([roof, ground])
    ids = np.concatenate([np.full(len(roof), 7), np.zeros(len(ground), np.int64)])
    cls = np.where(ids > 0, 6, 2).astype(np.uint8)
    return Epoch(xyz=xyz, origin=np.asarray(origin, float), classification=cls, building_id=ids, source="roof")


def test_a_roof_lifted_by_less_than_its_spacing_gives_that_lift_exactly():
    """Every roof point's nearest point in the second acquisition is its own copy 4 cm higher:
    |Δheight| is 0.04 m at every quantile; a plane stays a plane: no curvature change."""
    floor = SplitSettings(lod_height_m=0.01, lod_curvature=0.05)
    lod = calibrate(_roof(), _roof(dz=0.04), floor=floor, sample=5000)
    assert lod.height_at_quantile_m == pytest.approx(0.04, abs=1e-9)
    assert lod.lod_height_m == pytest.approx(0.04, abs=1e-9)
    assert lod.curvature_at_quantile == pytest.approx(0.0, abs=1e-9)
    assert lod.lod_curvature == 0.05  # the floor
    split = lod.split(floor)
    assert (split.lod_height_m, split.lod_curvature, split.min_changed_share) == (
        lod.lod_height_m, 0.05, floor.min_changed_share)


def test_identical_acquisitions_give_the_floors():
    lod = calibrate(_roof(), _roof(), sample=2000)
    assert lod.height_at_quantile_m == 0.0 and lod.curvature_at_quantile == 0.0
    assert (lod.lod_height_m, lod.lod_curvature) == (SplitSettings().lod_height_m, SplitSettings().lod_curvature)


def test_a_laser_rescan_stays_below_the_default_levels(tmp_path):
    """A box city scanned twice with new range noise: the measured 99.9th percentiles lie
    below the defaults (chosen on ULS), so the defaults are what calibration returns."""
    scan_box_pair(tmp_path, HEIGHTS)  # nothing changed: a rescan
    pre = read_epoch(tmp_path / "pre.las")
    post = read_epoch(tmp_path / "post.las", origin=pre.origin)
    lod = calibrate(pre, post, sample=20_000)
    assert 0 < lod.height_at_quantile_m < 0.1
    assert 0 < lod.curvature_at_quantile < SplitSettings().lod_curvature
    assert (lod.lod_height_m, lod.lod_curvature) == (0.3, 0.2)
    assert lod.points > 15_000
    stricter = calibrate(pre, post, sample=20_000, quantile=0.9999)
    assert stricter.curvature_at_quantile >= lod.curvature_at_quantile


def test_bad_input_is_refused():
    with pytest.raises(CalibrationError, match="quantile"):
        calibrate(_roof(), _roof(), quantile=1.0)
    with pytest.raises(CalibrationError, match="different local frames"):
        calibrate(_roof(), _roof(origin=UTM + 1.0))
    empty = _roof()
    empty.building_id = np.zeros(len(empty), np.int64)
    with pytest.raises(CalibrationError, match="no building points"):
        calibrate(_roof(), empty)


def test_calibrate_lod_command(tmp_path, capsys):
    import json

    from quakescan.cli import main

    scan_box_pair(tmp_path, HEIGHTS)
    out = tmp_path / "lod.json"
    assert main(["calibrate-lod", "--pre", str(tmp_path / "pre.las"), "--post", str(tmp_path / "post.las"),
                 "-o", str(out)]) == 0
    assert "--lod-height 0.300 --lod-curvature 0.200" in capsys.readouterr().out
    assert json.loads(out.read_text())["lod_curvature"] == 0.2
    assert main(["calibrate-lod", "--pre", str(tmp_path / "pre.las"), "--post", str(tmp_path / "nope.las")]) == 2
    assert "nope.las" in capsys.readouterr().err
