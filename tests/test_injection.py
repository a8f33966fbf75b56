"""Damage injected into real point clouds (`quakescan inject`): proxies, pulses, re-casting.

Closed forms: a flat roof with a known opening, re-cast along vertical and oblique pulses,
sends exactly the returns inside the opening to the floor below, where geometry puts them;
a flight line simulated with a known speed and height is recovered from its records. Real
files: an AHN3 tile with every building left at grade 0 comes back byte for byte; with one
building damaged, every return of the others is its real record."""
import csv
import json
import math

import laspy
import numpy as np
import pytest
import shapely

from quakescan.formats.scene import GROUND, INTERIOR, ROOF, WALL, Building, Scene
from quakescan.injection import pulses as pulses_mod
from quakescan.injection.inject import InjectionError, InjectSettings, estimate_range_noise, inject
from quakescan.injection.proxy import ProxyError, build_proxy, prism
from quakescan.injection.recast import KEPT, MOVED, REMOVED, recast

ROOF_Z, FLOOR_Z = 6.0, 3.0
HOLE = (4.0, 4.0, 8.0, 8.0)  # x0, y0, x1, y1 of the roof opening, inside a 12 x 12 m roof


def _quad(x0, y0, x1, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _scene(parts, origin):
    verts, faces, fb, fs = [], [], [], []
    n = 0
    for (v, f), bid, surf in parts:
        verts.append(v)
        faces.append(f + n)
        n += len(v)
        fb.append(np.full(len(f), bid, np.int32))
        fs.append(np.full(len(f), surf, np.uint8))
    fb = np.concatenate(fb)
    return Scene(np.concatenate(verts), np.concatenate(faces), fb, np.concatenate(fs),
                 [Building(id=7, grade=3)] if (fb == 7).any() else [], origin=np.asarray(origin, float))


def _roof_with_hole(z):
    """The 12 x 12 m roof at height z as four quads around HOLE."""
    x0, y0, x1, y1 = HOLE
    return [_quad(0, 0, 12, y0, z), _quad(0, y1, 12, 12, z), _quad(0, y0, x0, y1, z), _quad(x1, y0, 12, y1, z)]


def _box_scenes(origin):
    ground = (_quad(-30, -30, 42, 42, 0.0), 0, GROUND)
    pre = _scene([ground, (_quad(0, 0, 12, 12, ROOF_Z), 7, ROOF)], origin)
    post = _scene([ground] + [(q, 7, ROOF) for q in _roof_with_hole(ROOF_Z)]
                  + [(_quad(0, 0, 12, 12, FLOOR_Z), 7, INTERIOR)], origin)
    return pre, post


def _roof_returns(origin, spacing=0.25):
    """A grid of returns on the 12 x 12 m roof, half a spacing in from its edges."""
    g = np.arange(spacing / 2, 12, spacing)
    X, Y = np.meshgrid(g, g, indexing="ij")
    xyz = np.c_[X.ravel(), Y.ravel(), np.full(X.size, ROOF_Z)] + origin
    return xyz, np.full(len(xyz), 7, np.int64)


def _inside_hole(xy, origin):
    x0, y0, x1, y1 = HOLE
    p = xy - origin[:2]
    return (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (85_000.0, 446_000.0, -2.0), (674_500.0, 1_206_700.0, 300.0)])
def test_vertical_pulses_through_a_roof_opening_land_on_the_floor_below_at_the_right_count(origin):
    origin = np.asarray(origin)
    pre, post = _box_scenes(origin)
    xyz, owner = _roof_returns(origin)
    down = np.tile([0.0, 0.0, -1.0], (len(xyz), 1))
    r = recast(xyz, down, owner, pre, post, {7: 0.0}, range_noise_m=0.0, seed=0)
    hole = _inside_hole(xyz[:, :2], origin)
    assert hole.sum() == 16 * 16  # 4 m / 0.25 m each way
    assert np.array_equal(r.fate == MOVED, hole)
    np.testing.assert_allclose(r.xyz[hole], np.c_[xyz[hole, :2], np.full(hole.sum(), FLOOR_Z + origin[2])], atol=1e-6)
    assert np.array_equal(r.xyz[~hole], xyz[~hole])  # kept exactly
    assert (r.surface[hole] == INTERIOR).all() and (r.building[hole] == 7).all()


