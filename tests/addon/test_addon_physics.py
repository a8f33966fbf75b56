"""Collapse by physics (addon/physics.py) through the bpy module: triggers, the rigid-body
settling, labels, determinism, the operator and the generator's --damage option."""
import json
import subprocess
import sys

import numpy as np
import pytest

from tests.addon.conftest import REPO

pytestmark = pytest.mark.slow  # rigid-body simulations: seconds each


def _city(bpy, storeys=2, neighbour=True):
    from addon import scene_tools
    from addon.geometry.shell import ShellSpec, rect_footprint
    coll = bpy.data.collections.new("city")
    bpy.context.scene.collection.children.link(coll)
    spec = ShellSpec(footprint=rect_footprint(8, 6), storeys=storeys, storey_height=3.0, roof="flat")
    a = scene_tools.create_building_object(coll, spec, 1, location=(20.0, 10.0, 0.0), rotation_z=0.4, seed=3)
    b = None
    if neighbour:
        b = scene_tools.create_building_object(coll, spec, 2, location=(20.0, 18.0, 0.0), seed=4)
    return coll, spec, a, b


def _mesh(obj):
    from addon import scene_tools
    from addon.geometry import mesh as gm
    bm = scene_tools.read_bmesh(obj)
    try:
        return gm.arrays(bm)
    finally:
        bm.free()


def _top_heights(verts, tris, spec, cell=0.25):
    """Highest surface over each cell of the footprint (building frame), from points sampled
    on every triangle at a quarter of the cell size (large faces cover many cells)."""
    x0, y0, x1, y1 = spec.bbox
    nx, ny = int(round((x1 - x0) / cell)), int(round((y1 - y0) / cell))
    top = np.zeros((nx, ny))
    for t in tris:
        a, b, c = verts[t]
        n = max(1, int(np.ceil(max(np.linalg.norm(b - a), np.linalg.norm(c - b), np.linalg.norm(a - c)) / (cell / 4))))
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
        keep = i + j <= n
        u, v = i[keep] / n, j[keep] / n
        p = a + u[:, None] * (b - a) + v[:, None] * (c - a)
        ix = np.floor((p[:, 0] - x0) / cell).astype(int)
        iy = np.floor((p[:, 1] - y0) / cell).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        np.maximum.at(top, (ix[ok], iy[ok]), p[ok, 2])
    return top


def test_grade5_total_collapse_lies_low_and_the_grade0_neighbour_keeps_its_mesh(blank):
    from addon import physics
    from addon.geometry import mesh as gm
    bpy = blank
    coll, spec, a, b = _city(bpy)
    before = _mesh(b)
    rec = physics.collapse_object(a, 5, mode="everything", colliders=[b])
    assert rec["name"] == physics.PATTERN_NAME and rec["params"]["mode"] == "everything"
    assert rec["params"]["seed"] == 3
    verts, tris, surf, bid, part = _mesh(a)
    top = _top_heights(verts, tris, spec)
    assert (top < 0.4 * spec.height).mean() >= 0.8
    assert (bid == 1).all() and (surf == gm.DEBRIS).mean() > 0.9
    after = _mesh(b)
    assert all(np.array_equal(x, y) for x, y in zip(before, after))
    assert json.loads(a.qs_building.patterns_json)[-1]["name"] == physics.PATTERN_NAME
    assert a.qs_building.grade == 5
    # the temporary simulation scene and its objects are gone
    assert [s.name for s in bpy.data.scenes] == [bpy.context.scene.name]
    assert not [o for o in bpy.data.objects if o.name.startswith("qs_")]


def test_grade4_corner_leaves_the_rest_standing(blank):
    from addon import physics
    from addon.geometry import mesh as gm
    coll, spec, a, _ = _city(blank, neighbour=False)
    rec = physics.collapse_object(a, 4, mode="corner")
    p = rec["params"]
    assert p["shards"] > 0 and p["debris_shards"] > 0
    verts, tris, surf, bid, part = _mesh(a)
    # the part outside the zone stands: roof faces at full height remain
    roof_z = verts[tris[surf == gm.ROOF]][:, :, 2]
    assert roof_z.size and np.isclose(roof_z.max(), spec.height)
    top = _top_heights(verts, tris, spec)
    lowered = (top < spec.height - 0.5).mean()  # the corner above the failed storey came down
    assert 0.05 < lowered < 0.8


