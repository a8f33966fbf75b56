"""Virtual ULS: closed-form sampling, labels, determinism, UTM invariance, beam model, bad input."""
import math

import laspy
import numpy as np
import pytest

from quakescan.acquisition.raycast import RayCaster, ground_level
from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import FlightLine, plan_flight, preset
from quakescan.errors import SceneError, SurveyError
from quakescan.formats.scene import GROUND, ROOF, WALL, Scene
from quakescan.formats.synthetic import box_city, flat_ground
from tests.las_contract import CONTRACT_ORIGIN, read_checked
from tests.spacing import nearest_neighbour_spacing

EXACT = preset("paper").replace(range_noise_sigma_m=0.0)


def _read(path):
    las = laspy.read(path)
    return las, np.column_stack([las.x, las.y, las.z])


def _single_line(scene, survey, length=40.0):
    z = ground_level(scene) + survey.altitude_agl_m
    return [FlightLine(0, np.array([-length / 2, 0.0, z]), np.array([1.0, 0.0, 0.0]), length, 0.0,
                       survey.speed_m_s)]


def test_flat_ground_spacing_is_analytic(tmp_path):
    """Across track at nadir: h·Δθ, Δθ = sweep / pulses per line; along track: v / scan rate."""
    scene = flat_ground(size=600.0)
    s = EXACT
    out = tmp_path / "g.las"
    scan(scene, s, out, lines=_single_line(scene, s), require_buildings=False)
    las, xyz = _read(out)
    np.testing.assert_allclose(xyz[:, 2], 0.0, atol=1e-3)
    assert set(np.unique(las.classification)) == {2}
    assert set(np.unique(las.grade)) == {255}
    line_no = np.floor(las.gps_time * s.scan_rate_hz).astype(int)
    angle = np.asarray(las.scan_angle) * 0.006
    nadir = np.abs(angle) <= 1.0
    # across track: consecutive pulses of one scan line near nadir
    t = np.asarray(las.gps_time)
    order = np.argsort(t)
    xyz_o, line_o, nadir_o = xyz[order], line_no[order], nadir[order]
    same = (line_o[1:] == line_o[:-1]) & nadir_o[1:] & nadir_o[:-1]
    across = np.abs(np.diff(xyz_o[:, 1])[same])
    expect_across = s.altitude_agl_m * s.angle_step_rad
    np.testing.assert_allclose(across, expect_across, atol=2e-3)  # LAS stores millimetres
    assert math.isclose(expect_across, 0.1709, rel_tol=1e-3)
    # along track: the nadir-most point of consecutive scan lines
    best = {}
    for k, (ln, a, x) in enumerate(zip(line_no, np.abs(angle), xyz[:, 0])):
        if nadir[k] and (ln not in best or a < best[ln][0]):
            best[ln] = (a, x)
    xs = np.array([best[k][1] for k in sorted(best)])
    assert len(xs) > 100
    # the nadir-most pulse of a line may come one pulse earlier or later: ±v/PRR
    np.testing.assert_allclose(np.diff(xs), s.speed_m_s / s.scan_rate_hz, atol=2 * s.speed_m_s / s.pulse_rate_hz + 1e-3)
    # swath edges at ±FOV/2
    assert np.abs(xyz[:, 1]).max() == pytest.approx(s.altitude_agl_m * math.tan(math.radians(60)), rel=1e-3)


def _box_city_exact():
    return box_city(rows=2, cols=3, footprint=12.0, street=10.0, height=(6.0, 9.0, 12.0), grades=[0, 3, 4, 5, 1, 2])


