"""Scanner intensity: ρ · cos θ_inc · (R_ref / R)² scaled to uint16, in closed form."""
import math

import laspy
import numpy as np
import pytest

from quakescan.acquisition.raycast import ground_level
from quakescan.acquisition.reflectance import MATERIAL_REFLECTANCE, SURFACE_REFLECTANCE, intensity
from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import FlightLine, preset
from quakescan.errors import SceneError
from quakescan.formats.scene import GROUND, ROOF, read_scene, write_scene
from quakescan.formats.synthetic import box_city, flat_ground

R_REF = 40.0
EXACT = preset("paper").replace(range_noise_sigma_m=0.0, intensity_reference_range_m=R_REF)


def _line(scene, survey, length=20.0):
    z = ground_level(scene) + survey.altitude_agl_m
    return [FlightLine(0, np.array([-length / 2, 0.0, z]), np.array([1.0, 0.0, 0.0]), length, 0.0,
                       survey.speed_m_s)]


def _scan_ground(tmp_path, altitude, name, beam="single", fast=True):
    scene = flat_ground(size=600.0)
    s = EXACT.replace(altitude_agl_m=altitude, beam=beam)
    out = tmp_path / f"{name}.las"
    scan(scene, s, out, lines=_line(scene, s), require_buildings=False, fast=fast)
    las = laspy.read(out)
    return np.asarray(las.intensity).astype(float), np.asarray(las.scan_angle) * 0.006


def _expected_on_flat_ground(altitude, theta_deg):
    """Flat ground seen from height h at scan angle θ: R = h / cos θ and θ_inc = θ."""
    c = np.cos(np.radians(theta_deg))
    return 65535 * SURFACE_REFLECTANCE[GROUND] * c * (R_REF * c / altitude) ** 2


def test_a_flat_plate_at_two_ranges_gives_the_inverse_square_ratio(tmp_path):
    near, a_near = _scan_ground(tmp_path, 50.0, "near")
    far, a_far = _scan_ground(tmp_path, 100.0, "far")
    nadir_near, nadir_far = near[np.abs(a_near) < 0.5], far[np.abs(a_far) < 0.5]
    assert len(nadir_near) > 10 and len(nadir_far) > 10
    # 65535 · 0.2 · (40 / 50)² = 8388.5 and a quarter of it at twice the range
    assert nadir_near.mean() == pytest.approx(65535 * 0.2 * 0.64, abs=2)
    assert nadir_near.mean() / nadir_far.mean() == pytest.approx(4.0, rel=1e-3)


def test_incidence_angles_give_the_cosine_ratio(tmp_path):
    values, angle = _scan_ground(tmp_path, 50.0, "g")
    # every point within the rounding of the closed form (cos θ for incidence, cos² θ for range)
    np.testing.assert_allclose(values, np.rint(_expected_on_flat_ground(50.0, angle)), atol=1.0)


def test_a_tilted_plate_scanned_at_nadir_returns_cos_of_its_tilt(tmp_path):
    """A plane tilted by 60° about the flight line's axis, under a nadir-only scan: at equal
    range a flat plate returns twice as much."""
    results = {}
    for tilt in (0.0, 60.0):
        scene = flat_ground(size=300.0)
        # tilt about the x axis (the flight line): z = y · tan(tilt)
        scene.vertices[:, 2] = scene.vertices[:, 1] * math.tan(math.radians(tilt))
        s = EXACT.replace(altitude_agl_m=50.0, fov_deg=2.0)
        out = tmp_path / f"t{tilt:.0f}.las"
        lines = [FlightLine(0, np.array([-10.0, 0.0, 50.0]), np.array([1.0, 0.0, 0.0]), 20.0, 0.0, s.speed_m_s)]
        scan(scene, s, out, lines=lines, require_buildings=False)
        las = laspy.read(out)
        nadir = np.abs(np.asarray(las.scan_angle) * 0.006) < 0.05
        results[tilt] = np.asarray(las.intensity)[nadir].astype(float).mean()
    assert results[60.0] / results[0.0] == pytest.approx(0.5, rel=2e-3)


@pytest.mark.parametrize("beam", ["single", "adaptive", "full"])
def test_compiled_and_numpy_intensity_agree(tmp_path, beam):
    fast, _ = _scan_ground(tmp_path, 60.0, f"f{beam}", beam=beam)
    ref, _ = _scan_ground(tmp_path, 60.0, f"r{beam}", beam=beam, fast=False)
    np.testing.assert_array_equal(fast, ref)
    assert fast.min() > 0


def test_reflectance_by_material_and_from_the_scene(tmp_path):
    """Roofs at the same range: masonry 0.35, reinforced concrete 0.30, a scene's own 0.9."""
    scene = box_city(rows=1, cols=3, height=(9.0, 9.0, 9.0))
    scene.buildings[1].material = "reinforced_concrete"
    scene.buildings[2].extra["reflectance"] = 0.9
    write_scene(scene, tmp_path / "s")
    scene = read_scene(tmp_path / "s")
    s = EXACT.replace(intensity_reference_range_m=20.0, fov_deg=2.0)
    b = scene.bounds()
    y = 0.5 * (b[0, 1] + b[1, 1])
    line = [FlightLine(0, np.array([b[0, 0], y, 100.0]), np.array([1.0, 0.0, 0.0]), b[1, 0] - b[0, 0], 0.0, 8.0)]
    scan(scene, s, tmp_path / "c.las", seed=1, lines=line)
    las = laspy.read(tmp_path / "c.las")
    bid, surf, inten = np.asarray(las.building_id), np.asarray(las.surface), np.asarray(las.intensity)
    nadir = np.abs(np.asarray(las.scan_angle) * 0.006) < 0.05
    roof = {b: inten[(bid == b) & (surf == ROOF) & nadir].astype(float).mean() for b in (1, 2, 3)}
    assert roof[1] == pytest.approx(65535 * 0.35 * (20.0 / 91.0) ** 2, rel=1e-3)  # roofs 9 m up, 100 m flight
    assert roof[2] / roof[1] == pytest.approx(MATERIAL_REFLECTANCE["reinforced_concrete"]
                                              / MATERIAL_REFLECTANCE["masonry"], rel=0.01)
    assert roof[3] / roof[1] == pytest.approx(0.9 / MATERIAL_REFLECTANCE["masonry"], rel=0.01)


def test_closer_than_the_reference_range_saturates_and_nothing_wraps():
    v = intensity(np.array([1.0, 1.0, 0.5]), np.array([[0, 0, 1.0]] * 3), np.array([[0, 0, -1.0]] * 3),
                  np.array([5.0, 20.0, 1e-9]), 20.0)
    assert v.tolist() == [65535, 65535, 65535]


@pytest.mark.parametrize("value", [0, -0.1, 1.5, True, "high", float("nan")])
def test_a_bad_reflectance_in_scene_json_is_refused(tmp_path, value):
    import json

    scene = box_city(rows=1, cols=1)
    write_scene(scene, tmp_path / "s")
    manifest = json.loads((tmp_path / "s" / "scene.json").read_text())
    manifest["buildings"][0]["reflectance"] = value
    (tmp_path / "s" / "scene.json").write_text(json.dumps(manifest))
    with pytest.raises(SceneError, match=r"scene\.json: building 1 .*reflectance must be a number in \(0, 1\]"):
        read_scene(tmp_path / "s")
