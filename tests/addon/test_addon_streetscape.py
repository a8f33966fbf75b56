"""Streetscape: placement (pure Python), Blender objects, export and the generator's flag."""
import hashlib
import importlib.util
import math

import numpy as np
import pytest
from conftest import HAVE_BPY, REPO

from addon import citygen
from addon import streetscape as ss

SCRIPT = REPO / "blender_scripts" / "generate_scenes.py"
needs_bpy = pytest.mark.skipif(not HAVE_BPY, reason="bpy module not installed")


def _plan(set_name="generic", n=30, seed=1):
    plan = citygen.city_plan(set_name, n, seed)
    return plan, ss.plan_footprints(plan)


def _object_points(scape):
    """Sample points of everything that must stand outside footprints (crowns excluded)."""
    pts = [(t.x, t.y) for t in scape.trees] + [(f.x, f.y) for f in scape.furniture]
    for c in scape.cars:
        pts += ss._rect_samples(c.x, c.y, c.heading, c.length, c.width).tolist()
    for h in scape.hedges:
        pts += np.linspace((h.x0, h.y0), (h.x1, h.y1), 10).tolist()
    return np.array(pts)


@pytest.mark.parametrize("set_name", ["generic", "region", "small"])
def test_placement_is_seeded_and_nothing_stands_in_a_footprint(set_name):
    plan, fps = _plan(set_name, 40)
    a = ss.plan_streetscape(fps, plan.bounds, set_name, 3)
    assert a == ss.plan_streetscape(fps, plan.bounds, set_name, 3)
    assert a != ss.plan_streetscape(fps, plan.bounds, set_name, 4)
    assert a.trees and a.cars and a.furniture
    space = ss.FreeSpace(fps, plan.bounds)
    assert space.wall_distance(_object_points(a)).min() >= ss.CLEARANCE_M - 1e-9
    x0, y0, x1, y1 = plan.bounds
    p = _object_points(a)
    assert ((p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)).all()
    # no two trunks, cars or furniture on each other
    discs = [(t.x, t.y) for t in a.trees] + [(c.x, c.y) for c in a.cars] + [(f.x, f.y) for f in a.furniture]
    d = np.asarray(discs)
    gaps = np.hypot(d[:, None, 0] - d[None, :, 0], d[:, None, 1] - d[None, :, 1]) + np.eye(len(d)) * 99
    assert gaps.min() > 0.3


def test_densities_differ_by_set_and_crowns_overhang_roofs():
    plan, fps = _plan("generic", 60)
    town = ss.plan_streetscape(fps, plan.bounds, "generic", 1)
    rplan, rfps = _plan("region", 60)
    centre = ss.plan_streetscape(rfps, rplan.bounds, "region", 1)
    assert len(town.trees) > 4 * len(centre.trees)
    assert len(centre.cars) / 60 > 0.6
    # several sizes, large ones 15-20 m
    assert {t.kind for t in town.trees} == {"small", "medium", "large"}
    assert max(t.height for t in town.trees) > 15 and min(t.height for t in town.trees) < 7
    space = ss.FreeSpace(fps, plan.bounds)
    near = [t for t in town.trees if space.wall_distance([(t.x, t.y)])[0] <= 4.0 + 0.5]
    assert len(near) >= 10
    # a crown reaching over a footprint: its blob's edge point towards the wall lies inside
    overhang = 0
    for t in near:
        cx, cy, _, rx, _, _ = t.blobs[0]
        ang = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        ring = np.column_stack([cx + 0.9 * rx * np.cos(ang), cy + 0.9 * rx * np.sin(ang)])
        overhang += bool((space.wall_distance(ring) < 0).any())
    assert overhang >= 5