def test_labels_match_the_faces_hit(tmp_path):
    scene = _box_city_exact()
    out = tmp_path / "c.las"
    scan(scene, EXACT, out)
    las, xyz = _read(out)
    bid = np.asarray(las.building_id)
    surf = np.asarray(las.surface)
    grade = np.asarray(las.grade)
    assert set(np.unique(bid)) == set(range(0, 7))
    heights = {b.id: (6.0, 9.0, 12.0)[(b.id - 1) % 3] for b in scene.buildings}
    grades = {b.id: b.grade for b in scene.buildings}
    pitch = 22.0
    for b in scene.buildings:
        m = bid == b.id
        assert (grade[m] == grades[b.id]).all()
        assert (las.classification[m] == 6).all()
        r, c = divmod(b.id - 1, 3)
        x0, y0 = c * pitch, r * pitch
        roof = m & (surf == ROOF)
        # roof hits lie at the roof height, inside the footprint
        np.testing.assert_allclose(xyz[roof, 2], heights[b.id], atol=1e-3)
        assert (xyz[roof, 0] > x0 - 1e-3).all() and (xyz[roof, 0] < x0 + 12 + 1e-3).all()
        # wall hits lie on one of the four wall planes, below the roof
        wall = xyz[m & (surf == WALL)]
        assert len(wall) > 100
        d = np.min(np.abs(np.stack([wall[:, 0] - x0, wall[:, 0] - x0 - 12, wall[:, 1] - y0,
                                    wall[:, 1] - y0 - 12])), axis=0)
        assert d.max() < 1e-3
        assert (wall[:, 2] < heights[b.id] + 1e-3).all() and (wall[:, 2] > -1e-3).all()
    ground = bid == 0
    assert (surf[ground] == GROUND).all() and (las.classification[ground] == 2).all()
    assert (grade[ground] == 255).all()
    np.testing.assert_allclose(xyz[ground, 2], 0.0, atol=1e-3)


def test_las_follows_the_contract(tmp_path):
    scene = box_city(rows=1, cols=2, origin=CONTRACT_ORIGIN)
    scene.crs = "EPSG:2056"
    out = tmp_path / "c.laz"
    scan(scene, preset("paper"), out)
    las = read_checked(out, scene)
    assert las.header.number_of_points_by_return[0] == len(las.x)
    assert las.gps_time.min() >= 0 and np.all(np.diff(las.gps_time) >= 0)  # scan order
    assert set(np.unique(las.point_source_id)) == {1, 2}  # flight line numbers
    assert np.abs(las.scan_angle).max() * 0.006 <= 60.0 + 1e-9


def test_same_seed_same_bytes(tmp_path):
    scene = box_city(rows=1, cols=2)
    s = preset("paper").replace(beam="adaptive")
    scan(scene, s, tmp_path / "a.las", seed=7, workers=2, batch_rays=50_000)
    scan(scene, s, tmp_path / "b.las", seed=7, workers=1, batch_rays=50_000)
    scan(scene, s, tmp_path / "c.las", seed=8, workers=2, batch_rays=50_000)
    a, b, c = ((tmp_path / f"{k}.las").read_bytes() for k in "abc")
    assert a == b
    assert a != c


def test_paper_survey_point_spacing_matches_the_paper(tmp_path):
    """Zahs et al. report simulated spacing roof 0.07 m (std 0.03), facade 0.11 m (std 0.04)."""
    scene = box_city(rows=3, cols=4, footprint=14.0, street=12.0, height=(9.0, 12.0, 15.0, 6.0))
    out = tmp_path / "p.las"
    scan(scene, preset("paper"), out)
    las, xyz = _read(out)
    bid, surf = np.asarray(las.building_id), np.asarray(las.surface)
    for code, mean, std in ((ROOF, 0.07, 0.03), (WALL, 0.11, 0.04)):
        nn = nearest_neighbour_spacing(xyz, bid, surf, code)
        assert abs(nn.mean() - mean) <= std, (code, nn.mean())


@pytest.mark.parametrize("beam", ["single", "adaptive"])
def test_utm_coordinates_give_the_same_points(tmp_path, beam):
    s = EXACT.replace(beam=beam)
    local = box_city(rows=2, cols=2)
    at_origin_shift = box_city(rows=2, cols=2, origin=(500000.0, 5000000.0, 250.0))
    # the same city with its vertices themselves at UTM coordinates and a zero origin
    raw = box_city(rows=2, cols=2)
    raw.vertices = raw.vertices + np.array([500000.0, 5000000.0, 250.0])
    outs = []
    for k, sc in enumerate((local, at_origin_shift, raw)):
        out = tmp_path / f"{k}.las"
        scan(sc, s, out)
        outs.append(_read(out)[1])
    assert len(outs[0]) == len(outs[1]) == len(outs[2])
    ref = outs[0] + np.array([500000.0, 5000000.0, 250.0])
    # LAS stores millimetres; files with different offsets may round one unit apart
    assert np.abs(outs[1] - ref).max() <= 1e-3 + 1e-6
    assert np.abs(outs[2] - ref).max() <= 1e-3 + 1e-6


