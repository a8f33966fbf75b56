"""Roof and facade details: every kind is built with the building's ID and the right surface
codes, the same seed gives the same mesh, plans without details are today's plans, every
kind survives every damage pattern without floating, and the city generator honours its
frequency table."""
import collections
import hashlib
import json
import math

import numpy as np
import pytest

from addon import building_details, city_plan, citygen

BID = 9


# --- plans (pure Python) ---------------------------------------------------------------------

def _plan_digest(plan):
    doc = json.dumps([[b.id, b.shell, b.location, b.rotation, b.vulnerability_class, b.seed, b.typology,
                       list(b.extent)] for b in plan.buildings] + [list(plan.bounds)], sort_keys=True)
    return hashlib.sha256(doc.encode()).hexdigest()


# digests of city_plan(set, 60, 5) without details: main at d8f8a0b (before details existed)
# with the walls another building covers marked as party walls (citygen.mark_covered_walls)
PLAN_DIGESTS = {"generic": "e53e798f15141ebd571fc8768307435ce420f5295567102af636dfdf4fe9a5ca",
                "region": "bb7dde2a1a40b7350d270c6cb6827aa6d211820b3764d9a0d9237da01e438aa1"}


# the generator version these plans belong to: new digests mean the generator draws other
# cities from the same settings, so GENERATOR_VERSION must change with them (else bundles
# made before are reused as if current)
PLAN_DIGESTS_GENERATOR_VERSION = 3


def test_new_plans_come_with_a_new_generator_version():
    from addon import generation, generation_spec, versions

    assert versions.GENERATOR_VERSION == PLAN_DIGESTS_GENERATOR_VERSION, (
        "the pinned plan digests belong to another generator version: bump addon/versions.py's "
        "GENERATOR_VERSION and PLAN_DIGESTS_GENERATOR_VERSION together when the plans change")
    job = generation_spec.GenerationSpec("generic", "mixed", 4, 1, "o").checked()
    assert generation.generator_info(job, "pre")["version"] == versions.GENERATOR_VERSION


@pytest.mark.parametrize("set_name", citygen.SETS)
def test_plans_without_details_are_unchanged(set_name):
    # sets made after details existed (small) are compared with their own plan without details
    digest = PLAN_DIGESTS.get(set_name) or _plan_digest(citygen.city_plan(set_name, 60, 5))
    assert _plan_digest(citygen.city_plan(set_name, 60, 5)) == digest
    assert _plan_digest(citygen.city_plan(set_name, 60, 5, details="none")) == digest
    # with details, everything but the details is the same plan
    typical = citygen.city_plan(set_name, 60, 5, details="typical")
    for b in typical.buildings:
        b.shell.pop("details")
    assert _plan_digest(typical) == digest


def test_details_argument_checked():
    with pytest.raises(ValueError, match="details must be one of"):
        citygen.city_plan("generic", 3, 0, details="lots")


@pytest.mark.parametrize("set_name", citygen.SETS)
def test_typical_details_are_seeded(set_name):
    a = citygen.city_plan(set_name, 40, 7, details="typical")
    b = citygen.city_plan(set_name, 40, 7, details="typical")
    c = citygen.city_plan(set_name, 40, 8, details="typical")
    assert [x.shell["details"] for x in a.buildings] == [x.shell["details"] for x in b.buildings]
    assert [x.shell["details"] for x in a.buildings] != [x.shell["details"] for x in c.buildings]


def _fits(entry, shell, typology):
    """DETAIL_FITS as a predicate (placement aside)."""
    pitched = shell["roof"] in ("gable", "hip") and len(shell["footprint"]) == 4
    flat = not pitched
    return {"overhang": pitched, "dormer": pitched, "chimney": not shell.get("chimney"),
            "rooftop_structure": flat, "hvac": flat, "terrace": pitched or shell["storeys"] >= 3,
            "balcony": shell["storeys"] >= 2, "parapet": flat and not shell.get("parapet_height")}.get(entry, True)


def _has(entry, details):
    kind = building_details.entry_kind(entry)
    return any(d["kind"] == kind and (entry != "hvac" or d.get("type") == "hvac")
               and (entry != "rooftop_structure" or d.get("type") == "stair") for d in details)


# entries whose placement can fail for want of room get a lower bound only
ROOM_LIMITED = {"annex", "dormer", "terrace", "solar_panels", "skylight"}