@pytest.mark.parametrize("source", ["shell", "mesh"])
def test_same_seed_same_bytes(blank, source):
    from addon import physics
    bpy = blank
    out = []
    for _ in range(2):
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        if source == "shell":
            _, _, a, _ = _city(bpy, neighbour=False)
        else:
            a = _l_object(bpy)
        rec = physics.collapse_object(a, 5, mode="ground_storey")
        assert rec["params"]["element_source"] == source
        v, t, s, b, p = _mesh(a)
        out.append((v.tobytes(), t.tobytes(), s.tobytes(), rec))
    assert out[0] == out[1]


def test_lower_grades_are_refused_and_the_object_is_unchanged(blank):
    from addon import physics, scene_tools
    _, _, a, _ = _city(blank, neighbour=False)
    before = _mesh(a)
    with pytest.raises(scene_tools.DamageError, match="grades 4 and 5"):
        physics.collapse_object(a, 3)
    assert all(np.array_equal(x, y) for x, y in zip(before, _mesh(a)))


def test_unsettled_simulation_is_not_written(blank, monkeypatch):
    from addon import physics, scene_tools
    _, _, a, _ = _city(blank, neighbour=False)
    before = _mesh(a)
    with pytest.raises(scene_tools.DamageError, match="did not settle"):
        physics.collapse_object(a, 5, mode="everything", settle_steps=10)  # 0.4 s: still falling
    assert all(np.array_equal(x, y) for x, y in zip(before, _mesh(a)))
    assert a.qs_building.patterns_json == "[]"


def test_a_creeping_pile_stops_early_once_few_shards_move_fast(blank, monkeypatch):
    """From EARLY_STOP_STEPS on, the simulation ends as soon as the shards that moved
    CREEP_DRIFT or more within the last second hold at most EARLY_STOP_SHARE of the volume:
    the same collapse stepped to the limit takes every frame and is no closer to rest."""
    from addon import physics
    early = physics.EARLY_STOP_STEPS
    out = []
    for stop in (early, 10 ** 6):  # the second: no early stop
        blank.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        _, _, a, _ = _city(blank, neighbour=False)
        monkeypatch.setattr(physics, "EARLY_STOP_STEPS", stop)
        out.append(physics.collapse_object(a, 5, mode="everything")["params"])
    p, q = out
    assert not p["settled"] and early < p["frames"] < p["settle_steps"] + 1
    assert p["unsettled_volume_share"] <= physics.EARLY_STOP_SHARE
    assert not q["settled"] and q["frames"] == q["settle_steps"] + 1


def test_operator_button_and_apply_grade_option(blank):
    from addon import physics
    bpy = blank
    _, _, a, b = _city(bpy)
    bpy.context.view_layer.objects.active = a
    assert bpy.ops.damage.collapse_by_physics(grade=5) == {'FINISHED'}
    assert json.loads(a.qs_building.patterns_json)[-1]["name"] == physics.PATTERN_NAME
    with pytest.raises(RuntimeError, match="already damaged"):
        bpy.ops.damage.collapse_by_physics(grade=5)
    b.qs_building.grade = 4
    for o in bpy.context.view_layer.objects:
        o.select_set(o is b)
    bpy.context.view_layer.objects.active = b
    assert bpy.ops.damage.apply_grade(method="physics") == {'FINISHED'}
    assert json.loads(b.qs_building.patterns_json)[-1]["name"] == physics.PATTERN_NAME