def test_post_event_cars_keep_some_move_some_and_bring_new_ones():
    plan, fps = _plan("generic", 60)
    pre = ss.plan_streetscape(fps, plan.bounds, "generic", 2)
    post = ss.post_event_cars(pre, fps, plan.bounds, "generic", 2, "post")
    assert post == ss.post_event_cars(pre, fps, plan.bounds, "generic", 2, "post")
    other = ss.post_event_cars(pre, fps, plan.bounds, "generic", 2, "post_heavy")
    assert post != other
    pre_cars = {c.id: c for c in pre.cars}
    kept = [c for c in post if c.id in pre_cars and c == pre_cars[c.id]]
    moved = [c for c in post if c.id in pre_cars and c != pre_cars[c.id]]
    new = [c for c in post if c.id not in pre_cars]
    gone = set(pre_cars) - {c.id for c in post}
    assert kept and moved and new and gone
    space = ss.FreeSpace(fps, plan.bounds)
    for c in post:
        assert space.wall_distance(ss._rect_samples(c.x, c.y, c.heading, c.length, c.width)).min() >= ss.CLEARANCE_M
    # a moved car slid along its street
    for c in moved:
        p = pre_cars[c.id]
        assert c.heading == p.heading and 2.0 <= math.hypot(c.x - p.x, c.y - p.y) <= 8.0


