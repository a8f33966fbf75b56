"""Acquisitions (core/acquisition/acquire.py): ALS density, random acquisitions in their ranges,
JSON round trip, resumable atomic acquire, roof density measure and thinning."""
import dataclasses
import json
import math

import laspy
import numpy as np
import pytest

import quakescan.acquisition.dim
import quakescan.acquisition.scan
from quakescan.acquisition.acquire import KINDS, Acquisition, acquire, random_acquisition, sidecar_path
from quakescan.acquisition.density import measured_density, thin_to_density
from quakescan.acquisition.dim_settings import preset_dim
from quakescan.acquisition.scan import scan
from quakescan.acquisition.sensor_dim import DIM_ALTITUDE_M, DIM_NOISE_PX, DIM_POINT_STEP_PX
from quakescan.acquisition.sensor_lidar import (
    ALS_DENSITY_PTS_M2,
    ALS_MISALIGNMENT_M,
    ALS_RANGE_NOISE_M,
    ULS_ALTITUDE_M,
    ULS_MISALIGNMENT_M,
    ULS_OVERLAP_PCT,
    ULS_PULSE_RATE_HZ,
    ULS_RANGE_NOISE_M,
)
from quakescan.acquisition.survey import als_for_density, preset
from quakescan.errors import PointCloudError, QuakeScanError, SurveyError
from quakescan.formats.pointcloud import Epoch
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city

UTM = (500000.0, 5000000.0, 0.0)


def _within(value, lo_hi):
    return lo_hi[0] <= value <= lo_hi[1]


# Density ------------------------------------------------------------------------------

def _grid_roof(spacing, size=12.0, height=9.0, x0=0.3, y0=0.7):
    """A flat roof sampled on a regular grid (density 1/spacing²) with a wall below one edge
    and one through its middle (a step to a lower part, say)."""
    g = np.arange(spacing / 2, size, spacing)
    x, y = np.meshgrid(g + x0, g + y0)
    roof = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, height)])
    zz = np.arange(0.1, height, 0.05)
    walls = [np.column_stack([np.full(zz.size * 12, wx), np.repeat(np.arange(12) + y0 + 0.5, zz.size),
                              np.tile(zz, 12)]) for wx in (x0, x0 + size / 2)]
    return np.concatenate([roof, *walls])


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), UTM])
def test_measured_density_of_a_regular_roof_is_one_over_spacing_squared(origin):
    """A 0.25 m grid is 16 pts/m²; the walls and the ground do not count, and a cloud at UTM
    coordinates measures the same."""
    xyz = _grid_roof(0.25)
    ground = np.column_stack([np.random.default_rng(0).uniform(-20, 30, (5000, 2)), np.zeros(5000)])
    pts = np.concatenate([xyz, ground])
    cls = np.concatenate([np.full(len(xyz), 6, np.uint8), np.full(len(ground), 2, np.uint8)])
    assert measured_density(Epoch(pts, np.asarray(origin), cls)) == pytest.approx(16.0)
    # without class 6 the building_id says which points are buildings
    bid = np.concatenate([np.ones(len(xyz), np.int64), np.zeros(len(ground), np.int64)])
    assert measured_density(Epoch(pts, np.asarray(origin), np.full(len(pts), 1, np.uint8), bid)) == \
        pytest.approx(16.0)
    with pytest.raises(PointCloudError, match="no roof to measure"):
        measured_density(Epoch(ground, np.zeros(3), np.full(len(ground), 2, np.uint8), source="g.las"))


def test_als_preset_gives_8_to_12_points_per_m2_on_box_roofs(tmp_path):
    out = tmp_path / "als.las"
    scan(box_city(rows=3, cols=3), preset("als"), out, seed=1)
    assert 8.0 <= measured_density(out) <= 12.0


@pytest.mark.parametrize("density", [4.0, 30.0])
def test_als_for_density_measures_its_target_on_box_roofs(tmp_path, density):
    """Roofs (9 m) are closer to the scanner than the ground: a few per cent above nominal."""
    out = tmp_path / "als.las"
    scan(box_city(rows=3, cols=3), als_for_density(density), out, seed=1)
    assert measured_density(out) == pytest.approx(density, rel=0.15)


# Random acquisitions ------------------------------------------------------------------

