"""Operators through bpy.ops: context checks with messages, the authoring workflow, and
its export read back by the core (core is imported here, never by the add-on)."""
import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from quakescan.formats.scene import read_scene  # noqa: E402


def _active(bpy, obj):
    for o in bpy.context.selected_objects:
        o.select_set(False)
    if obj is not None:
        obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def _box(bpy, name="box", size=(10, 8, 9)):
    import bmesh
    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    for v in bm.verts:
        v.co.x *= size[0]
        v.co.y *= size[1]
        v.co.z = (v.co.z + 0.5) * size[2]
    bm.to_mesh(me)
    bm.free()
    obj = bpy.data.objects.new(name, me)
    bpy.context.collection.objects.link(obj)
    return obj


@pytest.mark.parametrize("op", ["apply_pattern", "apply_grade", "add_interior", "assign_ids", "reset_building"])
def test_operators_refuse_without_a_building(blank, op):
    bpy = blank
    with pytest.raises(RuntimeError, match=r"poll\(\).*(Select|building|Active)"):
        getattr(bpy.ops.damage, op)()
    obj = _box(bpy)  # a mesh, but no building ID yet
    _active(bpy, obj)
    if op != "assign_ids":
        with pytest.raises(RuntimeError, match="building"):
            getattr(bpy.ops.damage, op)()


def test_assign_ids_labels_faces(blank):
    bpy = blank
    a, b = _box(bpy, "a"), _box(bpy, "b")
    a.select_set(True)
    b.select_set(True)
    bpy.context.view_layer.objects.active = a
    assert bpy.ops.damage.assign_ids() == {'FINISHED'}
    assert (a.qs_building.building_id, b.qs_building.building_id) == (1, 2)
    assert a.qs_building.role == "BUILDING"
    ids = np.empty(len(b.data.polygons), np.int32)
    b.data.attributes["qs_building_id"].data.foreach_get("value", ids)
    assert (ids == 2).all()
    surf = np.empty(len(b.data.polygons), np.int32)
    b.data.attributes["qs_surface"].data.foreach_get("value", surf)
    # roof, 4 walls split at the storey levels (9 m box: 3 storeys), base
    assert sorted(surf.tolist()) == [1] + [2] * 12 + [4]
    storey = np.empty(len(b.data.polygons), np.int32)
    b.data.attributes["qs_storey"].data.foreach_get("value", storey)
    assert sorted(storey[surf == 2].tolist()) == [0] * 4 + [1] * 4 + [2] * 4


@pytest.mark.parametrize("pattern", __import__("addon.ems98", fromlist=["x"]).PATTERN_NAMES)
def test_every_pattern_on_a_user_mesh(blank, tmp_path, pattern):
    """A plain box made a building with Assign IDs (+ interior) takes every pattern whose
    requirements it meets; the export stays valid for the core."""
    bpy = blank
    from addon import scene_tools
    obj = _box(bpy, size=(16, 10, 12))
    _active(bpy, obj)
    bpy.ops.damage.assign_ids()
    bpy.ops.damage.add_interior()
    obj.qs_building.material = "reinforced_concrete" if pattern in (
        "infill_blowout", "pancake_collapse", "soft_storey_collapse", "mid_storey_collapse", "top_floor_pancake",
        "corner_failure", "overturn", "tilt") else "masonry"
    try:
        bpy.ops.damage.apply_pattern(pattern=pattern, randomize=True)
    except RuntimeError as e:
        assert pattern in ("gable_fall", "chimney_loss", "parapet_loss") and "does not apply" in str(e)
        return
    scene_tools.create_terrain_object(bpy.context.collection, -30, -30, 30, 30)
    sc = bpy.context.scene.qs_scene
    sc.export_dir = str(tmp_path / "b")
    sc.epoch = "post"
    assert bpy.ops.damage.export_bundle() == {'FINISHED'}
    s = read_scene(tmp_path / "b")
    assert s.buildings[0].patterns[0]["name"] == pattern


def test_user_mesh_workflow(blank, tmp_path):
    bpy = blank
    obj = _box(bpy)  # 9 m high: 3 storeys estimated
    _active(bpy, obj)
    bpy.ops.damage.assign_ids()
    assert obj.qs_building.storeys == 3 and obj.qs_building.storey_height == pytest.approx(3.0)
    assert bpy.ops.damage.add_interior() == {'FINISHED'}
    parts = np.empty(len(obj.data.polygons), np.int32)
    obj.data.attributes["qs_part"].data.foreach_get("value", parts)
    assert (parts == 3).sum() == 2  # two floor slabs
    with pytest.raises(RuntimeError, match="already has slabs"):
        bpy.ops.damage.add_interior()
    obj.qs_building.pattern = "wall_holes"
    assert bpy.ops.damage.apply_pattern() == {'FINISHED'}
    rec = json.loads(obj.qs_building.patterns_json)
    assert rec[0]["name"] == "wall_holes" and rec[0]["params"]["hole_area"] > 0
    assert obj.qs_building.grade == 3
    with pytest.raises(RuntimeError, match="does not apply.*gable"):
        bpy.ops.damage.apply_pattern(pattern="gable_fall")


