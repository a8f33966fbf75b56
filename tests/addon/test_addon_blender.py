"""The add-on in a real Blender (Debian's `blender`, 3.4 LTS) when one is on PATH: it
registers from the repository and from an installed zip, its operators and panels run,
and the batch generator's bundles read back with the core and match the bpy module's.

Official Blender 3.4 builds embed Python 3.10 (Debian's links its system 3.11), so the
add-on and the Blender scripts must not use syntax newer than 3.10: checked without Blender.
"""
import ast
import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from conftest import BLENDER, HAVE_BPY, REPO

needs_blender = pytest.mark.skipif(BLENDER is None, reason="no blender binary on PATH")
GENERATE = REPO / "blender_scripts" / "generate_scenes.py"


def _sources():
    return sorted([*(REPO / "addon").rglob("*.py"), *(REPO / "blender_scripts").glob("*.py")])


def test_addon_and_scripts_parse_as_python_310():
    assert _sources()
    for p in _sources():
        ast.parse(p.read_text(), filename=str(p), feature_version=(3, 10))
        src = p.read_text()
        for name in ("tomllib", "StrEnum", "datetime.UTC", "ExceptionGroup", "TaskGroup", "add_note("):
            assert name not in src, f"{p.relative_to(REPO)} uses {name} (Python 3.11+; Blender 3.4 has 3.10)"


def _blender(args, tmp_path, timeout=300, env=None):
    """Run blender headless with a private user config/scripts folder; return stdout."""
    e = dict(os.environ)
    e.update(BLENDER_USER_CONFIG=str(tmp_path / "bl_config"), BLENDER_USER_SCRIPTS=str(tmp_path / "bl_scripts"))
    e.update(env or {})
    r = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", *args],
                       capture_output=True, text=True, timeout=timeout, env=e, check=False)
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    return r.stdout


def _result(stdout):
    lines = [ln for ln in stdout.splitlines() if ln.startswith("QS_RESULT ")]
    assert lines, stdout[-3000:]
    return json.loads(lines[-1][len("QS_RESULT "):])


# Registers the add-on from the repository, runs every operator of the panel in the
# authoring workflow, draws the panels into a stand-in layout, exports pre and post.
WORKFLOW = r"""
import json, sys
import bpy, bmesh
sys.path.insert(0, REPO)
import addon
from addon import scene_tools
addon.register()
out = {"version": bpy.app.version_string, "python": sys.version.split()[0]}
ops = bpy.ops.damage
out["operators"] = sorted(n for n in dir(ops) if not n.startswith("_"))
bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
C = bpy.context

class Layout:
    def __init__(s, calls): s.calls = calls
    def _child(s, *a, **k): return Layout(s.calls)
    row = column = box = split = _child
    def prop(s, data, name, **k):
        assert name in data.bl_rna.properties.keys(), name
        s.calls.append(name)
    def operator(s, idname, **k):
        mod, name = idname.split(".")
        assert name in dir(getattr(bpy.ops, mod)), idname
        s.calls.append(idname)
    def label(s, **k): s.calls.append(k.get("text"))
    def separator(s, **k): pass

def draw(panel):
    calls = []
    panel.draw(type("P", (), {"layout": Layout(calls)})(), C)
    return calls

res = {}
res["add_building"] = ops.add_building(roof='gable', chimney=True, storeys=3)
b1 = C.active_object
b1.qs_building.grade = 3
b1.qs_building.pattern = "roof_holes"
res["apply_pattern"] = ops.apply_pattern()
res["apply_grade"] = ops.apply_grade()
calls = draw(bpy.types.DAMAGE_PT_main) + draw(bpy.types.DAMAGE_PT_damage) + draw(bpy.types.DAMAGE_PT_scene)
out["panel_calls"] = calls
res["reset_building"] = ops.reset_building()
b1.qs_building.grade = 5
# a user mesh: a box made a building with Assign IDs, with an interior
me = bpy.data.meshes.new("box")
bm = bmesh.new()
bmesh.ops.create_cube(bm, size=1.0)
for v in bm.verts:
    v.co.x *= 10; v.co.y *= 8; v.co.z = (v.co.z + 0.5) * 9
bm.to_mesh(me); bm.free()
box = bpy.data.objects.new("box", me)
C.collection.objects.link(box)
box.location.x = 30.0
for o in C.selected_objects: o.select_set(False)
box.select_set(True); C.view_layer.objects.active = box
res["assign_ids"] = ops.assign_ids()
res["add_interior"] = ops.add_interior()
box.qs_building.grade = 4
scene_tools.create_terrain_object(C.collection, -20, -20, 60, 20)
sc = C.scene.qs_scene
sc.origin = "500000.25, 5000000.5, 120.0"
sc.crs = "EPSG:32633"
sc.export_dir = OUT + "/pre"; sc.epoch = "pre"
res["export_pre"] = ops.export_bundle()
res["make_post_scene"] = ops.make_post_scene()
post = bpy.data.collections[sc.post_collection]
C.view_layer.active_layer_collection = C.view_layer.layer_collection.children[post.name]
sc.export_dir = OUT + "/post"; sc.epoch = "post"
res["export_post"] = ops.export_bundle()
out["results"] = {k: sorted(v) for k, v in res.items()}
addon.unregister()
out["unregistered"] = not hasattr(bpy.types.Object, "qs_building")
print("QS_RESULT " + json.dumps(out))
"""


