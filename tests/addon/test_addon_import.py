"""addon/io_import.py (scene bundle → Blender objects → bundle) and
`generate_scenes.py --set bundle`, through the bpy module. Only the tests import quakescan."""
import hashlib
import importlib.util
import json
import struct
import subprocess
import sys

import numpy as np
import pytest
from conftest import HAVE_BPY, REPO

pytestmark = pytest.mark.skipif(not HAVE_BPY, reason="bpy module not installed")

SCRIPT = REPO / "blender_scripts" / "generate_scenes.py"
DATA = REPO.parent / "shared" / "data"  # the shared data folder beside the repository
ROTTERDAM = DATA / "rotterdam_subset.json"
UTM = (500123.123456789, 5000456.987654321, 12.345678901)


def _gen():
    spec = importlib.util.spec_from_file_location("generate_scenes_import_test", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _canon(s):
    """Faces as sorted rows (building, surface, 9 coordinates starting at the smallest corner):
    independent of vertex order and of how faces are spread over objects."""
    c = s.vertices[s.faces]  # (m, 3, 3)
    rows = []
    for corners, b, su in zip(c, s.face_building, s.face_surface):
        k = min(range(3), key=lambda i: tuple(corners[i]))
        rows.append((float(b), float(su), *np.roll(corners, -k, axis=0).ravel()))
    a = np.array(rows, dtype=np.float64).reshape(-1, 11)
    return a[np.lexsort(a.T[::-1])]


def _roundtrip(bpy, src_scene, tmp_path):
    from addon import io_import, scene_tools
    from quakescan.formats.scene import read_scene, write_scene
    write_scene(src_scene, tmp_path / "src")
    coll = bpy.data.collections.new("imported")
    bpy.context.scene.collection.children.link(coll)
    info = io_import.import_bundle(tmp_path / "src", coll, scene=bpy.context.scene)
    assert [o.qs_building.building_id for o in info["buildings"]] == [b.id for b in src_scene.buildings]
    for o, b in zip(info["buildings"], src_scene.buildings):
        assert o.data.attributes["qs_building_id"].domain == 'FACE'
        assert {d.value for d in o.data.attributes["qs_building_id"].data} == {b.id}
        assert (o.qs_building.material, o.qs_building.storeys) == (b.material, b.storeys)
    assert info["terrain"] is not None and info["terrain"].qs_building.role == "TERRAIN"
    sc = bpy.context.scene.qs_scene
    assert sc.crs == (src_scene.crs or "")
    # the scene's export settings give back the same float64 origin
    origin = [float(x) for x in sc.origin.split(",")]
    assert origin == [float(x) for x in src_scene.origin]
    io_import.export_bundle(tmp_path / "out", scene_tools.scene_objects(coll), epoch=src_scene.epoch,
                            origin=sc.origin, crs=sc.crs or None)
    back = read_scene(tmp_path / "out")
    a, b = _canon(src_scene), _canon(back)
    assert a.shape == b.shape
    assert np.array_equal(a[:, :2], b[:, :2])  # building IDs and surface labels
    assert np.abs(a[:, 2:] - b[:, 2:]).max() <= 1e-9
    assert back.origin.tolist() == src_scene.origin.tolist() and back.crs == src_scene.crs
    assert [(x.id, x.grade, x.material, x.storeys, x.typology) for x in back.buildings] == \
        [(x.id, x.grade, x.material, x.storeys, x.typology) for x in src_scene.buildings]
    return back


def test_roundtrip_box_city_at_utm(blank, tmp_path):
    from quakescan.formats.synthetic import box_city
    s = box_city(2, 3, height=(6.0, 9.5, 13.7), origin=UTM)
    s.crs = "EPSG:32633"
    # irregular float64 offsets that float32 cannot hold
    s.vertices = s.vertices + np.array([0.123456789012, -0.98765432101, 0.5555555555])
    _roundtrip(blank, s, tmp_path)


def test_roundtrip_rotterdam_cityjson(blank, tmp_path):
    if not ROTTERDAM.is_file():
        pytest.skip(f"{ROTTERDAM} not available (shared data folder absent)")
    from quakescan.formats.cityjson import import_cityjson
    s = import_cityjson(ROTTERDAM)
    back = _roundtrip(blank, s, tmp_path)
    assert [b.extra.get("source_id") for b in back.buildings] == [b.extra.get("source_id") for b in s.buildings]


def _write_ply(path, verts, faces, bids, surfs):
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(verts)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
            "property int building_id\nproperty uchar surface\nend_header\n").encode()
    body = b"".join(struct.pack("<3d", *v) for v in verts)
    body += b"".join(struct.pack("<B", len(f)) + struct.pack(f"<{len(f)}i", *f) + struct.pack("<iB", b, s)
                     for f, b, s in zip(faces, bids, surfs))
    path.write_bytes(head + body)


