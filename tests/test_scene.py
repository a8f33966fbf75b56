"""Scene bundle contract: round trip and every malformed input named in the error."""
import json
import struct

import numpy as np
import pytest

from quakescan.errors import SceneError
from quakescan.formats.ply import read_ply, write_ply
from quakescan.formats.scene import Building, read_scene, write_scene
from quakescan.formats.synthetic import box_city


@pytest.fixture
def bundle(tmp_path):
    scene = box_city(rows=1, cols=2, origin=(500000.25, 5000000.5, 100.0))
    return write_scene(scene, tmp_path / "s"), scene


def test_round_trip_is_exact(bundle):
    folder, scene = bundle
    back = read_scene(folder)
    np.testing.assert_array_equal(back.vertices, scene.vertices)
    np.testing.assert_array_equal(back.faces, scene.faces)
    np.testing.assert_array_equal(back.face_building, scene.face_building)
    np.testing.assert_array_equal(back.face_surface, scene.face_surface)
    np.testing.assert_array_equal(back.origin, scene.origin)
    assert [b.to_json() for b in back.buildings] == [b.to_json() for b in scene.buildings]


def test_ply_header_is_the_contract(bundle):
    folder, _ = bundle
    head = (folder / "mesh.ply").read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in head
    for line in ("property double x", "property list uchar int vertex_indices", "property int building_id",
                 "property uchar surface"):
        assert line in head


def test_polygons_are_fan_triangulated(tmp_path):
    # one quad, written by hand as another tool would
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
              "property int building_id\nproperty uchar surface\nend_header\n").encode()
    body = struct.pack("<12f", 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0) + struct.pack("<B4iiB", 4, 0, 1, 2, 3, 7, 1)
    (tmp_path / "m.ply").write_bytes(header + body)
    mesh = read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(mesh.building_id, [7, 7])
    np.testing.assert_array_equal(mesh.surface, [1, 1])


def test_mixed_polygon_sizes(tmp_path):
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty double x\nproperty double y\n"
              "property double z\nelement face 2\nproperty list uchar int vertex_indices\n"
              "property int building_id\nproperty uchar surface\nend_header\n").encode()
    v = struct.pack("<15d", 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 2, 0, 0)
    f = struct.pack("<B4iiB", 4, 0, 1, 2, 3, 1, 1) + struct.pack("<B3iiB", 3, 1, 4, 2, 2, 2)
    (tmp_path / "m.ply").write_bytes(header + v + f)
    mesh = read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    np.testing.assert_array_equal(mesh.building_id, [1, 1, 2])


def _rewrite_manifest(folder, **changes):
    m = json.loads((folder / "scene.json").read_text())
    m.update(changes)
    (folder / "scene.json").write_text(json.dumps(m))


def _rewrite_mesh(folder, fn):
    mesh = read_ply(folder / "mesh.ply")
    fn(mesh)
    write_ply(folder / "mesh.ply", mesh)


@pytest.mark.parametrize("case, expected", [
    ("no_manifest", "scene.json is missing"),
    ("no_mesh", "mesh file named in scene.json is missing"),
    ("bad_json", "not valid JSON"),
    ("format", "format is 'something-else'"),
    ("version", "version 99 is not supported"),
    ("epoch", "epoch must be one of"),
    ("origin", "origin must be three finite numbers"),
    ("grade", "grade must be an EMS-98 grade 0..5"),
    ("material", "material must be one of"),
    ("duplicate", "duplicate building IDs [1]"),
    ("extra_in_manifest", "buildings [99] have no faces"),
    ("missing_in_manifest", "faces carry building IDs [2]"),
    ("bad_index", "points at vertex"),
    ("nan", "NaN/inf coordinates"),
    ("degenerate", "degenerate faces"),
    ("surface", "surface code 9"),
    ("truncated", "file ends inside element"),
    ("ascii", "PLY format 'ascii' is not supported"),
])
def test_malformed_bundles_are_named(bundle, case, expected):
    folder, scene = bundle
    manifest = json.loads((folder / "scene.json").read_text())
    if case == "no_manifest":
        (folder / "scene.json").unlink()
    elif case == "no_mesh":
        (folder / "mesh.ply").unlink()
    elif case == "bad_json":
        (folder / "scene.json").write_text("{not json")
    elif case == "format":
        _rewrite_manifest(folder, format="something-else")
    elif case == "version":
        _rewrite_manifest(folder, version=99)
    elif case == "epoch":
        _rewrite_manifest(folder, epoch="during")
    elif case == "origin":
        _rewrite_manifest(folder, origin=[0, "x", 0])
    elif case == "grade":
        manifest["buildings"][0]["grade"] = 7
        _rewrite_manifest(folder, buildings=manifest["buildings"])
    elif case == "material":
        manifest["buildings"][0]["material"] = "wood"
        _rewrite_manifest(folder, buildings=manifest["buildings"])
    elif case == "duplicate":
        _rewrite_manifest(folder, buildings=manifest["buildings"] + [manifest["buildings"][0]])
    elif case == "extra_in_manifest":
        _rewrite_manifest(folder, buildings=manifest["buildings"] + [dict(manifest["buildings"][0], id=99)])
    elif case == "missing_in_manifest":
        _rewrite_manifest(folder, buildings=manifest["buildings"][:1])
    elif case == "bad_index":
        _rewrite_mesh(folder, lambda m: m.faces.__setitem__((3, 1), 10_000))
    elif case == "nan":
        _rewrite_mesh(folder, lambda m: m.vertices.__setitem__((2, 0), np.nan))
    elif case == "degenerate":
        _rewrite_mesh(folder, lambda m: m.faces.__setitem__(5, [m.faces[5, 0]] * 3))
    elif case == "surface":
        _rewrite_mesh(folder, lambda m: m.surface.__setitem__(4, 9))
    elif case == "truncated":
        raw = (folder / "mesh.ply").read_bytes()
        (folder / "mesh.ply").write_bytes(raw[: len(raw) // 2])
    elif case == "ascii":
        (folder / "mesh.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(SceneError) as err:
        read_scene(folder)
    msg = str(err.value)
    assert expected in msg
    assert str(folder) in msg  # names the file


def test_missing_folder(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        read_scene(tmp_path / "nope")


def test_write_is_validated(tmp_path):
    scene = box_city(rows=1, cols=1)
    scene.buildings.append(Building(5))
    with pytest.raises(SceneError, match=r"buildings \[5\] have no faces"):
        write_scene(scene, tmp_path / "s")
    assert not (tmp_path / "s" / "scene.json").exists()


def test_extra_building_keys_survive(tmp_path):
    scene = box_city(rows=1, cols=1)
    scene.buildings[0].extra["source_id"] = "NL.IMBAG.Pand.1"
    scene.buildings[0].patterns = [{"name": "roof_holes", "params": {"count": 3}}]
    back = read_scene(write_scene(scene, tmp_path / "s"))
    assert back.buildings[0].extra == {"source_id": "NL.IMBAG.Pand.1"}
    assert back.buildings[0].patterns == [{"name": "roof_holes", "params": {"count": 3}}]