def test_oblique_pulses_move_by_the_height_drop_times_the_tangent_and_the_rim_shadows_the_floor():
    origin = np.zeros(3)
    pre, post = _box_scenes(origin)
    xyz, owner = _roof_returns(origin)
    theta = math.radians(20.0)
    d = np.tile([math.sin(theta), 0.0, -math.cos(theta)], (len(xyz), 1))
    r = recast(xyz, d, owner, pre, post, {7: 0.0}, range_noise_m=0.0, seed=0)
    hole = _inside_hole(xyz[:, :2], origin)
    moved = r.fate == MOVED
    assert np.array_equal(moved, hole)  # every pulse into the opening goes on: the floor is wider than it
    shift = (ROOF_Z - FLOOR_Z) * math.tan(theta)
    np.testing.assert_allclose(r.xyz[moved, 0], xyz[moved, 0] + shift, atol=1e-6)
    np.testing.assert_allclose(r.xyz[moved, 2], FLOOR_Z, atol=1e-6)
    # the floor seen lies shift metres beyond the opening's far side only where the opening lets the pulse by
    assert r.xyz[moved, 0].max() <= HOLE[2] + shift + 1e-9


def test_noise_is_seeded_along_the_pulse_and_only_on_new_returns():
    origin = np.zeros(3)
    pre, post = _box_scenes(origin)
    xyz, owner = _roof_returns(origin)
    down = np.tile([0.0, 0.0, -1.0], (len(xyz), 1))
    a = recast(xyz, down, owner, pre, post, {7: 0.0}, range_noise_m=0.05, seed=3)
    b = recast(xyz, down, owner, pre, post, {7: 0.0}, range_noise_m=0.05, seed=3)
    assert np.array_equal(a.xyz, b.xyz)
    moved = a.fate == MOVED
    dz = a.xyz[moved, 2] - FLOOR_Z
    assert abs(dz.std() - 0.05) < 0.01 and abs(dz.mean()) < 0.01
    np.testing.assert_allclose(a.xyz[moved, :2], xyz[moved, :2], atol=1e-9)  # vertical pulses: along z only
    assert np.array_equal(a.xyz[~moved], xyz[~moved])


def test_a_tree_over_the_roof_and_the_ground_beside_it_are_kept_and_a_pulse_that_meets_nothing_is_removed():
    origin = np.zeros(3)
    ground = (_quad(-30, -30, 42, 42, 0.0), 0, GROUND)
    pre = _scene([ground, (_quad(0, 0, 12, 12, ROOF_Z), 7, ROOF)], origin)
    # the whole roof gone and no floor: the pulse to the roof meets only the ground, a hole in it nothing
    post = _scene([(_quad(-30, -30, 5, 42, 0.0), 0, GROUND), (_quad(7, -30, 42, 42, 0.0), 0, GROUND)], origin)
    xyz = np.array([[6.0, 6.0, ROOF_Z + 4.0],  # a tree crown 4 m over the roof
                    [3.0, 3.0, ROOF_Z],  # roof: the ground under it stands
                    [6.0, 3.0, ROOF_Z],  # roof over the ground's gap: nothing behind
                    [20.0, 20.0, 0.0]])  # ground beside the building
    owner = np.array([7, 7, 7, 0])
    down = np.tile([0.0, 0.0, -1.0], (4, 1))
    r = recast(xyz, down, owner, pre, post, {7: 0.0}, range_noise_m=0.0, seed=0)
    assert r.fate.tolist() == [KEPT, MOVED, REMOVED, KEPT]
    np.testing.assert_allclose(r.xyz[1], [3.0, 3.0, 0.0], atol=1e-9)
    assert r.surface[1] == GROUND