def test_frequency_table_is_honoured():
    counts = collections.defaultdict(lambda: [0, 0])  # (typology, entry) -> [fits, has]
    for set_name, n in (("generic", 700), ("region", 900), ("small", 900)):
        for seed in (1, 2):
            for b in citygen.city_plan(set_name, n, seed, details="typical").buildings:
                for entry, p in building_details.DETAIL_FREQUENCIES[b.typology].items():
                    if _fits(entry, b.shell, b.typology):
                        c = counts[(b.typology, entry)]
                        c[0] += 1
                        c[1] += _has(entry, b.shell["details"])
    checked = 0
    for (typ, entry), (n, k) in sorted(counts.items()):
        if n < 60:
            continue
        p = building_details.DETAIL_FREQUENCIES[typ][entry]
        f = k / n
        tol = 4 * math.sqrt(p * (1 - p) / n) + 0.02
        assert f <= p + tol, (typ, entry, f, p, n)
        assert f >= (p - tol if entry not in ROOM_LIMITED else 0.6 * p - tol), (typ, entry, f, p, n)
        checked += 1
    assert checked >= 40


def test_all_kinds_but_parapet_appear_in_typical_cities():
    kinds = set()
    for set_name in citygen.SETS:
        for b in citygen.city_plan(set_name, 120, 1, details="typical").buildings:
            kinds |= {d["kind"] for d in b.shell["details"]}
    from_table = {building_details.entry_kind(e) for e in building_details.DETAIL_ENTRIES}
    assert kinds == from_table - {"parapet"}  # plans give every flat roof a parapet already


def test_annexes_keep_clear_of_other_buildings():
    for set_name in citygen.SETS:
        plan = citygen.city_plan(set_name, 150, 4, details="typical")
        polys = [city_plan.world_polygon(b) for b in plan.buildings]
        owners = list(range(len(polys)))
        for k, b in enumerate(plan.buildings):
            for d in b.shell["details"]:
                if d["kind"] == "annex":
                    polys.append(building_details._annex_world(b, d))
                    owners.append(k)
        n = len(plan.buildings)  # attached buildings may touch; annexes keep clear
        for i in range(n, len(polys)):
            for j in range(len(polys)):
                if owners[i] != owners[j]:
                    assert building_details._clear(polys[i], polys[j], building_details.ANNEX_CLEARANCE - 1e-6), (i, j)


# --- geometry (bpy module) -------------------------------------------------------------------

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402

from addon import ems98  # noqa: E402
from addon.geometry import details as dt  # noqa: E402
from addon.geometry import mesh as gm  # noqa: E402
from addon.geometry import patterns as gp  # noqa: E402
from addon.geometry.common import PatternNotApplicable  # noqa: E402
from addon.geometry.shell import ShellSpec, build_shell, rect_footprint  # noqa: E402
from addon_measure import check_valid, tri_normals  # noqa: E402

PITCHED = [
    {"kind": "dormer", "edge": 0, "t": 4.0, "width": 2.0, "height": 1.4, "setback": 1.0, "roof": "gable"},
    {"kind": "dormer", "edge": 2, "t": 6.0, "width": 1.6, "height": 1.2, "setback": 1.0, "roof": "flat"},
    {"kind": "chimney", "x": -3.0, "y": 1.0, "size": 0.6, "height": 1.2},
    {"kind": "skylight", "edge": 0, "t": 8.5, "v": 2.0, "width": 0.8, "length": 1.2},
    {"kind": "overhang", "depth": 0.5},
    {"kind": "antenna", "x": 2.0, "y": -1.0, "type": "dish", "height": 1.0, "size": 0.8, "azimuth": -1.5},
    {"kind": "antenna", "x": -1.0, "y": 1.5, "type": "mast", "height": 2.5},
    {"kind": "solar_panels", "mode": "flush", "edge": 2, "u0": 0.8, "u1": 4.5, "v0": 0.8, "v1": 3.0},
    {"kind": "annex", "edge": 1, "t": 4.5, "width": 4.0, "depth": 3.0, "height": 2.5, "roof": "shed"},
    {"kind": "terrace", "mode": "altana", "x": 0.5, "y": 0.0, "sx": 2.5, "sy": 2.5},
    {"kind": "balcony", "edge": 0, "positions": [2.5], "storeys": [1, 2], "width": 2.0, "depth": 1.2},
]
FLAT = [
    {"kind": "parapet", "height": 0.5},
    {"kind": "rooftop_structure", "type": "stair", "x": -3.0, "y": 1.0, "sx": 3.0, "sy": 2.5, "height": 2.8},
    {"kind": "rooftop_structure", "type": "hvac", "x": 4.5, "y": -2.0, "sx": 1.5, "sy": 1.0, "height": 1.2},
    {"kind": "solar_panels", "mode": "rows", "x0": 0.0, "y0": -3.5, "x1": 3.5, "y1": 0.0, "tilt": 20.0,
     "depth": 1.0, "pitch": 1.8},
    {"kind": "skylight", "x": -4.0, "y": -2.5, "width": 1.0, "length": 1.0},
    {"kind": "terrace", "mode": "penthouse", "x0": -5.5, "y0": 2.0, "x1": -1.0, "y1": 4.0, "height": 2.8,
     "railing": True},
    {"kind": "chimney", "x": 4.0, "y": 3.0, "size": 0.5, "height": 1.0},
    {"kind": "antenna", "x": 1.0, "y": 3.0, "type": "mast", "height": 3.0},
    {"kind": "balcony", "edge": 1, "positions": [4.5], "storeys": [1, 2], "width": 2.5, "depth": 1.5},
    {"kind": "annex", "edge": 3, "t": 4.5, "width": 3.0, "depth": 2.5, "height": 2.4},
]


