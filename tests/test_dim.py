"""Virtual DIM: visibility (≥ 2 cameras), paper point spacing, determinism, labels, UTM
invariance, noise with obliqueness, survey files and bad input."""
import json
import math

import laspy
import numpy as np
import pytest

from quakescan.acquisition.dim import simulate_dim
from quakescan.acquisition.dim_cameras import plan_cameras
from quakescan.acquisition.dim_settings import (FIELD_DOC, PhotoSurvey, load_photo_survey, preset_dim,
                                                write_photo_survey_template)
from quakescan.acquisition.raycast import RayCaster, ground_level
from quakescan.errors import SceneError, SurveyError
from quakescan.formats.scene import GROUND, ROOF, WALL, Building, Scene
from quakescan.formats.synthetic import _MeshBuilder, box_city, box_mesh, ground_mesh
from tests.las_contract import CONTRACT_ORIGIN, read_checked
from tests.spacing import nearest_neighbour_spacing

# A smaller flight for the quick tests: the obliques still reach a small city's facades.
QUICK = preset_dim("paper").replace(margin_m=60.0)
EXACT = QUICK.replace(noise_px=0.0, smoothing_radius_m=0.0)


def _read(path):
    las = laspy.read(path)
    return las, np.column_stack([las.x, las.y, las.z])


def _courtyard_scene(height=30.0):
    """A 12 × 12 m ring building (ID 1) around a closed 2 × 2 m courtyard, 30 m tall, and a
    plain 10 m box (ID 2) beside it, on a ground patch."""
    mb = _MeshBuilder()
    mb.add(*ground_mesh(-20, -20, 50, 32), 0)
    for x0, y0, x1, y1 in ((0, 0, 12, 5), (0, 7, 12, 12), (0, 5, 5, 7), (7, 5, 12, 7)):
        mb.add(*box_mesh(x0, y0, x1, y1, 0.0, height), 1)
    mb.add(*box_mesh(22, 0, 34, 12, 0.0, 10.0), 2)
    v, f, b, s = mb.arrays()
    return Scene(v, f, b, s, [Building(1, grade=3, storeys=10), Building(2, grade=0, storeys=3)])


def _count_views(scene, survey, world_xyz, normals):
    """Independent check: cameras that see each point (in frame, incidence below the cut-off,
    nothing on the ray from the point to the camera), cast point → camera."""
    caster = RayCaster(scene)
    cams = plan_cameras(survey, caster.bounds_local, ground_level(scene) - caster.local_origin[2])
    p = world_xyz - scene.origin - caster.local_origin
    cos_max = math.cos(math.radians(survey.max_incidence_deg))
    count = np.zeros(len(p), np.int64)
    for c in range(len(cams)):
        rel = p - cams.position[c]
        q = rel @ cams.rotation[c].T
        d = np.linalg.norm(rel, axis=1)
        cos_t = np.abs(np.einsum("ij,ij->i", normals, rel)) / d
        ok = ((q[:, 2] > 0) & (np.abs(q[:, 0]) <= q[:, 2] * cams.tan_half_w[c])
              & (np.abs(q[:, 1]) <= q[:, 2] * cams.tan_half_h[c]) & (cos_t >= cos_max))
        i = np.flatnonzero(ok)
        if not len(i):
            continue
        u = -rel[i] / d[i, None]
        start = 0.02
        face, t = caster.cast(p[i] + start * u, u, float((d[i] - start).max()))
        count[i] += (face < 0) | (t > d[i] - start)  # a hit beyond the camera does not count
    return count