def test_debris_in_front_of_a_neighbours_ground_return_hides_it():
    origin = np.zeros(3)
    ground = (_quad(-30, -30, 42, 42, 0.0), 0, GROUND)
    pre = _scene([ground, (_quad(0, 0, 12, 12, ROOF_Z), 7, ROOF)], origin)
    from quakescan.formats.scene import DEBRIS
    post = _scene([ground, (_quad(0, 0, 12, 12, ROOF_Z), 7, ROOF), (_quad(13, 0, 16, 12, 1.0), 7, DEBRIS)], origin)
    xyz = np.array([[14.0, 5.0, 0.0], [14.0, 5.0, 0.95], [20.0, 5.0, 0.0]])
    r = recast(xyz, np.tile([0.0, 0.0, -1.0], (3, 1)), np.zeros(3, np.int64), pre, post, {7: 0.0}, 0.0, 0)
    # the ground under the debris now returns from its top; a return within IN_FRONT_M of it stays real
    assert r.fate.tolist() == [MOVED, KEPT, KEPT]
    np.testing.assert_allclose(r.xyz[0], [14.0, 5.0, 1.0], atol=1e-9)


def test_a_simulated_flight_line_is_recovered_from_its_records():
    rng = np.random.default_rng(0)
    speed, height, heading = 60.0, 400.0, np.array([math.cos(0.6), math.sin(0.6)])
    right = np.array([heading[1], -heading[0]])
    t = np.sort(rng.uniform(0, 3.0, 20000))
    angle = np.radians(rng.uniform(-20, 20, len(t)))
    sensor = np.array([85_000.0, 446_000.0]) + np.outer(t, speed * heading)
    ground_z = rng.normal(0.0, 0.5, len(t))
    xy = sensor + np.outer((height - ground_z) * np.tan(angle), right)
    xyz = np.c_[xy, ground_z]
    p = pulses_mod.lidar_pulses(xyz, t + 3e5, np.round(np.degrees(angle), 3), np.full(len(t), 9))
    (line,) = p.lines
    assert line.method == pulses_mod.TRAJECTORY and (p.method == pulses_mod.TRAJECTORY).all()
    assert abs(line.speed_m_s - speed) < 0.5 and abs(line.height_m - height) < 5.0
    want = np.c_[np.sin(angle)[:, None] * right, -np.cos(angle)]
    cos = np.clip(np.einsum("ij,ij->i", p.directions, want), -1, 1)
    assert np.degrees(np.arccos(cos)).max() < 0.5


def test_a_line_too_short_to_fit_keeps_its_scan_angles_and_a_file_without_them_looks_down():
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(0, 100, 50), rng.uniform(0, 100, 50), np.zeros(50)]
    p = pulses_mod.lidar_pulses(xyz, np.full(50, 5.0), np.full(50, 30.0), np.full(50, 3))
    assert (p.method == pulses_mod.NADIR).all()  # no heading could be fitted: straight down
    q = pulses_mod.lidar_pulses(xyz, None, None, None)
    assert (q.directions == [0, 0, -1]).all()
    heading = np.array([1.0, 0.0])
    d = pulses_mod.scan_angle_directions(np.radians([30.0, -30.0]), heading)
    np.testing.assert_allclose(d, [[0, -0.5, -math.sqrt(3) / 2], [0, 0.5, -math.sqrt(3) / 2]], atol=1e-12)


def test_a_prism_has_the_footprints_area_as_roof_and_outward_walls():
    poly = shapely.Polygon([(0, 0), (10, 0), (10, 4), (4, 4), (4, 10), (0, 10)],
                           holes=[[(1, 1), (2, 1), (2, 2), (1, 2)]])
    origin = np.array([100.0, 200.0, 0.0])
    v, f, s = prism(shapely.affinity.translate(poly, 100, 200), -0.5, 7.0, origin)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    roof = s == ROOF
    assert math.isclose(0.5 * np.linalg.norm(n[roof], axis=1).sum(), poly.area, rel_tol=1e-12)
    assert (n[roof, 2] > 0).all()
    walls = s == WALL
    centre = (a + b + c)[walls] / 3
    # outward: a step along the normal leaves the polygon (the hole's walls point into the hole)
    step = centre[:, :2] + 0.01 * n[walls, :2] / np.linalg.norm(n[walls, :2], axis=1, keepdims=True)
    assert not shapely.contains_xy(poly, step[:, 0], step[:, 1]).any()
    assert math.isclose(0.5 * np.linalg.norm(n[walls], axis=1).sum(), poly.length * 7.5, rel_tol=1e-12)