def test_random_acquisitions_are_seeded_and_within_their_ranges():
    for kind in KINDS:
        draws = [random_acquisition(kind, seed) for seed in range(40)]
        assert draws == [random_acquisition(kind, np.random.default_rng(seed)) for seed in range(40)]
        assert len({a.label for a in draws}) > 30  # they vary
        for a in draws:
            s = a.settings
            assert a.kind == kind and _within(s.line_direction_deg, (0.0, 180.0))
            if kind == "uls":
                assert _within(s.altitude_agl_m, ULS_ALTITUDE_M) and _within(s.pulse_rate_hz, ULS_PULSE_RATE_HZ)
                assert _within(s.range_noise_sigma_m, ULS_RANGE_NOISE_M)
                assert _within(s.strip_misalignment_m, ULS_MISALIGNMENT_M)
                assert _within(s.strip_overlap_pct, ULS_OVERLAP_PCT)
                assert a.label.startswith(f"uls {s.altitude_agl_m:.0f}m {s.pulse_rate_hz / 1e3:.0f}kHz noise ")
            elif kind == "als":
                assert s.nominal_density_pts_m2 == pytest.approx(np.clip(s.nominal_density_pts_m2,
                                                                         *ALS_DENSITY_PTS_M2), rel=1e-3)
                assert _within(s.range_noise_sigma_m, ALS_RANGE_NOISE_M)
                assert _within(s.strip_misalignment_m, ALS_MISALIGNMENT_M)
                assert s.deflector == "oscillating_mirror" and s.altitude_agl_m == preset("als").altitude_agl_m
            else:
                assert _within(s.altitude_agl_m, DIM_ALTITUDE_M) and _within(s.noise_px, DIM_NOISE_PX)
                assert _within(s.point_step_px, DIM_POINT_STEP_PX) and s.oblique_cameras in (0, 4)
                assert 0.0146 <= s.gsd_m <= 0.0276  # 80–150 m with 4.4 µm pixels and 24 mm
        if kind == "dim":
            assert {a.settings.oblique_cameras for a in draws} == {0, 4}
    with pytest.raises(SurveyError, match=r"kind must be one of \('uls', 'als', 'dim'\), got 'lidar'"):
        random_acquisition("lidar", 0)


def test_acquisition_json_round_trip_and_bad_documents():
    for kind in KINDS:
        a = random_acquisition(kind, 3)
        doc = json.loads(json.dumps(a.to_json()))
        assert Acquisition.from_json(doc) == a
        assert doc["label"] == a.label
    doc = random_acquisition("uls", 3).to_json()
    for change, text in (({"kind": "lidar"}, "kind must be one of"), ({"format": "x"}, "not an acquisition"),
                         ({"version": 9}, "version 9 not supported"),
                         ({"settings": {"speed": 3}}, "unknown survey fields ['speed']"),
                         ({"settings": {"altitude_agl_m": -1}}, "altitude_agl_m must be a positive number")):
        with pytest.raises(SurveyError) as err:
            Acquisition.from_json({**doc, **change}, source="pairs/a.json")
        assert text in str(err.value) and "pairs/a.json" in str(err.value)
    with pytest.raises(SurveyError, match="kind must be one of"):
        Acquisition("lidar", preset("paper"))
    with pytest.raises(SurveyError, match="a 'dim' acquisition needs a PhotoSurvey"):
        Acquisition("dim", preset("paper"))


# Acquire ------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uls", "dim"])
def test_acquire_writes_a_sidecar_and_resumes_without_simulating(tmp_path, monkeypatch, kind):
    scene_dir = write_scene(box_city(rows=1, cols=2), tmp_path / "scene")
    if kind == "uls":
        acq = Acquisition("uls", preset("paper").replace(pulse_rate_hz=50_000.0, strip_misalignment_m=0.02))
    else:
        acq = Acquisition("dim", preset_dim("paper").replace(margin_m=30.0, point_step_px=16.0))
    out = tmp_path / "out" / "pre.laz"
    first = acquire(scene_dir, acq, out, seed=4)
    assert not first.resumed and out.is_file() and first.record["summary"]["points"] == len(laspy.read(out).x)
    record = json.loads(sidecar_path(out).read_text())
    assert sidecar_path(out).name == "pre.laz.acquisition.json"
    assert Acquisition.from_json(record["acquisition"]) == acq and record["seed"] == 4
    assert not list(out.parent.glob("*.part"))
    data = out.read_bytes()

    def no_simulation(*args, **kwargs):
        raise AssertionError("resumed acquisition simulated again")

    monkeypatch.setattr(quakescan.acquisition.scan, "scan", no_simulation)
    monkeypatch.setattr(quakescan.acquisition.dim, "simulate_dim", no_simulation)
    again = acquire(scene_dir, acq, out, seed=4)
    assert again.resumed and out.read_bytes() == data
    # another seed or other settings are another acquisition
    monkeypatch.undo()
    assert not acquire(scene_dir, acq, out, seed=5).resumed
    changed = dataclasses.replace(acq, settings=acq.settings.replace(altitude_agl_m=110.0))
    assert not acquire(scene_dir, changed, out, seed=5).resumed
    assert acquire(scene_dir, changed, out, seed=5).resumed