def test_generator_damage_physics_records_the_collapse(tmp_path):
    out = tmp_path / "city"
    r = subprocess.run([sys.executable, str(REPO / "blender_scripts" / "generate_scenes.py"), "--set", "generic",
                        "--dataset", "mixed", "--grade-mix", "0:1,5:1", "--seed", "2", "--damage", "physics",
                        "--out", str(out)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    post = json.loads((out / "post" / "scene.json").read_text())
    assert post["generator"]["damage"] == "physics"
    by_grade = {b["grade"]: b for b in post["buildings"]}
    names = [p["name"] for p in by_grade[5]["patterns"]]
    assert names == ["physics_collapse"] or "gets the patterns instead" in r.stderr
    if names == ["physics_collapse"]:
        assert by_grade[5]["patterns"][0]["params"]["seed"] == by_grade[5]["seed"]
    assert by_grade[0]["patterns"] == []
    pre = json.loads((out / "pre" / "scene.json").read_text())
    assert "damage" in pre["generator"]  # a patterns-only run would not reuse these bundles


def test_neighbours_are_colliders_as_they_stand_when_the_collapses_start(blank):
    from addon import physics, post_scene, scene_tools
    coll, spec, a, b = _city(blank)
    terrain = scene_tools.create_terrain_object(coll, 0.0, 0.0, 40.0, 30.0)
    objs = list(coll.objects)
    # a neighbour that keeps the patterns is a collider as it was, the terrain too
    got = post_scene.PhysicsColliders(objs, {1: 5, 2: 3}, "physics").of(a)
    assert b in got and terrain in got and a not in got
    # one that collapses too: only what stands outside its own zone (nothing at grade 5)
    co, polys = [c for c in post_scene.PhysicsColliders(objs, 5, "physics").of(a) if isinstance(c, tuple)][0]
    assert len(polys) == 0
    co, polys = physics.standing_part(b, 4, mode="corner")
    whole = physics._world_arrays(b)
    # its standing part lost the corner of the roof (and nothing else of it)
    assert 0 < _top_area(*whole) - _top_area(co, polys) < 0.7 * _top_area(*whole)
    assert sorted(o.name for o in blank.data.objects) == sorted(o.name for o in objs)  # nothing left behind


def _top_area(co, polys, tol=0.01):
    """Area of the polygons lying at the mesh's highest level."""
    top = co[:, 2].max() - tol
    area = 0.0
    for p in polys:
        f = co[p]
        if (f[:, 2] >= top).all():
            area += 0.5 * abs(np.cross(f, np.roll(f, -1, axis=0)).sum(axis=0)[2])
    return area


def _l_object(bpy, location=(30.0, 5.0, 0.0), rotation_z=0.3):
    """The L-shaped gable-roofed building of tests/addon/l_building.py as a user mesh:
    faces only, IDs and labels from 'Assign Building IDs' (2 storeys)."""
    from addon import scene_tools
    from tests.addon.l_building import l_building
    coll = bpy.data.collections.new("own")
    bpy.context.scene.collection.children.link(coll)
    v, f, _ = l_building()
    me = bpy.data.meshes.new("l_building")
    me.from_pydata([tuple(map(float, c)) for c in v], [], f)
    obj = bpy.data.objects.new("l_building", me)
    coll.objects.link(obj)
    obj.location = location
    obj.rotation_euler = (0.0, 0.0, rotation_z)
    scene_tools.assign_ids([obj], storeys=2)
    obj.qs_building.seed = 5
    return obj


def _top_over(verts, tris, inside, cell=0.25):
    """Highest surface over each cell of the xy bounding box of `verts` whose centre
    `inside` ((m, 2) points -> (m,) bool) accepts (a footprint), as in _top_heights."""
    x0, y0 = verts[:, 0].min() - 5, verts[:, 1].min() - 5
    x1, y1 = verts[:, 0].max() + 5, verts[:, 1].max() + 5

    class Box:
        bbox = (x0, y0, x1, y1)
    top = _top_heights(verts, tris, Box, cell)
    nx, ny = top.shape
    cx, cy = np.meshgrid(x0 + (np.arange(nx) + 0.5) * cell, y0 + (np.arange(ny) + 0.5) * cell, indexing="ij")
    mask = inside(np.column_stack([cx.ravel(), cy.ravel()])).reshape(nx, ny)
    return top[mask]


def _collapse_own_mesh(obj, height, inside_footprint, settle_steps=250):
    """Collapse by physics as grade 5 (everything fails); the checks of issue 14 on the
    building's own outline. Returns the record."""
    from addon import physics
    from addon.geometry import mesh as gm
    spec, elements, source, _, _ = physics.collapse_basis(obj)
    assert source == "mesh" and elements
    rec = physics.collapse_object(obj, 5, mode="everything", settle_steps=settle_steps)
    p = rec["params"]
    assert p["element_source"] == "mesh"
    # the shards tile the elements (no zone: every element is fractured)
    assert p["zone_volume"] == pytest.approx(sum(e.volume for e in elements), rel=1e-6)
    verts, tris, surf, bid, part = _mesh(obj)
    top = _top_over(verts, tris, inside_footprint)
    assert (top < 0.4 * height).mean() >= 0.8
    # the debris lies on and around the building's own outline, not over its bounding box
    debris = verts[np.unique(tris[surf == gm.DEBRIS])]
    return rec, debris


def test_user_l_mesh_with_a_gable_roof_collapses_as_itself(blank):
    from addon.geometry import poly2d
    from tests.addon.l_building import FOOTPRINT, RIDGE
    fp = np.array(FOOTPRINT, dtype=np.float64)
    obj = _l_object(blank, location=(0.0, 0.0, 0.0), rotation_z=0.0)
    rec, debris = _collapse_own_mesh(obj, RIDGE, lambda q: poly2d.contains(fp, q))
    p = rec["params"]
    assert (p["footprint_vertices"], p["roof_planes"], p["roof_faces_skipped"]) == (6, 4, 0)
    near = poly2d.signed_distance(fp, debris[:, :2]) <= 3.0
    assert near.mean() >= 0.95
    # the L's empty quadrant (inside its bounding box) holds little of it
    empty = (debris[:, 0] > 10.0) & (debris[:, 1] > 10.0)
    assert empty.mean() < 0.05


def test_rotterdam_building_collapses_over_its_own_outline(blank, tmp_path, shared_data):
    data = shared_data / "rotterdam_subset.json"
    from quakescan.formats.cityjson import import_cityjson
    from quakescan.formats.scene import write_scene
    from addon import io_import, physics
    from addon.geometry import mesh as gm
    s = import_cityjson(data)
    write_scene(s, tmp_path / "src")
    coll = blank.data.collections.new("imported")
    blank.context.scene.collection.children.link(coll)
    objs = io_import.import_bundle(tmp_path / "src", coll)["buildings"]
    for o in objs:
        io_import.prepare_for_damage(o)
    # the building whose own outline differs most from its bounding rectangle
    def fill(o):
        spec = physics.collapse_basis(o)[0]
        x0, y0, x1, y1 = spec.bbox
        return spec.footprint_area / ((x1 - x0) * (y1 - y0))
    obj = min(objs, key=fill)
    assert fill(obj) < 0.9
    verts, tris, surf, _, _ = _mesh(obj)
    ground = verts[tris[surf == gm.GROUND]][:, :, :2]  # the real outline, as triangles
    assert len(ground)

    def inside(q):
        a, b, c = ground[:, 0][None], ground[:, 1][None], ground[:, 2][None]
        qq = q[:, None, :]

        def side(u, v):
            return ((v[..., 0] - u[..., 0]) * (qq[..., 1] - u[..., 1])
                    - (v[..., 1] - u[..., 1]) * (qq[..., 0] - u[..., 0]))
        s1, s2, s3 = side(a, b), side(b, c), side(c, a)
        return (((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))).any(axis=1)
    # an 18 m, 6-storey building falls longer than the default 250 frames allow
    rec, debris = _collapse_own_mesh(obj, float(verts[:, 2].max()), inside, settle_steps=500)
    assert rec["params"]["footprint_vertices"] > 4