def test_a_proxy_stands_on_its_ground_points_up_to_its_roof_and_refuses_a_cloud_with_no_building():
    from quakescan.formats.footprints import Footprints

    rng = np.random.default_rng(2)
    g = rng.uniform(-20, 30, (4000, 2))
    ground = np.c_[g, rng.normal(1.0, 0.01, len(g))]
    r = rng.uniform(0, 10, (2000, 2))
    roof = np.c_[r, np.full(len(r), 9.0)]
    xyz = np.r_[ground, roof] + [85_000.0, 446_000.0, 0.0]
    cls = np.r_[np.full(len(g), 2), np.full(len(r), 6)].astype(np.uint8)
    fp = Footprints(np.array([5]), [shapely.box(85_000.0, 446_000.0, 85_010.0, 446_010.0)])
    from quakescan.formats.footprints import assign_buildings

    owner = assign_buildings(xyz[:, 0], xyz[:, 1], fp)
    m = build_proxy(xyz, cls, owner, fp, np.floor(xyz.min(axis=0)))
    (p,) = m.buildings.values()
    assert abs(p.ground_z - 1.0) < 0.05 and p.roof_z == 9.0
    assert m.scene.buildings[0].storeys == round(8.0 / 3.0)
    with pytest.raises(ProxyError, match="no footprint holds enough points"):
        build_proxy(ground + [85_000.0, 446_000.0, 0.0], cls[:len(g)], np.zeros(len(g), np.int64), fp,
                    np.zeros(3))


def test_a_building_cropped_tight_takes_its_ground_from_farther_off_and_none_beyond_the_reach():
    from quakescan.injection.proxy import GROUND_FALLBACK_M, GROUND_SEARCH_M, ground_heights

    box = shapely.box(0.0, 0.0, 10.0, 10.0)
    ground = np.array([[-15.0, 5.0, 2.0], [-15.0, 6.0, 4.0]])  # 15 m west: beyond the first search
    assert GROUND_SEARCH_M < 15.0 < GROUND_FALLBACK_M
    z = ground_heights(ground, np.array([2, 2]), [box])
    assert z[0] == pytest.approx(2.0 + 0.1 * 2.0)  # the 10th percentile of the two
    far = ground - [GROUND_FALLBACK_M, 0.0, 0.0]
    assert np.isnan(ground_heights(far, np.array([2, 2]), [box])[0])


def test_range_noise_is_the_spread_of_ground_returns_in_their_cells():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 50, (50_000, 2))
    xyz = np.c_[xy, 0.1 * xy[:, 0] + rng.normal(0, 0.03, len(xy))]  # a 10 % slope: 0.029 m across a 1 m cell
    est = estimate_range_noise(xyz, np.full(len(xy), 2, np.uint8))
    assert 0.03 <= est <= math.hypot(0.03, 0.1 / math.sqrt(12)) + 0.003


def test_settings_refuse_what_they_cannot_do():
    with pytest.raises(InjectionError, match="either grades per building or a grade mix"):
        InjectSettings()
    with pytest.raises(InjectionError, match=r"grades \(3, 4, 5\)"):
        InjectSettings(grade_mix={2: 1})
    with pytest.raises(InjectionError, match="building 4: grade must be an integer 0-5"):
        InjectSettings(grades={4: 6})


@pytest.fixture
def tile2(shared_data):
    return shared_data / "ahn3_cropped_2.laz", shared_data / "ahn3_footprints_rd.geojson"


def test_a_real_tile_left_at_grade_0_comes_back_byte_for_byte(tile2, tmp_path):
    cloud, footprints = tile2
    r = inject(cloud, footprints, tmp_path / "out", InjectSettings(grades={}))
    a, b = laspy.read(cloud), laspy.read(r.post)
    assert r.counts == {"kept": len(a.points), "moved": 0, "removed": 0}
    assert a.points.array.tobytes() == b.points.array.tobytes()
    truth = list(csv.DictReader(open(r.truth)))
    assert len(truth) == 160 and all(t["grade"] == "0" for t in truth)