def test_add_building_pattern_params_from_panel(blank):
    bpy = blank
    assert bpy.ops.damage.add_building(length=12, width=9, storeys=3, roof='gable', chimney=True) == {'FINISHED'}
    obj = bpy.context.active_object
    pg = obj.qs_building
    assert pg.building_id == 1 and pg.role == "BUILDING" and pg.shell_json
    pg.pattern = "roof_holes"
    pg.params.roof_holes__n_holes = 5
    pg.params.roof_holes__area_fraction = 0.1
    assert bpy.ops.damage.apply_pattern() == {'FINISHED'}
    prm = json.loads(pg.patterns_json)[-1]["params"]
    assert prm["area_fraction"] == pytest.approx(0.1, abs=0.01)
    assert bpy.ops.damage.apply_pattern(pattern="debris_heap", randomize=True) == {'FINISHED'}
    with pytest.raises(RuntimeError, match="already collapsed"):
        bpy.ops.damage.apply_pattern(pattern="roof_holes")
    assert bpy.ops.damage.reset_building() == {'FINISHED'}
    assert pg.patterns_json == "[]"
    assert bpy.ops.damage.apply_pattern(pattern="roof_holes") == {'FINISHED'}


def test_apply_grade_operator(blank):
    bpy = blank
    bpy.ops.damage.add_building(storeys=4, roof='flat', parapet_height=0.8, material='reinforced_concrete')
    obj = bpy.context.active_object
    obj.qs_building.grade = 5
    assert bpy.ops.damage.apply_grade() == {'FINISHED'}
    rec = json.loads(obj.qs_building.patterns_json)
    from addon import ems98
    assert any(5 in ems98.PATTERNS[r["name"]].grades for r in rec)


def test_make_post_scene_and_export_round_trip(blank, tmp_path):
    bpy = blank
    scene = bpy.context.scene
    for i, (g, roof, mat) in enumerate([(0, 'gable', 'masonry'), (3, 'gable', 'masonry'), (4, 'hip', 'masonry'),
                                        (5, 'flat', 'reinforced_concrete')]):
        bpy.context.scene.cursor.location = (i * 20.0, 0.0, 0.0)
        bpy.ops.damage.add_building(roof=roof, material=mat, storeys=3,
                                    parapet_height=0.6 if roof == 'flat' else 0.0)
        bpy.context.active_object.qs_building.grade = g
    from addon import scene_tools
    scene_tools.create_terrain_object(bpy.context.collection, -20, -20, 80, 20)
    sc = scene.qs_scene
    sc.export_dir = str(tmp_path / "pre")
    sc.epoch = "pre"
    sc.origin = "500000.25, 5000000.5, 120.0"
    sc.crs = "EPSG:32633"
    assert bpy.ops.damage.export_bundle() == {'FINISHED'}
    assert bpy.ops.damage.make_post_scene() == {'FINISHED'}
    post = bpy.data.collections[sc.post_collection]
    assert len([o for o in post.objects if o.qs_building.role == "BUILDING"]) == 4
    # the post collection must not be the source
    bpy.context.view_layer.active_layer_collection = bpy.context.view_layer.layer_collection.children[post.name]
    with pytest.raises(RuntimeError, match="post collection"):
        bpy.ops.damage.make_post_scene()
    sc.export_dir = str(tmp_path / "post")
    sc.epoch = "post"
    assert bpy.ops.damage.export_bundle() == {'FINISHED'}

    pre = read_scene(tmp_path / "pre")
    post = read_scene(tmp_path / "post")
    assert pre.epoch == "pre" and post.epoch == "post"
    assert pre.origin.tolist() == [500000.25, 5000000.5, 120.0] and pre.crs == "EPSG:32633"
    assert [b.id for b in pre.buildings] == [b.id for b in post.buildings] == [1, 2, 3, 4]
    assert [b.grade for b in post.buildings] == [0, 3, 4, 5]
    assert [b.grade for b in pre.buildings] == [0, 0, 0, 0]
    assert [b.extra.get("planned_grade") for b in pre.buildings] == [None, 3, 4, 5]
    assert post.buildings[0].patterns == [] and all(b.patterns for b in post.buildings[1:])
    assert post.buildings[3].material == "reinforced_concrete" and post.buildings[3].storeys == 3
    assert set(np.unique(post.face_building).tolist()) == {0, 1, 2, 3, 4}
    assert (post.face_surface[post.face_building == 0] == 0).all()
    assert (post.face_surface == 3).any()  # debris
    # building 1 (grade 0) is geometrically unchanged
    m1 = pre.face_building == 1
    assert np.allclose(np.sort(pre.vertices[np.unique(pre.faces[m1])], axis=0),
                       np.sort(post.vertices[np.unique(post.faces[post.face_building == 1])], axis=0))


def test_export_refuses_without_folder_or_buildings(blank, tmp_path):
    bpy = blank
    with pytest.raises(RuntimeError, match="export folder"):
        bpy.ops.damage.export_bundle()
    bpy.context.scene.qs_scene.export_dir = str(tmp_path / "x")
    with pytest.raises(RuntimeError, match="nothing to export"):
        bpy.ops.damage.export_bundle()
    with pytest.raises(RuntimeError, match="no building objects"):
        bpy.ops.damage.make_post_scene()


def test_a_pattern_applied_from_the_panel_keeps_its_draws_when_the_catalogue_grows(blank, monkeypatch):
    """The panel's random parameters are salted by the pattern's name, not its place in the
    catalogue: a pattern inserted before it changes nothing."""
    bpy = blank
    from addon import ems98, scene_tools

    def wall_holes():
        obj = _box(bpy, size=(16, 10, 12))
        _active(bpy, obj)
        bpy.ops.damage.assign_ids()
        return scene_tools.apply_pattern_to_object(obj, "wall_holes", randomize=True)

    first = wall_holes()
    monkeypatch.setattr(ems98, "PATTERN_NAMES", ("a_new_pattern",) + ems98.PATTERN_NAMES)
    assert wall_holes() == first