def test_no_points_where_fewer_than_two_cameras_see(tmp_path):
    scene = _courtyard_scene()
    out = tmp_path / "c.las"
    summary = simulate_dim(scene, EXACT, out)
    assert summary.rejected_by_visibility + summary.hidden_pieces > 0
    las, xyz = _read(out)
    surf = np.asarray(las.surface)
    # the closed courtyard floor is seen by fewer than two cameras (checked independently) …
    g = np.stack(np.meshgrid(np.linspace(5.05, 6.95, 12), np.linspace(5.05, 6.95, 12)), -1).reshape(-1, 2)
    floor = np.column_stack([g, np.zeros(len(g))])
    up = np.tile([0.0, 0.0, 1.0], (len(floor), 1))
    assert _count_views(scene, EXACT, floor, up).max() < 2
    # … and gets no point
    in_court = (xyz[:, 0] > 5) & (xyz[:, 0] < 7) & (xyz[:, 1] > 5) & (xyz[:, 1] < 7) & (xyz[:, 2] < 29)
    assert not in_court.any()
    # every point of a horizontal surface is seen by at least two cameras
    horizontal = np.flatnonzero((surf == ROOF) | (surf == GROUND))
    pick = np.random.default_rng(0).choice(horizontal, 1500, replace=False)
    counts = _count_views(scene, EXACT, xyz[pick], np.tile([0.0, 0.0, 1.0], (len(pick), 1)))
    assert counts.min() >= 2, np.bincount(counts)[:3]
    # walls: axis-aligned, normal from the nearest box plane
    walls = np.flatnonzero(surf == WALL)
    pick = np.random.default_rng(1).choice(walls, 1500, replace=False)
    pw = xyz[pick]
    planes_x = np.array([0.0, 5.0, 7.0, 12.0, 22.0, 34.0])
    planes_y = np.array([0.0, 5.0, 7.0, 12.0])
    dx = np.abs(pw[:, :1] - planes_x).min(axis=1)
    dy = np.abs(pw[:, 1:2] - planes_y).min(axis=1)
    normals = np.where((dx < dy)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    counts = _count_views(scene, EXACT, pw, normals)
    assert counts.min() >= 2, np.bincount(counts)[:3]
    # the hidden faces inside the ring and below the boxes get nothing
    assert not ((xyz[:, 2] < -1e-3) | (xyz[:, 2] > 30.0 + 1e-3)).any()


def test_paper_preset_spacing_matches_the_lAquila_dim_clouds(tmp_path):
    """Zahs et al.: L'Aquila DIM roofs 0.09 m (std 0.03), facades 0.12 m (std 0.04)."""
    scene = box_city(rows=3, cols=4, footprint=14.0, street=12.0, height=(9.0, 12.0, 15.0, 6.0))
    out = tmp_path / "p.las"
    summary = simulate_dim(scene, preset_dim("paper"), out)
    las, xyz = _read(out)
    bid, surf = np.asarray(las.building_id), np.asarray(las.surface)
    for code, mean, std in ((ROOF, 0.09, 0.03), (WALL, 0.12, 0.04)):
        nn = nearest_neighbour_spacing(xyz, bid, surf, code)
        assert abs(nn.mean() - mean) <= std, (code, nn.mean())
        assert abs(nn.std() - std) <= 0.02, (code, nn.std())
    assert set(summary.points_by_building) == set(range(1, 13))
    assert summary.points == len(xyz)
    json.dumps(summary.to_json())


def test_same_seed_same_bytes(tmp_path):
    scene = box_city(rows=1, cols=2)
    calls = []
    simulate_dim(scene, QUICK, tmp_path / "a.las", seed=3, workers=2, progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1][0] == calls[-1][1]
    simulate_dim(scene, QUICK, tmp_path / "b.las", seed=3, workers=1)
    simulate_dim(scene, QUICK, tmp_path / "c.las", seed=4, workers=2)
    a, b, c = ((tmp_path / f"{k}.las").read_bytes() for k in "abc")
    assert a == b
    assert a != c


def test_labels_match_the_faces(tmp_path):
    grades = [0, 3, 4, 5]
    heights = (6.0, 9.0, 12.0, 15.0)
    scene = box_city(rows=2, cols=2, height=heights, grades=grades)
    for survey, tol in ((EXACT, 1e-3), (QUICK, 0.25)):
        out = tmp_path / "l.las"
        simulate_dim(scene, survey, out)
        las, xyz = _read(out)
        bid, surf, grade = np.asarray(las.building_id), np.asarray(las.surface), np.asarray(las.grade)
        cls = np.asarray(las.classification)
        assert set(np.unique(bid)) == {0, 1, 2, 3, 4}
        assert (np.asarray(las.return_number) == 1).all() and (np.asarray(las.number_of_returns) == 1).all()
        for b in scene.buildings:
            m = bid == b.id
            assert (grade[m] == b.grade).all() and (cls[m] == 6).all()
            r, c = divmod(b.id - 1, 2)
            x0, y0 = c * 22.0, r * 22.0
            roof = xyz[m & (surf == ROOF)]
            assert len(roof) > 1000
            np.testing.assert_allclose(roof[:, 2], heights[b.id - 1], atol=tol)
            assert (roof[:, 0] > x0 - tol).all() and (roof[:, 0] < x0 + 12 + tol).all()
            wall = xyz[m & (surf == WALL)]
            assert len(wall) > 1000
            d = np.min(np.abs(np.stack([wall[:, 0] - x0, wall[:, 0] - x0 - 12, wall[:, 1] - y0,
                                        wall[:, 1] - y0 - 12])), axis=0)
            assert d.max() < tol
        ground = bid == 0
        assert (surf[ground] == GROUND).all() and (cls[ground] == 2).all() and (grade[ground] == 255).all()
        np.testing.assert_allclose(xyz[ground, 2], 0.0, atol=tol)


def test_utm_coordinates_give_the_same_points(tmp_path):
    shift = np.array([500000.0, 5000000.0, 250.0])
    local = box_city(rows=1, cols=2)
    moved = box_city(rows=1, cols=2, origin=tuple(shift))
    raw = box_city(rows=1, cols=2)
    raw.vertices = raw.vertices + shift
    outs = []
    for k, sc in enumerate((local, moved, raw)):
        out = tmp_path / f"{k}.las"
        simulate_dim(sc, QUICK, out, seed=5)
        outs.append(_read(out)[1])
    assert len(outs[0]) == len(outs[1]) == len(outs[2])
    ref = outs[0] + shift
    assert np.abs(outs[1] - ref).max() <= 1e-3 + 1e-6
    assert np.abs(outs[2] - ref).max() <= 1e-3 + 1e-6


def test_noise_grows_with_obliqueness(tmp_path):
    scene = box_city(rows=1, cols=2, height=12.0)
    out = tmp_path / "n.las"
    simulate_dim(scene, QUICK.replace(smoothing_radius_m=0.0), out)
    las, xyz = _read(out)
    bid, surf = np.asarray(las.building_id), np.asarray(las.surface)
    roof = xyz[(bid > 0) & (surf == ROOF), 2] - 12.0
    wall = xyz[(bid > 0) & (surf == WALL)]
    x0 = np.where(bid[(bid > 0) & (surf == WALL)] == 1, 0.0, 22.0)
    y0 = 0.0
    d = np.min(np.abs(np.stack([wall[:, 0] - x0, wall[:, 0] - x0 - 12, wall[:, 1] - y0,
                                wall[:, 1] - y0 - 12])), axis=0)
    roof_sigma, wall_sigma = roof.std(), np.sqrt(np.mean(d ** 2))
    assert 0.005 < roof_sigma < 0.05
    assert wall_sigma > 1.2 * roof_sigma, (roof_sigma, wall_sigma)


def test_edges_are_smoothed(tmp_path):
    """Near a roof edge the smoothed cloud leaves the roof plane (rounded edge)."""
    scene = box_city(rows=1, cols=1, height=10.0)
    runs = {}
    for r in (0.0, 0.3):
        out = tmp_path / f"s{r}.las"
        summary = simulate_dim(scene, EXACT.replace(smoothing_radius_m=r), out)
        las, xyz = _read(out)
        roof = xyz[np.asarray(las.surface) == ROOF]
        edge = (np.minimum.reduce([roof[:, 0], 12 - roof[:, 0], roof[:, 1], 12 - roof[:, 1]]) < 0.05)
        runs[r] = (summary.smoothed_points, np.abs(roof[edge, 2] - 10.0).mean())
    assert runs[0.0] == (0, 0.0)
    assert runs[0.3][0] > 0 and runs[0.3][1] > 0.02


def test_survey_file_round_trip_and_documentation(tmp_path):
    path = tmp_path / "photo.json"
    write_photo_survey_template(path)
    data = json.loads(path.read_text())
    names = [k for k in PhotoSurvey.__dataclass_fields__ if k != "name"]
    assert set(data["_doc"]) == set(names) == set(FIELD_DOC)
    assert all("[" in text for text in data["_doc"].values())  # every field states its unit
    assert load_photo_survey(path) == preset_dim("paper")
    assert load_photo_survey("paper") == PhotoSurvey()
    data["altitude_agl_m"] = 80.0
    path.write_text(json.dumps(data))
    assert load_photo_survey(path).altitude_agl_m == 80.0
    s = PhotoSurvey()
    assert s.gsd_m == pytest.approx(120 * 4.4e-6 / 0.024)


@pytest.mark.parametrize("change, word", [({"side_overlap_pct": 100.0}, "side_overlap_pct"),
                                          ({"oblique_cameras": 3}, "oblique_cameras"),
                                          ({"min_views": 0}, "min_views"),
                                          ({"max_incidence_deg": 95.0}, "max_incidence_deg"),
                                          ({"altitude_agl_m": -5.0}, "altitude_agl_m"),
                                          ({"noise_px": float("nan")}, "noise_px")])
def test_bad_survey_values_are_refused(change, word):
    with pytest.raises(SurveyError, match=word):
        preset_dim("paper").replace(**change)


def test_bad_input_gives_clear_errors(tmp_path):
    empty = Scene(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int32), np.zeros(0, np.uint8), [])
    with pytest.raises(SceneError, match="empty"):
        simulate_dim(empty, QUICK, tmp_path / "e.las")
    v, f, s = ground_mesh(0, 0, 10, 10)
    bare = Scene(v, f, np.zeros(len(f), np.int32), s, [])
    with pytest.raises(SceneError, match="no buildings"):
        simulate_dim(bare, QUICK, tmp_path / "e.las")
    with pytest.raises(SurveyError, match="unknown photo survey preset"):
        load_photo_survey("nope")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "quakescan-photo-survey", "version": 1, "altitude_m": 3}))
    with pytest.raises(SurveyError, match="altitude_m"):
        load_photo_survey(bad)
    bad.write_text(json.dumps({"format": "quakescan-survey", "version": 1}))
    with pytest.raises(SurveyError, match="not a photo survey"):
        load_photo_survey(bad)
    with pytest.raises(SurveyError, match="does not exist"):
        load_photo_survey(tmp_path / "missing.json")
    # nadir images that see the ground only within 0.5° of their axis: no surface in two images
    with pytest.raises(SurveyError, match="no points|no surface"):
        simulate_dim(box_city(rows=1, cols=1), QUICK.replace(oblique_cameras=0, max_incidence_deg=0.5),
                     tmp_path / "e.las")
    assert not (tmp_path / "e.las").exists()


def test_las_follows_the_contract(tmp_path):
    scene = box_city(rows=1, cols=2, origin=CONTRACT_ORIGIN)
    scene.crs = "EPSG:2056"
    out = tmp_path / "c.laz"
    summary = simulate_dim(scene, QUICK, out)
    las = read_checked(out, scene)
    assert las.header.system_identifier == "QuakeScan virtual DIM"
    assert las.header.point_count == summary.points
    assert (np.asarray(las.scan_angle) == 0).all()
    assert las.gps_time.min() >= QUICK.gps_start_s
    assert np.asarray(las.point_source_id).min() >= 1
    assert summary.points_by_surface["roof"] + summary.points_by_surface["wall"] + \
        summary.points_by_surface["ground"] == summary.points