def test_a_damaged_building_changes_only_returns_near_it_and_a_rerun_is_kept(tile2, tmp_path):
    cloud, footprints = tile2
    settings = InjectSettings(grades={95: 5}, seed=1)
    r = inject(cloud, footprints, tmp_path / "out", settings)
    a, b = laspy.read(cloud).points.array, laspy.read(r.post).points.array
    assert len(a) == len(b)  # nothing removed: the terrain lies under every collapsed part
    changed = a != b
    from quakescan.formats.footprints import assign_buildings, read_footprints

    fp = read_footprints(footprints)
    las = laspy.read(cloud)
    owner = assign_buildings(np.asarray(las.x), np.asarray(las.y), fp)
    own = owner == 95
    assert changed[own].mean() > 0.5  # a heap in place of the building
    assert r.counts["moved"] == changed.sum()
    poly = fp.polygons[list(fp.ids).index(95)]
    far = ~shapely.dwithin(poly, shapely.points(np.c_[las.x, las.y]), 30.0)
    assert not changed[far].any()
    post = laspy.read(r.post)
    assert (np.asarray(post.z)[own].mean() < np.asarray(las.z)[own].mean() - 2.0)
    record = json.loads(r.record.read_text())
    assert record["grades"]["95"] == 5 and record["kind"] == "lidar"
    assert {line["method"] for line in record["pulses"]["lines"]} == {"trajectory"}
    again = inject(cloud, footprints, tmp_path / "out", settings)
    assert again.reused and again.post.read_bytes() == r.post.read_bytes()
    with pytest.raises(InjectionError, match="building 99999 is not one of the footprints' IDs"):
        inject(cloud, footprints, tmp_path / "bad", InjectSettings(grades={99999: 3}))
    with pytest.raises(InjectionError, match="only .* have a proxy"):
        inject(cloud, footprints, tmp_path / "bad", InjectSettings(grade_mix={3: 500}))


def test_the_command_writes_its_three_files_and_refuses_bad_arguments(tile2, tmp_path, capsys):
    from quakescan.cli import main

    cloud, footprints = tile2
    grades = tmp_path / "grades.csv"
    grades.write_text("building_id,grade\n95,4\n")
    out = tmp_path / "out"
    assert main(["inject", str(cloud), "--footprints", str(footprints), "--grades", str(grades), "--seed", "2",
                 "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "1 buildings damaged (0 at grade 3, 1 at grade 4, 0 at grade 5)" in said
    assert sorted(p.name for p in out.iterdir()) == ["inject.json", "post.laz", "scenes", "truth.csv"]
    truth = {r["building_id"]: r for r in csv.DictReader(open(out / "truth.csv"))}
    assert truth["95"]["grade"] == "4" and truth["95"]["injected"] == "1" and truth["95"]["patterns"]
    with pytest.raises(SystemExit):
        main(["inject", str(cloud), "--footprints", str(footprints), "--grade-mix", "2:3", "-o", str(out)])
    assert "grades must be 3, 4, 5" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("building_id,grade\n95,7\n")
    assert main(["inject", str(cloud), "--footprints", str(footprints), "--grades", str(bad), "-o", str(out)]) == 2
    assert "grade 7 is not an EMS-98 grade" in capsys.readouterr().err
    # an output folder holding the input under the output's name is refused, the input untouched
    twin = tmp_path / "twin"
    twin.mkdir()
    (twin / "post.laz").write_bytes(cloud.read_bytes())
    assert main(["inject", str(twin / "post.laz"), "--footprints", str(footprints), "-o", str(twin)]) == 2
    assert "is an input of this run" in capsys.readouterr().err
    assert (twin / "post.laz").read_bytes() == cloud.read_bytes()


def test_the_public_api_injects_as_the_command_does(tile2, tmp_path):
    import quakescan as qs

    cloud, footprints = tile2
    r = qs.inject(cloud, footprints, tmp_path / "api", grades={95: 5}, seed=1)
    again = inject(cloud, footprints, tmp_path / "lib", InjectSettings(grades={95: 5}, seed=1))
    assert r.post.read_bytes() == again.post.read_bytes() and r.counts == again.counts