def showcase(roof, material="masonry"):
    details = FLAT if roof == "flat" else PITCHED
    if roof == "hip":  # clear of the hips, no altana
        details = [dict(d, t=6.0) if d["kind"] == "dormer" else d for d in details
                   if d["kind"] not in ("terrace", "skylight", "solar_panels")]
    return ShellSpec(footprint=rect_footprint(12, 9), storeys=3, storey_height=3.0, roof=roof, roof_pitch=40.0,
                     material=material, bay_width=4.5 if material != "masonry" else 0.0, details=details)


SHOWCASES = {"gable": lambda: showcase("gable"), "hip": lambda: showcase("hip"),
             "flat_rc": lambda: showcase("flat", "reinforced_concrete")}
KIND_PART = {"overhang": gm.P_OVERHANG, "balcony": gm.P_BALCONY, "annex": gm.P_ANNEX, "parapet": gm.P_PARAPET}


def built(spec):
    bm = bmesh.new()
    build_shell(bm, spec, BID)
    return bm


def _faces_of(bm, spec, index):
    lab = gm.Labels(bm)
    d = spec.details[index]
    part = KIND_PART.get(d["kind"], gm.P_DETAIL)
    if part == gm.P_DETAIL:
        return [f for f in bm.faces if f[lab.part] == part and f[lab.elem] == index], lab
    return [f for f in bm.faces if f[lab.part] == part], lab


@pytest.mark.parametrize("name", list(SHOWCASES))
def test_every_kind_is_built_with_id_and_surfaces(name):
    spec = SHOWCASES[name]()
    bm = built(spec)
    bm.normal_update()
    v, t, s, b, p = gm.arrays(bm)
    check_valid(v, t, s, b, BID)
    for index, d in enumerate(spec.details):
        faces, lab = _faces_of(bm, spec, index)
        assert faces, f"{d['kind']} made no faces"
        for f in faces:
            assert f[lab.bid] == BID
            if d["kind"] in ("balcony", "parapet"):
                assert f[lab.surface] == gm.WALL
            else:  # tops roof, vertical sides wall
                assert f[lab.surface] == (gm.ROOF if f.normal.z > 0.5 else gm.WALL), (d["kind"], tuple(f.normal))
        if d["kind"] != "annex":
            assert max(v_.co.z for f in faces for v_ in f.verts) > 3.0  # not on the ground
    # details never reach below the element they sit on: roof-top ones not below the eaves
    roof_top = [f for f in bm.faces if f[gm.Labels(bm).part] == gm.P_DETAIL]
    assert min(v_.co.z for f in roof_top for v_ in f.verts) >= spec.eave_height - 1e-6
    # outward normals: balconies, annexes and dormer fronts face away from the footprint
    n = tri_normals(v, t)
    c = v[t].mean(axis=1)
    side = np.isin(p, [gm.P_BALCONY, gm.P_ANNEX]) & (np.abs(n[:, 2]) < 0.1)
    from addon.geometry import poly2d
    outside = ~poly2d.contains(spec.poly, c[side][:, :2] + 0.01 * n[side][:, :2])
    assert outside.mean() > 0.6  # railings and walls away from the building (back slab sides excepted)


def test_kinds_cover_the_catalogue():
    built_kinds = {d["kind"] for d in FLAT + PITCHED}
    assert built_kinds == set(dt.KINDS)