def _manifest(folder, ids, **kw):
    m = {"format": "quakescan-scene", "version": 1, "epoch": "pre", "origin": [1.5, 2.5, 0.0], "crs": None,
         "units": "m", "mesh": "mesh.ply", "buildings": [{"id": i, "storeys": 1} for i in ids]}
    m.update(kw)
    (folder / "scene.json").write_text(json.dumps(m))


def test_polygons_import_and_export_as_triangles(blank, tmp_path):
    from addon import io_import, scene_tools
    from quakescan.formats.scene import read_scene
    src = tmp_path / "poly"
    src.mkdir()
    v = [(0, 0, 0), (4, 0, 0), (4, 3, 0), (0, 3, 0), (0, 0, 3), (4, 0, 3), (4, 3, 3), (0, 3, 3),
         (-9, -9, 0), (9, -9, 0), (9, 9, 0), (-9, 9, 0)]
    f = [(4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (8, 9, 10, 11)]
    _write_ply(src / "mesh.ply", v, f, [7] * 5 + [0], [1, 2, 2, 2, 2, 0])
    _manifest(src, [7])
    coll = blank.data.collections.new("c")
    blank.context.scene.collection.children.link(coll)
    info = io_import.import_bundle(src, coll)
    assert len(info["buildings"][0].data.polygons) == 5
    assert all(len(p.vertices) == 4 for p in info["buildings"][0].data.polygons)
    io_import.export_bundle(tmp_path / "out", scene_tools.scene_objects(coll), origin=info["origin"])
    back = read_scene(tmp_path / "out")
    assert len(back.faces) == 12 and back.origin.tolist() == [1.5, 2.5, 0.0]
    assert sorted(np.bincount(back.face_surface).tolist()) == [2, 2, 8]


def test_malformed_bundles_name_the_file(blank, tmp_path):
    from addon import io_import
    coll = blank.data.collections.new("c")
    with pytest.raises(io_import.BundleError, match="does not exist"):
        io_import.import_bundle(tmp_path / "nope", coll)
    d = tmp_path / "bad"
    d.mkdir()
    v = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    _write_ply(d / "mesh.ply", v, [(0, 1, 2)], [1], [1])
    _manifest(d, [1])
    raw = (d / "mesh.ply").read_bytes()
    (d / "mesh.ply").write_bytes(raw[:-4])
    with pytest.raises(ValueError, match=r"mesh\.ply.*ends inside"):
        io_import.import_bundle(d, coll)
    _write_ply(d / "mesh.ply", v, [(0, 1, 5)], [1], [1])
    with pytest.raises(ValueError, match=r"mesh\.ply: face 0 points at vertex"):
        io_import.import_bundle(d, coll)
    _write_ply(d / "mesh.ply", v, [(0, 1, 2)], [2], [1])
    with pytest.raises(ValueError, match=r"mesh\.ply: faces carry building IDs \[2\]"):
        io_import.import_bundle(d, coll)
    (d / "mesh.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(ValueError, match=r"mesh\.ply: PLY format must be binary_little_endian"):
        io_import.import_bundle(d, coll)
    (d / "scene.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"scene\.json: not a readable JSON"):
        io_import.import_bundle(d, coll)
    assert not list(coll.objects)


def _digest(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A source bundle: the Rotterdam CityJSON subset when available, else a box city at UTM."""
    from quakescan.formats.scene import write_scene
    folder = tmp_path_factory.mktemp("src") / "bundle"
    if ROTTERDAM.is_file():
        from quakescan.formats.cityjson import import_cityjson
        s = import_cityjson(ROTTERDAM)
    else:
        from quakescan.formats.synthetic import box_city
        s = box_city(3, 3, height=(6.0, 9.0, 15.0), origin=UTM)
    s.crs = s.crs or "EPSG:28992"
    write_scene(s, folder)
    return folder, s


def test_generate_bundle_paper(bpy_registered, source, tmp_path, capsys):
    from quakescan.formats.scene import read_scene
    gen = _gen()
    src, s = source
    argv = ["--set", "bundle", "--source", str(src), "--dataset", "paper", "--buildings", "4", "--seed", "5"]
    assert gen.main(argv + ["--out", str(tmp_path / "a")]) == 0
    pre = read_scene(tmp_path / "a" / "pre")
    assert len(pre.buildings) == 4 and set(pre.building_ids) <= set(s.building_ids)
    assert pre.origin.tolist() == s.origin.tolist() and pre.crs == s.crs
    assert all(b.grade == 0 for b in pre.buildings)
    # the pre scene keeps the source's roofs exactly (float64), walls are only split at storeys
    ids = pre.building_ids
    src_roof = _canon(_subset(s, ids, surface=1))
    pre_roof = _canon(_subset(pre, ids, surface=1))
    assert src_roof.shape == pre_roof.shape and np.abs(src_roof - pre_roof).max() <= 1e-9
    for name, grade in (("post_heavy", 3), ("post_extreme", 4), ("post_destruction", 5)):
        post = read_scene(tmp_path / "a" / name)
        assert post.epoch == "post" and post.origin.tolist() == s.origin.tolist() and post.crs == s.crs
        assert post.building_ids.tolist() == ids.tolist()
        for b in post.buildings:
            assert b.grade == grade and b.patterns, (name, b.id)
            fa, fb = pre.face_building == b.id, post.face_building == b.id
            ba = np.ptp(pre.vertices[np.unique(pre.faces[fa])], axis=0)
            bb = np.ptp(post.vertices[np.unique(post.faces[fb])], axis=0)
            assert fa.sum() != fb.sum() or not np.allclose(ba, bb), (name, b.id)
        # terrain unchanged
        assert (post.face_building == 0).sum() == (pre.face_building == 0).sum()
    # same seed → same bytes; resume skips everything
    assert gen.main(argv + ["--out", str(tmp_path / "b")]) == 0
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    capsys.readouterr()
    assert gen.main(argv + ["--out", str(tmp_path / "a")]) == 0
    assert "nothing to do" in capsys.readouterr().err
    # another seed samples/damages differently and is refused in the same folder without --force
    assert gen.main(argv[:-1] + ["6", "--out", str(tmp_path / "a")]) == 1


def _subset(s, ids, surface):
    from quakescan.formats.scene import Scene
    keep = np.isin(s.face_building, ids) & (s.face_surface == surface)
    return Scene(s.vertices, s.faces[keep], s.face_building[keep], s.face_surface[keep], [], origin=s.origin)


def test_generate_bundle_mixed_all_buildings(bpy_registered, source, tmp_path):
    from quakescan.formats.scene import read_scene
    src, s = source
    assert _gen().main(["--set", "bundle", "--source", str(src), "--dataset", "mixed", "--seed", "2",
                        "--out", str(tmp_path / "m")]) == 0
    pre, post = read_scene(tmp_path / "m" / "pre"), read_scene(tmp_path / "m" / "post")
    assert pre.building_ids.tolist() == post.building_ids.tolist() == s.building_ids.tolist()
    info = json.loads((tmp_path / "m" / "post" / "scene.json").read_text())["generator"]
    assert info["set"] == "bundle" and len(info["source"]["sha256"]) == 64


def test_generate_bundle_bad_source(bpy_registered, tmp_path, capsys):
    gen = _gen()
    base = ["--set", "bundle", "--dataset", "paper", "--out", str(tmp_path / "o")]
    assert gen.main(base + ["--source", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        gen.main(["--set", "bundle", "--dataset", "paper", "--out", "x"])
    assert e.value.code == 2
    assert not (tmp_path / "o").exists()


def test_generate_bundle_malformed_ply_as_script(tmp_path):
    d = tmp_path / "bad"
    d.mkdir()
    _manifest(d, [1])
    (d / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
                                 b"property double x\nproperty double y\nproperty double z\n"
                                 b"element face 1\nproperty list uchar int vertex_indices\n"
                                 b"property int building_id\nproperty uchar surface\nend_header\n" + b"\0" * 10)
    r = subprocess.run([sys.executable, str(SCRIPT), "--set", "bundle", "--source", str(d), "--dataset", "mixed",
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode != 0
    assert "mesh.ply" in r.stderr and "ends inside the vertex data" in r.stderr
    assert not (tmp_path / "o").exists()


def test_generate_bundle_from_an_addon_scene_with_interiors(bpy_registered, tmp_path):
    """A pre scene written by the generator itself (slabs and inner walls present) as source."""
    from quakescan.formats.scene import INTERIOR, read_scene
    gen = _gen()
    assert gen.main(["--set", "generic", "--dataset", "mixed", "--buildings", "3", "--seed", "1",
                     "--out", str(tmp_path / "g")]) == 0
    assert gen.main(["--set", "bundle", "--source", str(tmp_path / "g" / "pre"), "--dataset", "paper",
                     "--out", str(tmp_path / "b")]) == 0
    pre = read_scene(tmp_path / "b" / "pre")
    src = read_scene(tmp_path / "g" / "pre")
    # interiors are not doubled
    assert (pre.face_surface == INTERIOR).sum() == (src.face_surface == INTERIOR).sum()
    assert [b.grade for b in read_scene(tmp_path / "b" / "post_extreme").buildings] == [4, 4, 4]


def test_unreadable_extra_keys_refuse_export(blank, tmp_path):
    """An imported building's extra keys that no longer parse are not dropped silently."""
    from addon import io_export, io_import, scene_tools
    from quakescan.formats.scene import write_scene
    from quakescan.formats.synthetic import box_city
    write_scene(box_city(1, 1), tmp_path / "src")
    coll = blank.data.collections.new("imported")
    blank.context.scene.collection.children.link(coll)
    info = io_import.import_bundle(tmp_path / "src", coll, scene=blank.context.scene)
    obj = info["buildings"][0]
    obj[io_import.EXTRA_PROP] = "{not json"
    with pytest.raises(io_export.ExportError, match="is not a JSON object"):
        io_import.export_bundle(tmp_path / "out", scene_tools.scene_objects(coll))
    assert not (tmp_path / "out" / "scene.json").exists()