def test_ground_heights_follow_a_sloped_terrain():
    v = np.array([[0, 0, 0], [100, 0, 10], [100, 100, 10], [0, 100, 0]], float)
    z = ss.terrain_height_function(v, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(z(np.array([[50, 50], [25, 80], [150, 50]])), [5.0, 2.5, 10.0])


def _gen():
    spec = importlib.util.spec_from_file_location("generate_scenes_street_test", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _digest(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _faces_of(scene, surface):
    keep = scene.face_surface == surface
    tri = scene.vertices[scene.faces[keep]]
    return np.sort(tri.reshape(len(tri), -1), axis=0)


@needs_bpy
def test_generator_streetscape_keeps_trees_changes_cars_and_none_is_unchanged(bpy_registered, tmp_path, capsys):
    import json

    from quakescan.acquisition.raycast import RayCaster
    from quakescan.formats.scene import OBJECT, VEGETATION, read_scene
    gen = _gen()
    argv = ["--set", "generic", "--dataset", "paper", "--buildings", "10", "--seed", "2"]
    assert gen.main(argv + ["--out", str(tmp_path / "plain")]) == 0
    assert gen.main(argv + ["--streetscape", "none", "--out", str(tmp_path / "none")]) == 0
    assert _digest(tmp_path / "plain") == _digest(tmp_path / "none")
    assert "streetscape" not in json.loads((tmp_path / "none" / "pre" / "scene.json").read_text())["generator"]
    assert gen.main(argv + ["--streetscape", "typical", "--out", str(tmp_path / "street")]) == 0
    # a folder made without the streetscape is not reused for one with it
    assert gen.main(argv + ["--streetscape", "typical", "--out", str(tmp_path / "plain")]) == 1
    pre = read_scene(tmp_path / "street" / "pre")
    assert json.loads((tmp_path / "street" / "pre" / "scene.json").read_text())["generator"]["streetscape"] == "typical"
    assert pre.has_porous and pre.transmission == 0.5
    assert (pre.face_building[pre.face_surface >= VEGETATION] == 0).all()
    assert set(RayCaster(pre).face_class[pre.face_porous]) == {5}
    trees = _faces_of(pre, VEGETATION)
    cars = _faces_of(pre, OBJECT)
    assert len(trees) and len(cars)
    for name in ("post_heavy", "post_extreme", "post_destruction"):
        post = read_scene(tmp_path / "street" / name)
        np.testing.assert_array_equal(_faces_of(post, VEGETATION), trees)  # same trees and hedges
        assert post.face_porous.sum() == pre.face_porous.sum()
        assert not np.array_equal(_faces_of(post, OBJECT), cars)  # other cars
    # buildings are those of the run without streetscape
    plain = read_scene(tmp_path / "plain" / "pre")
    for sc in (plain, pre):
        sc.b = sc.faces[sc.face_building > 0]
    assert np.array_equal(plain.vertices[plain.b], pre.vertices[pre.b])


@needs_bpy
def test_streetscape_objects_round_trip_through_both_exporters(blank, tmp_path):
    from addon import io_export, io_import, scene_tools, street_objects
    from quakescan.formats.scene import OBJECT, VEGETATION, read_scene
    bpy = blank
    coll = bpy.data.collections.new("city")
    bpy.context.scene.collection.children.link(coll)
    plan, fps = _plan("generic", 4)
    scene_tools.create_terrain_object(coll, *plan.bounds)
    from addon.geometry.shell import ShellSpec
    b = plan.buildings[0]
    scene_tools.create_building_object(coll, ShellSpec(**b.shell), b.id, location=(*b.location, 0.0),
                                       rotation_z=b.rotation)
    scape = ss.plan_streetscape(fps, plan.bounds, "generic", 5)
    objs = street_objects.add_objects(coll, scape)
    assert {o[street_objects.STREET_PROP] for o in objs} >= {"trees", "cars"}
    io_export.export_objects(tmp_path / "a", scene_tools.scene_objects(coll))
    a = read_scene(tmp_path / "a")
    assert {int(x) for x in np.unique(a.face_surface)} >= {0, 1, 2, VEGETATION, OBJECT}
    assert a.has_porous and (a.face_surface[a.face_porous] == VEGETATION).all()
    assert (a.face_surface == VEGETATION).sum() > a.face_porous.sum()  # trunks are opaque
    # the exact exporter (bundle sets) keeps them too, after an import
    coll2 = bpy.data.collections.new("imported")
    bpy.context.scene.collection.children.link(coll2)
    io_import.import_bundle(tmp_path / "a", coll2)
    io_import.export_bundle(tmp_path / "b", scene_tools.scene_objects(coll2))
    b2 = read_scene(tmp_path / "b")
    assert b2.face_porous.sum() == a.face_porous.sum()
    assert np.array_equal(np.bincount(b2.face_surface, minlength=7), np.bincount(a.face_surface, minlength=7))


@needs_bpy
def test_generator_streetscape_around_an_imported_bundle(bpy_registered, tmp_path):
    from quakescan.formats.scene import VEGETATION, read_scene, write_scene
    from quakescan.formats.synthetic import box_city
    src = box_city(3, 3, height=(6.0, 9.0, 15.0), origin=(500000.0, 5000000.0, 0.0), margin=25.0)
    src.crs = "EPSG:32633"
    src.vertices = src.vertices + [0.0, 0.0, 40.0]  # terrain at 40 m: objects stand on it
    write_scene(src, tmp_path / "src")
    gen = _gen()
    argv = ["--set", "bundle", "--source", str(tmp_path / "src"), "--dataset", "mixed", "--seed", "1",
            "--streetscape", "typical", "--out", str(tmp_path / "out")]
    assert gen.main(argv) == 0
    pre = read_scene(tmp_path / "out" / "pre")
    post = read_scene(tmp_path / "out" / "post")
    assert pre.origin.tolist() == src.origin.tolist() and pre.has_porous
    veg = pre.vertices[pre.faces[pre.face_surface == VEGETATION]]
    assert veg[..., 2].min() >= 40.0 - 0.31 and veg[..., 2].max() > 43.0
    # no trunk, car or furniture inside a building's extent
    fps = []
    for b in pre.buildings:
        xy = pre.vertices[pre.faces[pre.face_building == b.id]][..., :2].reshape(-1, 2)
        fps.append(np.array([xy.min(0), [xy.max(0)[0], xy.min(0)[1]], xy.max(0), [xy.min(0)[0], xy.max(0)[1]]]))
    opaque = (pre.face_surface >= VEGETATION) & ~pre.face_porous
    pts = pre.vertices[pre.faces[opaque]][..., :2].reshape(-1, 2)
    assert ss.FreeSpace(fps, (-1e9, -1e9, 1e9, 1e9)).wall_distance(pts).min() > 0
    np.testing.assert_array_equal(_faces_of(post, VEGETATION), _faces_of(pre, VEGETATION))


def test_annexes_of_detailed_plans_are_footprints_too():
    plan = citygen.city_plan("generic", 40, 3, details="typical")
    annexes = [(b, d) for b in plan.buildings for d in b.shell.get("details") or [] if d["kind"] == "annex"]
    assert annexes
    fps = ss.plan_footprints(plan)
    assert len(fps) == len(plan.buildings) + len(annexes)
    # every annex polygon touches its building's footprint along one edge and lies outside it
    space_main = ss.FreeSpace(fps[:len(plan.buildings)], plan.bounds)
    for poly in fps[len(plan.buildings):]:
        d = space_main.wall_distance(poly)
        assert np.isclose(d, 0, atol=1e-6).sum() == 2 and (d > 0.5).sum() == 2
    scape = ss.plan_streetscape(fps, plan.bounds, "generic", 3)
    assert ss.FreeSpace(fps, plan.bounds).wall_distance(_object_points(scape)).min() >= ss.CLEARANCE_M - 1e-9