def test_same_seed_same_mesh():
    plan = citygen.city_plan("generic", 12, 3, details="typical")
    meshes = []
    for _ in range(2):
        out = []
        for b in plan.buildings:
            bm = built(ShellSpec(**b.shell))
            out.append(gm.arrays(bm))
            bm.free()
        meshes.append(out)
    for a, b in zip(*meshes):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_spec_round_trip_and_old_specs_load():
    spec = showcase("gable")
    again = ShellSpec.from_json(spec.to_json())
    assert again.details == spec.details
    old = json.loads(spec.to_json())
    del old["details"]
    assert ShellSpec.from_json(json.dumps(old)).details == []
    a, b = built(spec), built(again)
    np.testing.assert_array_equal(gm.arrays(a)[0], gm.arrays(b)[0])


def test_details_that_do_not_fit_are_refused():
    with pytest.raises(dt.DetailError, match="slope"):
        built(ShellSpec(rect_footprint(12, 9), roof="gable", roof_pitch=30.0, details=[
            {"kind": "dormer", "edge": 0, "t": 4.0, "width": 2.0, "height": 3.0, "setback": 1.0}]))
    with pytest.raises(dt.DetailError, match="pitched"):
        built(ShellSpec(rect_footprint(12, 9), roof="flat", details=[{"kind": "overhang", "depth": 0.5}]))
    with pytest.raises(dt.DetailError, match="unknown detail kind"):
        built(ShellSpec(rect_footprint(12, 9), details=[{"kind": "gargoyle"}]))
    with pytest.raises(dt.DetailError, match="inside the footprint"):
        built(ShellSpec(rect_footprint(12, 9), details=[{"kind": "chimney", "x": 6.0, "y": 0, "size": 1,
                                                         "height": 1}]))


def _unit_bases(bm):
    lab = gm.Labels(bm)
    units = dt._components([f for f in bm.faces if f[lab.part] in dt.SETTLING_PARTS])
    return [min(v.co.z for f in u for v in f.verts) for u in units]


def _structure_top(bm):
    lab = gm.Labels(bm)
    faces = [f for f in bm.faces if f[lab.part] not in dt.DETAIL_PARTS | {gm.P_DEBRIS}]
    return max((v.co.z for f in faces for v in f.verts), default=0.0)


def _check_not_floating(bm, spec, rigid):
    """No detail left hanging: each detail piece's lowest point is at most 0.5 m above the
    highest remaining part of the building (and each still finds its element)."""
    top = _structure_top(bm)
    for zb in _unit_bases(bm):
        assert zb <= top + 0.5, f"a detail floats {zb - top:.2f} m above the building"
    if not rigid:  # rigid motions carry details along (their probes look straight down)
        lab = gm.Labels(bm)
        tree = dt._bvh([f for f in bm.faces if f[lab.part] not in dt.SETTLING_PARTS | {gm.P_DEBRIS, gm.P_ANNEX}])
        for unit in dt._components([f for f in bm.faces if f[lab.part] in dt.SETTLING_PARTS]):
            assert dt.supported(unit, tree, dt._probe_shift(spec, unit[0][lab.part], unit[0][lab.elem]))


@pytest.mark.parametrize("name", list(SHOWCASES))
@pytest.mark.parametrize("pattern", ems98.PATTERN_NAMES)
def test_every_kind_survives_every_pattern(name, pattern):
    spec = SHOWCASES[name]()
    grade = max(ems98.PATTERNS[pattern].grades)
    outs = []
    for _ in range(2):
        bm = built(spec)
        rng = np.random.default_rng(5)
        try:
            rec = gp.apply_pattern(bm, spec, pattern, ems98.sample_params(pattern, rng, grade, spec.material), rng, BID)
        except PatternNotApplicable:
            assert not ems98.requirements_met(pattern, spec.features())
            return
        v, t, s, b, p = gm.arrays(bm)
        check_valid(v, t, s, b, BID)
        assert set(np.unique(p).tolist()) <= set(gm.PART_NAMES)
        _check_not_floating(bm, spec, ems98.PATTERNS[pattern].stage == 3)
        outs.append((v, t, s, rec))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    assert outs[0][3] == outs[1][3]