def test_acquire_redoes_a_cloud_whose_sidecar_is_missing_or_whose_scene_changed(tmp_path):
    acq = Acquisition("als", als_for_density(4.0))
    scene = box_city(rows=1, cols=2)
    out = tmp_path / "a.las"
    assert not acquire(scene, acq, out, seed=1).resumed
    assert acquire(scene, acq, out, seed=1).resumed
    sidecar_path(out).unlink()  # e.g. interrupted between the cloud and its sidecar
    assert not acquire(scene, acq, out, seed=1).resumed
    taller = box_city(rows=1, cols=2, height=12.0)
    assert not acquire(taller, acq, out, seed=1).resumed


def test_acquire_refuses_what_it_cannot_acquire(tmp_path):
    scene = box_city(rows=1, cols=1)
    with pytest.raises(QuakeScanError, match=r"acquisition must be an Acquisition \(kind one of"):
        acquire(scene, "uls", tmp_path / "a.las")
    with pytest.raises(PointCloudError, match="must end in .las or .laz"):
        acquire(scene, Acquisition("uls", preset("paper")), tmp_path / "a.ply")
    # a failed simulation leaves neither a cloud nor a sidecar
    with pytest.raises(SurveyError, match="recorded no points"):
        acquire(scene, Acquisition("uls", preset("paper").replace(max_range_m=50.0)), tmp_path / "a.las")
    assert list(tmp_path.iterdir()) == []


# Thinning -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dense_epoch(tmp_path_factory):
    """A paper-ULS scan of a 2 × 2 box city at UTM coordinates with a CRS (~90 pts/m² on roofs)."""
    scene = box_city(rows=2, cols=2, origin=UTM)
    scene.crs = "EPSG:32633"
    out = tmp_path_factory.mktemp("thin") / "dense.las"
    scan(scene, preset("paper").replace(strip_misalignment_m=0.02), out, seed=2)
    return out


@pytest.mark.parametrize("target, suffix", [(30.0, ".las"), (8.0, ".laz")])
def test_thin_to_density_hits_the_target_and_keeps_every_attribute(tmp_path, dense_epoch, target, suffix):
    out = tmp_path / f"thin{suffix}"
    result = thin_to_density(dense_epoch, out, target, seed=9)
    assert measured_density(out) == pytest.approx(target, rel=0.15)
    assert result.density_after == pytest.approx(measured_density(out))
    assert result.density_before == pytest.approx(measured_density(dense_epoch))
    src, thin = laspy.read(dense_epoch), laspy.read(out)
    assert result.points_after == len(thin.points) < result.points_before == len(src.points)
    # the kept points are the input's records, byte for byte, in their order
    a, b = src.points.array, thin.points.array
    assert a.dtype == b.dtype
    rows = {r.tobytes() for r in a}
    assert all(r.tobytes() in rows for r in b)
    assert np.all(np.diff(np.asarray(thin.gps_time)) >= 0)
    for name in ("building_id", "grade", "surface"):
        assert name in thin.point_format.dimension_names
    np.testing.assert_array_equal(thin.header.scales, src.header.scales)
    np.testing.assert_array_equal(thin.header.offsets, src.header.offsets)
    assert thin.header.parse_crs().to_epsg() == 32633
    assert thin.header.point_count == len(thin.points)
    # every class thinned alike: the ground's share stays
    share = [np.mean(np.asarray(x.classification) == 2) for x in (src, thin)]
    assert share[1] == pytest.approx(share[0], abs=0.02)
    # seeded: same seed, same bytes
    again = tmp_path / f"again{suffix}"
    thin_to_density(dense_epoch, again, target, seed=9)
    assert again.read_bytes() == out.read_bytes()


def test_thin_to_density_refuses_to_add_points(tmp_path, dense_epoch):
    with pytest.raises(PointCloudError, match="thinning cannot add points"):
        thin_to_density(dense_epoch, tmp_path / "x.las", 1000.0, seed=1)
    with pytest.raises(PointCloudError, match="would overwrite its input"):
        thin_to_density(dense_epoch, dense_epoch, 10.0, seed=1)
    assert not (tmp_path / "x.las").exists()
    assert math.isfinite(measured_density(dense_epoch))
