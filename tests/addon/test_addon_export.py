"""io_export: the add-on's own PLY/JSON writer against the core reader (the contract)."""
import json

import numpy as np
import pytest

from addon import io_export
from quakescan.formats.scene import read_scene


def _box_city():
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0],  # ground
                  [2, 2, 0], [5, 2, 0], [5, 5, 3], [2, 5, 3]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    b = np.array([0, 0, 5, 5], np.int32)
    s = np.array([0, 0, 1, 1])
    recs = [{"id": 5, "grade": 4, "material": "masonry", "storeys": 2, "typology": "t",
             "patterns": [{"name": "roof_holes", "params": {"n_holes": 3}}], "seed": 9}]
    return v, f, b, s, recs


def test_bundle_round_trip(tmp_path):
    v, f, b, s, recs = _box_city()
    io_export.write_bundle(tmp_path / "s", v + [0.001, 0, 0], f, b, s, recs, epoch="post",
                           origin="600000.125 5100000.5 0", crs="EPSG:32632")
    sc = read_scene(tmp_path / "s")
    np.testing.assert_array_equal(sc.vertices, v + [0.001, 0, 0])  # doubles survive exactly
    np.testing.assert_array_equal(sc.faces, f)
    np.testing.assert_array_equal(sc.face_building, b)
    np.testing.assert_array_equal(sc.face_surface, s)
    assert sc.origin.tolist() == [600000.125, 5100000.5, 0.0]
    bld = sc.buildings[0]
    assert (bld.id, bld.grade, bld.material, bld.storeys, bld.seed) == (5, 4, "masonry", 2, 9)
    assert bld.patterns == recs[0]["patterns"]
    assert not list(tmp_path.glob("s/*.tmp")) and not list(tmp_path.glob("s/.*.part"))


def test_the_export_never_follows_a_planted_link_nor_writes_through_one(tmp_path):
    """Issue 45: a predictable temporary name (NAME.tmp) would let a link planted there send
    the bytes outside the folder; the export's temporary is exclusive and unguessable."""
    import os
    import stat

    v, f, b, s, _ = _box_city()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    out = tmp_path / "bundle"
    out.mkdir()
    (out / "mesh.ply.tmp").symlink_to(victim)
    (out / "scene.json.tmp").symlink_to(victim)
    io_export.write_ply(out / "mesh.ply", v, f, b, s)
    io_export.write_json(out / "scene.json", {"a": 1})
    assert victim.read_text() == "keep me"
    assert not (out / "mesh.ply").is_symlink() and json.loads((out / "scene.json").read_text()) == {"a": 1}
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((out / "mesh.ply").stat().st_mode) == 0o666 & ~umask
    assert sorted(p.name for p in out.iterdir()) == ["mesh.ply", "mesh.ply.tmp", "scene.json", "scene.json.tmp"]
    (out / "scene.json").unlink()
    (out / "scene.json").symlink_to(victim)
    with pytest.raises(OSError, match="is a symbolic link"):
        io_export.write_json(out / "scene.json", {"b": 2})
    assert victim.read_text() == "keep me"
    assert not list(out.glob(".*.part"))


def test_ply_header_is_the_contract(tmp_path):
    v, f, b, s, recs = _box_city()
    io_export.write_ply(tmp_path / "m.ply", v, f, b, s)
    raw = (tmp_path / "m.ply").read_bytes()
    head = raw[:raw.index(b"end_header")].decode()
    assert "format binary_little_endian 1.0" in head
    for line in ("property double x", "property list uchar int vertex_indices", "property int building_id",
                 "property uchar surface"):
        assert line in head
    assert len(raw) - raw.index(b"end_header\n") - 11 == 8 * 24 + 4 * (1 + 12 + 4 + 1)


@pytest.mark.parametrize("case, match", [
    ("nan", "NaN"), ("degenerate", "degenerate"), ("surface", "surface code 7"),
    ("missing", r"buildings \[6\] have no faces"), ("unknown", r"building IDs \[5\]"), ("epoch", "epoch"),
    ("origin", "origin"),
])
def test_invalid_bundles_are_refused(tmp_path, case, match):
    v, f, b, s, recs = _box_city()
    kw = {}
    if case == "nan":
        v[6, 2] = np.nan
    elif case == "degenerate":
        v[6] = v[5]
        v[7] = v[4]
    elif case == "surface":
        s = s.copy()
        s[2] = 7
    elif case == "missing":
        recs = recs + [dict(recs[0], id=6)]
    elif case == "unknown":
        recs = []
    elif case == "epoch":
        kw["epoch"] = "during"
    elif case == "origin":
        kw["origin"] = "1, 2"
    with pytest.raises(io_export.ExportError, match=match):
        io_export.write_bundle(tmp_path / "s", v, f, b, s, recs, **kw)
    assert not (tmp_path / "s" / "scene.json").exists()


def test_objects_export_drops_degenerate_and_uses_matrix(blank, tmp_path):
    bpy = blank
    from addon import scene_tools
    from addon.geometry.shell import ShellSpec, rect_footprint
    coll = bpy.context.collection
    spec = ShellSpec(rect_footprint(10, 6), storeys=2, storey_height=3.0, roof="flat")
    obj = scene_tools.create_building_object(coll, spec, 3, location=(100.0, 50.0, 0.0), rotation_z=np.pi / 2,
                                             grade=3)
    scene_tools.create_terrain_object(coll, 80, 30, 120, 70)
    # a degenerate polygon (three collinear vertices) must not reach the file
    bm = scene_tools.read_bmesh(obj)
    vs = [bm.verts.new(c) for c in ((0, 0, 20), (1, 0, 20), (2, 0, 20))]
    bm.faces.new(vs)
    scene_tools.write_bmesh(obj, bm)
    bm.free()
    rep = io_export.export_objects(tmp_path / "b", scene_tools.scene_objects(coll), epoch="post")
    assert rep["dropped_degenerate"] >= 1
    sc = read_scene(tmp_path / "b")
    bv = sc.vertices[np.unique(sc.faces[sc.face_building == 3])]
    # rotated 90 degrees about z at (100, 50): the 10 m side now runs along y
    assert bv[:, 0].max() - bv[:, 0].min() == pytest.approx(6.0, abs=1e-4)
    assert bv[:, 1].max() - bv[:, 1].min() == pytest.approx(10.0, abs=1e-4)
    assert bv[:, :2].mean(axis=0) == pytest.approx([100.0, 50.0], abs=1e-3)
    assert sc.buildings[0].grade == 3 and sc.buildings[0].id == 3
    manifest = json.loads((tmp_path / "b" / "scene.json").read_text())
    assert manifest["buildings"][0]["vulnerability_class"] == "B"


def test_building_without_faces_is_named(blank, tmp_path):
    bpy = blank
    from addon import scene_tools
    me = bpy.data.meshes.new("empty")
    obj = bpy.data.objects.new("empty_building", me)
    bpy.context.collection.objects.link(obj)
    obj.qs_building.role = "BUILDING"
    obj.qs_building.building_id = 4
    scene_tools.create_terrain_object(bpy.context.collection, 0, 0, 10, 10)
    with pytest.raises(io_export.ExportError, match=r"buildings \[4\] have no faces"):
        io_export.export_objects(tmp_path / "e", scene_tools.scene_objects(bpy.context.collection))
    obj.qs_building.building_id = 0
    with pytest.raises(io_export.ExportError, match="empty_building.*without an ID"):
        io_export.export_objects(tmp_path / "e", scene_tools.scene_objects(bpy.context.collection))