def test_details_fall_with_their_roof():
    spec = showcase("flat", "reinforced_concrete")
    bm = built(spec)
    n0 = len(_unit_bases(bm))
    rec = gp.apply_pattern(bm, spec, "pancake_collapse", None, np.random.default_rng(1), BID)
    assert rec["params"]["details_fallen"] == n0 - len(_unit_bases(bm)) > 0
    lab = gm.Labels(bm)
    assert not [f for f in bm.faces if f[lab.part] == gm.P_DETAIL]  # the roof came down: nothing stays up
    # the intact upper block of a soft-storey collapse carries its details along
    bm = built(spec)
    rec = gp.apply_pattern(bm, spec, "soft_storey_collapse", dict(drop=2.8, tilt=0.0, offset=0.0,
                                                                  solid_fraction=0.15, bulking=1.5),
                           np.random.default_rng(1), BID)
    assert "details_fallen" not in rec["params"]
    assert len(_unit_bases(bm)) == n0


def test_buildings_without_details_are_untouched_by_settling():
    spec = showcase("gable")
    spec.details = []
    for pattern in ("partial_roof_collapse", "pancake_collapse"):
        a, b = built(spec), built(spec)
        ra = gp.apply_pattern(a, spec, pattern, None, np.random.default_rng(2), BID)
        assert dt.settle(b, spec, BID) == 0
        rb = gp.apply_pattern(b, spec, pattern, None, np.random.default_rng(2), BID)
        assert ra == rb and "details_fallen" not in ra["params"]


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_roof_details_on_a_mesh_without_spec(seed):
    spec = showcase("gable")
    spec.details = []
    bm = built(spec)
    n0 = len(bm.faces)
    kinds = dt.add_roof_details(bm, BID, seed, spec.storeys, min_area=4.0)
    again = built(spec)
    assert dt.add_roof_details(again, BID, seed, spec.storeys, min_area=4.0) == kinds
    np.testing.assert_array_equal(gm.arrays(bm)[0], gm.arrays(again)[0])
    lab = gm.Labels(bm)
    new = [f for f in bm.faces if f[lab.part] == gm.P_DETAIL]
    assert len(bm.faces) - n0 == len(new) and (len(new) > 0) == bool(kinds)
    assert all(f[lab.bid] == BID and f[lab.surface] in (gm.ROOF, gm.WALL) for f in new)
    for pattern in ("partial_roof_collapse", "top_storey_collapse", "roof_holes"):
        trial = bm.copy()
        gp.apply_pattern(trial, spec, pattern, None, np.random.default_rng(seed), BID)
        v, t, s, b, p = gm.arrays(trial)
        check_valid(v, t, s, b, BID)
        _check_not_floating(trial, spec, False)
        trial.free()


def test_roof_details_kinds_over_many_seeds():
    spec = showcase("flat")
    spec.details = []
    seen = collections.Counter()
    for seed in range(40):
        bm = built(spec)
        seen.update(dt.add_roof_details(bm, BID, seed, spec.storeys))
        bm.free()
    assert {"chimney", "antenna", "solar_panels", "rooftop_structure", "skylight"} <= set(seen)


# --- objects, grades, operator, generator ----------------------------------------------------

@pytest.mark.parametrize("set_name", citygen.SETS)
def test_every_grade_on_detailed_objects_exports(blank, set_name):
    from addon import io_export, scene_tools
    bpy = blank
    plan = citygen.city_plan(set_name, 10, 2, details="typical")
    coll = bpy.context.scene.collection
    for b in plan.buildings:
        src = scene_tools.create_building_object(coll, ShellSpec(**b.shell), b.id, location=(*b.location, 0.0),
                                                 rotation_z=b.rotation, vulnerability_class=b.vulnerability_class,
                                                 seed=b.seed)
        for g in range(6):
            obj = src.copy()
            obj.data = src.data.copy()
            coll.objects.link(obj)
            scene_tools.apply_grade_to_object(obj, g)
            v, f, bid, surf, recs, _ = io_export.collect([obj], epoch="post")
            io_export._validate(v, f, bid, surf, recs)
            bm = scene_tools.read_bmesh(obj)
            _check_not_floating(bm, ShellSpec(**b.shell), any(r["name"] in ("tilt", "overturn")
                                                              for r in json.loads(obj.qs_building.patterns_json)))
            bm.free()