@needs_blender
def test_addon_registers_and_operators_run_in_blender(tmp_path):
    from addon import ems98
    from quakescan.formats.scene import read_scene
    expr = f"REPO = {str(REPO)!r}; OUT = {str(tmp_path)!r}\n" + WORKFLOW
    out = _result(_blender(["--python-expr", expr], tmp_path))
    assert set(out["operators"]) >= {"add_building", "assign_ids", "add_interior", "reset_building",
                                     "apply_pattern", "apply_grade", "make_post_scene", "export_bundle"}
    assert all(v == ["FINISHED"] for v in out["results"].values()), out["results"]
    assert "3: substantial to heavy" in out["panel_calls"] and "damage.export_bundle" in out["panel_calls"]
    assert out["unregistered"]
    pre, post = read_scene(tmp_path / "pre"), read_scene(tmp_path / "post")
    assert [b.id for b in pre.buildings] == [b.id for b in post.buildings] == [1, 2]
    assert [b.grade for b in pre.buildings] == [0, 0]
    assert [b.grade for b in post.buildings] == [5, 4]
    assert all(b.patterns and b.patterns[0]["name"] in ems98.PATTERNS for b in post.buildings)
    assert pre.origin.tolist() == [500000.25, 5000000.5, 120.0] and pre.crs == "EPSG:32633"
    assert set(np.unique(post.face_surface).tolist()) >= {0, 1, 2, 3}


INSTALL = r"""
import json, sys
import bpy
bpy.ops.preferences.addon_install(filepath=ZIP)
bpy.ops.preferences.addon_enable(module="quakescan_damage")
import addon_utils
loaded_default, loaded_state = addon_utils.check("quakescan_damage")
ok = bpy.ops.damage.add_building(storeys=2)
print("QS_RESULT " + json.dumps({"enabled": loaded_state, "add_building": sorted(ok),
      "id": bpy.context.active_object.qs_building.building_id,
      "module": bpy.types.DAMAGE_PT_main.__module__}))
"""


def _zip_addon(tmp_path):
    """docs/addon.md's zip: the addon/ folder as quakescan_damage/ (bl_info for Blender < 4.2,
    blender_manifest.toml for 4.2+ extensions)."""
    zpath = tmp_path / "quakescan_damage.zip"
    with zipfile.ZipFile(zpath, "w") as z:
        for p in sorted((REPO / "addon").rglob("*")):
            if p.is_file() and "__pycache__" not in p.parts:
                z.write(p, "quakescan_damage/" + p.relative_to(REPO / "addon").as_posix())
    return zpath