def test_float32_without_the_shift_errs_at_utm():
    """Why the local origin exists: Embree's float32 at UTM coordinates misplaces hits by ~0.1 m."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    off = np.array([500000.0, 5000000.0, 0.0])
    scene = box_city(rows=1, cols=1)
    v = scene.vertices + off
    es = rtcore_scene.EmbreeScene()
    TriangleMesh(es, v.astype(np.float32), scene.faces.astype(np.int32))
    rng = np.random.default_rng(0)
    n = 2000
    target = np.column_stack([rng.uniform(0.5, 11.5, n), rng.uniform(0.5, 11.5, n), np.full(n, 9.0)]) + off
    origin = target + np.array([30.0, 20.0, 100.0])
    d = (target - origin) / np.linalg.norm(target - origin, axis=1, keepdims=True)
    o32, d32 = origin.astype(np.float32), d.astype(np.float32)
    r = es.run(o32, d32, output=1)
    naive = (o32 + d32 * r["tfar"][:, None]).astype(np.float64)  # a float32 pipeline's hit point
    naive_err = np.linalg.norm(naive - target, axis=1).max()
    caster = RayCaster(scene)
    face, t = caster.cast(origin - off - caster.local_origin, d, 1e3)
    ours = origin - off + d * t[:, None]
    assert naive_err > 0.05
    assert np.linalg.norm(ours - (target - off), axis=1).max() < 1e-6


def test_grazing_rays_stay_finite_and_on_the_surface():
    scene = box_city(rows=1, cols=1)
    caster = RayCaster(scene)
    lo = caster.local_origin
    # rays sliding along the west wall (x = 0) at angles down to 1e-7 rad, and exactly in-plane
    angles = np.array([1e-2, 1e-4, 1e-5, 1e-6, 1e-7, 0.0])
    origin = np.array([[-1e-7 - 0.0, 6.0, 50.0]]) - lo
    origin = np.repeat(origin, len(angles), axis=0)
    origin[:, 0] = -50.0 * np.tan(angles) - lo[0]  # reaches x = 0 at z = 0 … for angle > 0
    d = np.column_stack([np.sin(angles), np.zeros(len(angles)), -np.cos(angles)])
    face, t = caster.cast(origin, d, 1e3)
    assert np.all(np.isfinite(t[face >= 0]))
    assert np.all(np.isinf(t[face < 0]))
    hit = origin[face >= 0] + d[face >= 0] * t[face >= 0, None] + lo
    on_wall_or_ground = np.minimum(np.abs(hit[:, 0]), np.abs(hit[:, 2]))
    assert on_wall_or_ground.max() < 1e-6


def test_full_beam_splits_returns_at_roof_edges_and_adaptive_agrees(tmp_path):
    scene = box_city(rows=1, cols=2, height=(12.0, 6.0))
    s = EXACT.replace(beam_divergence_mrad=3.0)  # a wide beam so that edges catch many pulses
    res = {}
    for beam in ("single", "adaptive", "full"):
        out = tmp_path / f"{beam}.las"
        summary = scan(scene, s.replace(beam=beam), out)
        las = laspy.read(out)
        res[beam] = (summary, las)
    single, adaptive, full = (res[k][1] for k in ("single", "adaptive", "full"))
    assert single.number_of_returns.max() == 1
    assert full.number_of_returns.max() >= 2
    # returns are numbered 1..n within each pulse, and n agrees with the count of its points
    for las in (adaptive, full):
        rn, nr = np.asarray(las.return_number), np.asarray(las.number_of_returns)
        assert np.all(rn <= nr) and np.all(rn >= 1)
    # adaptive casts sub-rays for a small share of pulses and reproduces the full beam's returns
    sa, sf = res["adaptive"][0], res["full"][0]
    assert sa.pulses_with_sub_rays < 0.1 * sf.pulses_with_sub_rays
    assert sa.rays_cast < 0.2 * sf.rays_cast
    assert abs(len(adaptive.x) - len(full.x)) <= 0.001 * len(full.x)
    multi_a = np.sum(adaptive.return_number == 2)
    multi_f = np.sum(full.return_number == 2)
    assert abs(multi_a - multi_f) <= 0.02 * multi_f
    # on the flat interior of a roof the full beam's range equals the central ray's
    roof_f = np.asarray(full.surface) == ROOF
    np.testing.assert_allclose(np.median(np.asarray(full.z)[roof_f & (np.asarray(full.building_id) == 1)]), 12.0,
                               atol=1e-3)


def test_flight_plan_covers_the_scene_with_overlap():
    s = preset("paper")
    bounds = np.array([[0.0, 0.0, 0.0], [300.0, 500.0, 20.0]])
    plan = plan_flight(s, bounds, 0.0)
    assert s.swath_m == pytest.approx(2 * 100 * math.tan(math.radians(60)))
    assert s.line_spacing_m == pytest.approx(0.4 * s.swath_m)
    ys = np.array([ln.start[1] for ln in plan.lines])
    np.testing.assert_allclose(np.diff(ys), s.line_spacing_m)
    assert ys.min() <= 0.0 and ys.max() >= 500.0  # outermost lines at or beyond the edges
    # every point across the scene is inside at least two strips
    for y in np.linspace(0, 500, 101):
        assert np.sum(np.abs(ys - y) <= s.swath_m / 2) >= 2
    # serpentine, continuous GPS time, at 100 m above ground, at 8 m/s
    assert plan.lines[0].heading[0] == 1 and plan.lines[1].heading[0] == -1
    for a, b in zip(plan.lines, plan.lines[1:]):
        assert b.t_start > a.t_start + a.duration_s
    assert all(ln.start[2] == 100.0 for ln in plan.lines)


@pytest.mark.parametrize("make, err, text", [
    (lambda: Scene(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int32), np.zeros(0, np.uint8), []),
     SceneError, "scene is empty"),
    (lambda: flat_ground(), SceneError, "has no buildings"),
])
def test_unscannable_scenes_say_so(tmp_path, make, err, text):
    with pytest.raises(err, match=text):
        scan(make(), preset("paper"), tmp_path / "x.las")
    assert not (tmp_path / "x.las").exists()


def test_survey_that_misses_the_scene(tmp_path):
    with pytest.raises(SurveyError, match="recorded no points"):
        scan(box_city(rows=1, cols=1), preset("paper").replace(max_range_m=50.0), tmp_path / "x.las")
    assert not (tmp_path / "x.las").exists() and not (tmp_path / "x.las.part").exists()


@pytest.mark.parametrize("beam, deflector, misalignment", [
    ("single", "rotating_polygon", 0.0), ("adaptive", "rotating_polygon", 0.0), ("full", "oscillating_mirror", 0.0),
    ("single", "rotating_polygon", 0.05), ("adaptive", "oscillating_mirror", 0.05)])
def test_compiled_loops_match_the_numpy_reference(tmp_path, beam, deflector, misalignment):
    """The numba kernels (pulses, rays, hit refinement, LAS packing) give the same bytes as
    their numpy references (`_scan_reference`), strip misalignment included."""
    scene = box_city(rows=1, cols=2, origin=(500000.0, 5000000.0, 0.0))
    s = preset("paper").replace(beam=beam, deflector=deflector, pulse_rate_hz=60_000.0,
                                strip_misalignment_m=misalignment)
    scan(scene, s, tmp_path / "fast.las", seed=3, fast=True, batch_rays=100_000)
    scan(scene, s, tmp_path / "ref.las", seed=3, fast=False, batch_rays=100_000)
    assert (tmp_path / "fast.las").read_bytes() == (tmp_path / "ref.las").read_bytes()


def test_oscillating_mirror_sweeps_both_ways(tmp_path):
    scene = box_city(rows=1, cols=1)
    s = EXACT.replace(deflector="oscillating_mirror")
    out = tmp_path / "o.las"
    scan(scene, s, out, lines=_single_line(scene, s, 10.0))
    las = laspy.read(out)
    flags = np.asarray(las.scan_direction_flag)
    assert set(np.unique(flags)) == {0, 1}
    # within one sweep the angle changes monotonically in the sweep's direction
    a = np.asarray(las.scan_angle).astype(int)
    t = np.asarray(las.gps_time)
    line = np.floor(t * s.scan_rate_hz).astype(int)
    same = line[1:] == line[:-1]
    step = np.diff(a)[same]
    fwd = flags[1:][same] == 1
    assert (step[fwd] >= 0).all() and (step[~fwd] <= 0).all()


def test_crosshatch_sees_the_walls_facing_along_track(tmp_path):
    """A vertical scan plane across the track cannot see walls facing along the track;
    the crosshatch pattern (a second set of lines at 90°) can."""
    scene = box_city(rows=1, cols=1)
    counts = {}
    for pattern in ("parallel", "crosshatch"):
        out = tmp_path / f"{pattern}.las"
        scan(scene, EXACT.replace(pattern=pattern, pulse_rate_hz=100_000.0), out)
        las, xyz = _read(out)
        wall = (np.asarray(las.surface) == WALL) & (np.asarray(las.building_id) == 1)
        facing_x = wall & ((np.abs(xyz[:, 0]) < 1e-3) | (np.abs(xyz[:, 0] - 12.0) < 1e-3))
        facing_y = wall & ~facing_x
        counts[pattern] = (facing_x.sum(), facing_y.sum())
        lines = set(np.unique(las.point_source_id))
        assert len(lines) == (2 if pattern == "parallel" else 4)
    assert counts["parallel"][0] < 0.01 * counts["parallel"][1]
    assert counts["crosshatch"][0] > 0.3 * counts["crosshatch"][1]


def _roof_lines(survey, offsets_y, length=30.0):
    """Flight lines at roof-centre heights over box_city(rows=1, cols=1)'s 12 m roof, one per
    across-track offset: every line sees the whole roof."""
    z = survey.altitude_agl_m
    return [FlightLine(k, np.array([6.0 - length / 2, 6.0 + y, z]), np.array([1.0, 0.0, 0.0]), length,
                       k * length / survey.speed_m_s, survey.speed_m_s) for k, y in enumerate(offsets_y)]


def test_strip_misalignment_moves_every_point_of_a_line_by_its_offset(tmp_path):
    """Same seed with and without misalignment: the same pulses and noise, every point of line k
    moved by strip_offset(k) (to the LAS millimetre); the paper preset has none."""
    from quakescan.acquisition.beams import strip_offset

    assert preset("paper").strip_misalignment_m == 0
    scene = box_city(rows=1, cols=1)
    base = preset("paper").replace(pulse_rate_hz=50_000.0)
    lines = _roof_lines(base, (-3.0, 3.0))
    xyz = {}
    for sigma in (0.0, 0.05):
        out = tmp_path / f"{sigma}.las"
        scan(scene, base.replace(strip_misalignment_m=sigma), out, seed=11, lines=lines)
        las, xyz[sigma] = _read(out)
    line = np.asarray(las.point_source_id) - 1
    assert set(np.unique(line)) == {0, 1}
    moved = xyz[0.05] - xyz[0.0]
    for k in (0, 1):
        expect = strip_offset(base.replace(strip_misalignment_m=0.05), 11, k)
        assert np.abs(expect).max() > 1e-3
        np.testing.assert_allclose(moved[line == k], np.broadcast_to(expect, moved[line == k].shape),
                                   atol=1e-3 + 1e-9)


def test_strip_misalignment_height_steps_have_the_expected_spread(tmp_path):
    """Two overlapping lines over one flat roof, sigma = 0.05 m per axis: the difference of the
    lines' mean roof heights is Gaussian with variance 2 sigma² (range noise off, so a line's
    mean roof height is the roof plus its z offset). Over n pairs (seeds × line pairs) the sum
    of squared differences / (2 sigma²) is chi² with n degrees of freedom; the test accepts the
    central 1 - 2e-6 of it."""
    from scipy.stats import chi2

    sigma = 0.05
    scene = box_city(rows=1, cols=1, height=9.0)
    s = EXACT.replace(pulse_rate_hz=20_000.0, strip_misalignment_m=sigma)
    lines = _roof_lines(s, (-4.0, 4.0, -2.0, 2.0, -1.0, 1.0, -3.0, 3.0))
    steps = []
    for seed in range(12):
        out = tmp_path / f"{seed}.las"
        scan(scene, s, out, seed=seed, lines=lines)
        las, xyz = _read(out)
        roof = np.asarray(las.surface) == ROOF
        line = np.asarray(las.point_source_id) - 1
        mean_z = np.array([xyz[roof & (line == k), 2].mean() for k in range(len(lines))])
        steps.append(mean_z[0::2] - mean_z[1::2])
    steps = np.concatenate(steps)
    n = len(steps)
    statistic = float(np.sum(steps ** 2) / (2 * sigma ** 2))
    assert chi2.ppf(1e-6, n) < statistic < chi2.ppf(1 - 1e-6, n), (n, statistic, steps.std())
    assert abs(steps.mean()) < 6 * math.sqrt(2) * sigma / math.sqrt(n)  # no bias between lines


def test_strip_misalignment_same_seed_same_bytes_whatever_the_threads(tmp_path):
    scene = box_city(rows=1, cols=2)
    s = preset("paper").replace(pulse_rate_hz=100_000.0, strip_misalignment_m=0.05)
    scan(scene, s, tmp_path / "a.las", seed=7, workers=2, batch_rays=20_000)
    scan(scene, s, tmp_path / "b.las", seed=7, workers=1, batch_rays=20_000)
    scan(scene, s, tmp_path / "c.las", seed=8, workers=2, batch_rays=20_000)
    a, b, c = ((tmp_path / f"{k}.las").read_bytes() for k in "abc")
    assert a == b
    assert a != c


def test_unknown_preset_lists_the_known_ones():
    with pytest.raises(SurveyError, match="unknown survey preset 'fast'; known: 'paper', 'als'"):
        preset("fast")


def test_als_preset_is_an_aircraft_scan_of_about_10_points_per_m2():
    s = preset("als")
    assert s.name == "als" and s.deflector == "oscillating_mirror"
    assert 40 <= s.fov_deg <= 60 and 300 <= s.altitude_agl_m <= 1000 and s.speed_m_s == 60
    assert 0.02 <= s.range_noise_sigma_m <= 0.03 and 0.25 <= s.beam_divergence_mrad <= 0.5
    assert s.max_range_m >= s.altitude_agl_m / math.cos(math.radians(s.fov_deg / 2))
    assert s.nominal_density_pts_m2 == pytest.approx(10.0, rel=0.01)
    assert s.strip_misalignment_m == 0
    from quakescan.acquisition.survey import load_survey

    assert load_survey("als") == s  # --survey als


@pytest.mark.parametrize("density", [4.0, 10.0, 17.5, 30.0])
def test_als_for_density_turns_pulse_rate_and_speed_within_realistic_ranges(density):
    from quakescan.acquisition.survey import ALS_PULSE_RATE_HZ, ALS_SCAN_RATE_HZ, ALS_SPEED_M_S, als_for_density

    s = als_for_density(density)
    assert s.nominal_density_pts_m2 == pytest.approx(density, rel=1e-9)
    assert ALS_PULSE_RATE_HZ[0] <= s.pulse_rate_hz <= ALS_PULSE_RATE_HZ[1]
    assert ALS_SPEED_M_S[0] <= s.speed_m_s <= ALS_SPEED_M_S[1]
    assert ALS_SCAN_RATE_HZ[0] <= s.scan_rate_hz <= ALS_SCAN_RATE_HZ[1]
    # the flight geometry is the preset's
    a = preset("als")
    assert (s.altitude_agl_m, s.fov_deg, s.strip_overlap_pct) == (a.altitude_agl_m, a.fov_deg, a.strip_overlap_pct)


def test_als_for_density_beyond_the_pulse_rates_moves_the_speed_or_says_why():
    from quakescan.acquisition.survey import ALS_SPEED_M_S, als_for_density

    slow = als_for_density(1.5)  # 1.5 pts/m² at the lowest pulse rate (25 kHz) needs a faster aircraft
    assert slow.pulse_rate_hz == 25_000.0 and ALS_SPEED_M_S[0] <= slow.speed_m_s <= ALS_SPEED_M_S[1]
    assert slow.speed_m_s > 60.0 and slow.nominal_density_pts_m2 == pytest.approx(1.5)
    for bad, text in ((500.0, "out of reach"), (0.0, "positive number"), (float("nan"), "positive number")):
        with pytest.raises(SurveyError, match=text):
            als_for_density(bad)


def test_a_short_max_range_narrows_the_strips_instead_of_leaving_gaps():
    """At 150 m with a 120° FOV the swath's edges lie 300 m away; with max_range 200 m the
    scanner records a swath of 2·sqrt(200² - 150²) and the plan spaces its lines by that."""
    s = preset("paper").replace(altitude_agl_m=150.0, max_range_m=200.0)
    assert s.swath_m == pytest.approx(2 * math.sqrt(200.0 ** 2 - 150.0 ** 2))
    plan = plan_flight(s, np.array([[0.0, 0.0, 0.0], [200.0, 300.0, 10.0]]), 0.0)
    ys = np.array([ln.start[1] for ln in plan.lines])
    for y in np.linspace(0, 300, 61):
        assert np.sum(np.abs(ys - y) <= s.swath_m / 2) >= 2
    assert preset("paper").swath_m == pytest.approx(2 * 100 * math.tan(math.radians(60)))  # range not limiting


def test_als_over_a_300_m_scene_with_one_line_or_the_plan(tmp_path):
    """500 m above a 284 m × 284 m city: the box culling and the 2 km range let one flight
    line (swath 466 m) record every building; the plan flies three lines, two strips everywhere."""
    from quakescan.acquisition.survey import als_for_density

    scene = box_city(rows=10, cols=10, footprint=12.0, street=16.0, margin=10.0)
    s = als_for_density(4.0)
    b = scene.bounds()
    one = [FlightLine(0, np.array([b[0, 0] - s.run_in_m, 0.5 * (b[0, 1] + b[1, 1]), s.altitude_agl_m]),
                      np.array([1.0, 0.0, 0.0]), b[1, 0] - b[0, 0] + 2 * s.run_in_m, 0.0, s.speed_m_s)]
    single = scan(scene, s, tmp_path / "one.las", seed=1, lines=one)
    planned = scan(scene, s, tmp_path / "plan.las", seed=1)
    assert planned.lines == 3
    for summary in (single, planned):
        assert set(summary.points_by_building) == set(range(1, 101))
    # one strip against two: about half the points
    assert 0.4 < single.points / planned.points < 0.6


def test_the_flight_plan_is_estimated_before_scanning_and_dry_run_scans_nothing(tmp_path, capsys):
    from quakescan.acquisition.scan import estimate_scan, scan
    from quakescan.acquisition.survey import preset
    from quakescan.cli import main
    from quakescan.formats.scene import write_scene
    from quakescan.formats.synthetic import box_city

    scene = box_city(rows=1, cols=2)
    survey = preset("paper").replace(pulse_rate_hz=100_000.0)
    est = estimate_scan(scene, survey)
    summary = scan(scene, survey, tmp_path / "a.las", seed=1)
    assert est.pulses == pytest.approx(summary.pulses_emitted, rel=1e-3)  # the same plan, counted before
    assert est.lines == summary.lines and abs(est.flight_time_s - summary.flight_duration_s) < 1.0
    assert summary.points <= est.points and est.megabytes >= (tmp_path / "a.las").stat().st_size / 1e6
    assert not est.large
    write_scene(scene, tmp_path / "scene")
    assert main(["scan", str(tmp_path / "scene"), "-o", str(tmp_path / "b.las"), "--dry-run"]) == 0
    assert "flight plan:" in capsys.readouterr().out and not (tmp_path / "b.las").exists()