def test_add_building_operator_details(blank):
    bpy = blank
    assert bpy.ops.damage.add_building(roof='gable', storeys=2, details='typical', details_seed=4) == {'FINISHED'}
    obj = bpy.context.active_object
    spec = ShellSpec.from_json(obj.qs_building.shell_json)
    assert spec.details and spec.typology == "detached_house"
    bare = json.loads(ShellSpec(**{**json.loads(spec.to_json()), "details": []}).to_json())
    again = building_details.draw_details(bare, "detached_house", 4)
    assert spec.details == again
    parts = np.empty(len(obj.data.polygons), np.int32)
    obj.data.attributes[gm.PART_LAYER].data.foreach_get("value", parts)
    assert np.isin(parts, list(dt.DETAIL_PARTS)).any()
    assert bpy.ops.damage.add_building(roof='flat', details='none') == {'FINISHED'}
    assert ShellSpec.from_json(bpy.context.active_object.qs_building.shell_json).details == []
    from addon.ui import _detail_kinds
    assert _detail_kinds(obj.qs_building.shell_json) == sorted({d["kind"] for d in spec.details})


def test_generator_details_flag(tmp_path, bpy_registered, capsys):
    import importlib.util

    from conftest import REPO
    from quakescan.formats.scene import read_scene
    sp = importlib.util.spec_from_file_location("generate_scenes", REPO / "blender_scripts" / "generate_scenes.py")
    gen = importlib.util.module_from_spec(sp)
    sp.loader.exec_module(gen)
    args = ["--set", "generic", "--dataset", "mixed", "--buildings", "6", "--seed", "2"]
    assert gen.main([*args, "--details", "typical", "--out", str(tmp_path / "d")]) == 0
    assert gen.main([*args, "--out", str(tmp_path / "n")]) == 0
    doc = json.loads((tmp_path / "d" / "pre" / "scene.json").read_text())
    assert doc["generator"]["details"] == "typical"
    assert "details" not in json.loads((tmp_path / "n" / "pre" / "scene.json").read_text())["generator"]
    d, n = read_scene(tmp_path / "d" / "pre"), read_scene(tmp_path / "n" / "pre")
    assert len(d.faces) > len(n.faces)
    # bundles made without details are not reused for details
    assert gen.main([*args, "--details", "typical", "--out", str(tmp_path / "n")]) == 1
    assert "other settings" in capsys.readouterr().err
    # imported shells get roof-top details too
    assert gen.main(["--set", "bundle", "--source", str(tmp_path / "n" / "pre"), "--dataset", "mixed", "--seed", "1",
                     "--details", "typical", "--out", str(tmp_path / "b")]) == 0
    assert len(read_scene(tmp_path / "b" / "pre").faces) > len(n.faces)


def test_the_librarys_generate_passes_details(monkeypatch, tmp_path):
    import subprocess
    from pathlib import Path

    from quakescan import generator
    seen = {}

    def fake_run(cmd, **kw):  # the job file exists while the generator runs
        seen["spec"] = json.loads(Path(cmd[cmd.index("--spec") + 1]).read_text())
        return subprocess.CompletedProcess(cmd, 0, "", "")
    monkeypatch.setattr(generator.subprocess, "run", fake_run)
    generator.generate(generator.GenerationSpec("generic", "mixed", 4, 1, tmp_path, details="typical"))
    assert seen["spec"]["details"] == "typical"
    generator.generate(generator.GenerationSpec("generic", "mixed", 4, 1, tmp_path))
    assert seen["spec"]["details"] == "none"


@pytest.mark.parametrize("party", [[], [1, 3]])
def test_overhang_closed_form_and_party_walls(party):
    from addon_measure import area
    o, pitch = 0.5, 40.0
    spec = ShellSpec(rect_footprint(12, 9), storeys=2, roof="gable", roof_pitch=pitch, party_walls=party,
                     details=[{"kind": "overhang", "depth": o}])
    v, t, s, b, p = gm.arrays(built(spec))
    mask = p == gm.P_OVERHANG
    top = mask & (s == gm.ROOF)
    cos = math.cos(math.radians(pitch))
    ends = 0.0 if party else 2 * o  # eaves run past the gable walls, verges beyond them
    assert area(v, t, top) == pytest.approx(2 * ((12 + ends) * o + (2 * o * 4.5 if not party else 0.0)) / cos)
    assert area(v, t, mask & (s == gm.WALL)) == pytest.approx(2 * (12 + ends) * 0.15)  # fascia boards
    xy = v[t[mask]].reshape(-1, 3)
    assert xy[:, 0].min() == pytest.approx(-6.0 - (o if not party else 0.0))  # nothing over a neighbour
    assert xy[:, 1].min() == pytest.approx(-4.5 - o)
    assert xy[:, 2].min() == pytest.approx(spec.eave_height - o * math.tan(math.radians(pitch)) - 0.15)