@needs_blender
def test_addon_installs_from_zip_in_blender(tmp_path):
    """What docs/addon.md tells a user of Blender < 4.2: Preferences > Add-ons > Install, enable."""
    zpath = _zip_addon(tmp_path)
    out = _result(_blender(["--python-expr", f"ZIP = {str(zpath)!r}\n" + INSTALL], tmp_path))
    assert out["enabled"] and out["add_building"] == ["FINISHED"] and out["id"] == 1
    assert out["module"].startswith("quakescan_damage")
    assert (tmp_path / "bl_scripts" / "addons" / "quakescan_damage" / "__init__.py").is_file()


EXTENSION = r"""
import json
import bpy
ok = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default", enable_on_install=True)
added = bpy.ops.damage.add_building(storeys=2)
print("QS_RESULT " + json.dumps({"install": sorted(ok), "add_building": sorted(added),
      "module": bpy.types.DAMAGE_PT_main.__module__}))
"""


@pytest.mark.skipif(not HAVE_BPY, reason="bpy module not installed")
def test_addon_installs_as_extension_with_bpy_module(tmp_path):
    """Blender 4.2+: the same zip installs as an extension (blender_manifest.toml)."""
    zpath = _zip_addon(tmp_path)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "res"))
    r = subprocess.run([sys.executable, "-c", f"ZIP = {str(zpath)!r}\n" + EXTENSION], capture_output=True,
                       text=True, timeout=300, env=env, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    out = _result(r.stdout)
    assert out["install"] == ["FINISHED"] and out["add_building"] == ["FINISHED"]
    assert out["module"].startswith("bl_ext.user_default.quakescan_damage")
    assert (tmp_path / "res" / "extensions" / "user_default" / "quakescan_damage" / "blender_manifest.toml").is_file()


def _area_table(scene):
    """{(building_id, surface): (total area, )} of a scene's triangles."""
    v, f = scene.vertices, scene.faces
    a = v[f[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - a, v[f[:, 2]] - a), axis=1)
    keys = scene.face_building.astype(np.int64) * 10 + scene.face_surface
    return {int(k): float(area[keys == k].sum()) for k in np.unique(keys)}


@needs_blender
@pytest.mark.skipif(not HAVE_BPY, reason="bpy module not installed")
def test_blender_generator_output_reads_back_and_matches_bpy_module(tmp_path):
    """`blender -b -P generate_scenes.py` and `python generate_scenes.py` give the same
    scenes: same manifests and vertices; only Blender's triangulation of n-gons may differ
    between versions (same area per building and surface)."""
    from quakescan.formats.scene import read_scene
    args = ["--set", "generic", "--dataset", "paper", "--buildings", "6", "--seed", "1"]
    _blender(["-P", str(GENERATE), "--", *args, "--out", str(tmp_path / "bl")], tmp_path)
    r = subprocess.run([sys.executable, str(GENERATE), *args, "--out", str(tmp_path / "py")],
                       capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("pre", "post_heavy", "post_extreme", "post_destruction"):
        a, b = read_scene(tmp_path / "bl" / name), read_scene(tmp_path / "py" / name)
        assert (tmp_path / "bl" / name / "scene.json").read_bytes() == (tmp_path / "py" / name / "scene.json").read_bytes()
        assert a.epoch == ("pre" if name == "pre" else "post") and [x.id for x in a.buildings] == list(range(1, 7))
        assert np.array_equal(a.vertices, b.vertices), name
        ta, tb = _area_table(a), _area_table(b)
        assert ta.keys() == tb.keys()
        for k in ta:
            assert ta[k] == pytest.approx(tb[k], rel=1e-9, abs=1e-9), (name, k)
