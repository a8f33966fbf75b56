"""Scene work on explicit objects and collections (no bpy.context): create building and
terrain objects, label user meshes, apply damage, build the post-event collection.

Operators are thin wrappers around these functions; the batch generator calls them too.
"""
from __future__ import annotations

import json
import math

import bmesh
import bpy
import numpy as np

from . import ems98
from .geometry import mesh as gm
from .geometry import details
from .geometry import patterns as gp
from .geometry import poly2d
from .geometry.common import PatternNotApplicable
from .geometry.shell import ShellSpec, build_shell


class DamageError(ValueError):
    """A user-facing problem with the objects (message says what to do)."""


# --- BMesh <-> object -----------------------------------------------------------------------

def read_bmesh(obj):
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    return bm


def write_bmesh(obj, bm):
    bm.to_mesh(obj.data)
    obj.data.update()


def new_mesh_object(collection, name, bm):
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    obj = bpy.data.objects.new(name, me)
    collection.objects.link(obj)
    return obj


# --- buildings ------------------------------------------------------------------------------

def set_building_props(obj, building_id, spec: ShellSpec | None = None, grade=0, material=None,
                       vulnerability_class="B", seed=0, typology=None, storeys=None, storey_height=None):
    pg = obj.qs_building
    pg.role = "BUILDING"
    pg.building_id = int(building_id)
    pg.grade = int(grade)
    pg.material = material or (spec.material if spec else ems98.MASONRY)
    pg.vulnerability_class = vulnerability_class
    pg.seed = int(seed)
    pg.storeys = int(storeys or (spec.storeys if spec else 1))
    pg.storey_height = float(storey_height or (spec.storey_height if spec else 3.0))
    pg.typology = typology or (spec.typology if spec else "generic")
    pg.patterns_json = "[]"
    pg.shell_json = spec.to_json() if spec else ""


def create_building_object(collection, spec: ShellSpec, building_id: int, name=None, location=(0.0, 0.0, 0.0),
                           rotation_z=0.0, grade=0, vulnerability_class="B", seed=0):
    """A new object holding a procedural shell in its local frame, placed at `location`
    rotated `rotation_z` radians about z."""
    bm = bmesh.new()
    try:
        build_shell(bm, spec, building_id)
        obj = new_mesh_object(collection, name or f"building_{building_id:04d}", bm)
    finally:
        bm.free()
    obj.location = location
    obj.rotation_euler = (0.0, 0.0, rotation_z)
    set_building_props(obj, building_id, spec, grade=grade, vulnerability_class=vulnerability_class, seed=seed)
    return obj


def create_terrain_object(collection, x0, y0, x1, y1, z=0.0, name="terrain"):
    bm = bmesh.new()
    lab = gm.Labels(bm)
    gm.add_polygon(bm, lab, [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)], gm.GROUND, 0, gm.P_OTHER)
    obj = new_mesh_object(collection, name, bm)
    bm.free()
    obj.qs_building.role = "TERRAIN"
    return obj


def shell_of(obj) -> ShellSpec:
    """The object's shell description: stored by the add-on, or inferred from the mesh
    (bounding-box footprint, flat roof, storeys from the object's properties)."""
    pg = obj.qs_building
    if pg.shell_json:
        spec = ShellSpec.from_json(pg.shell_json)
        spec.material = pg.material
        return spec
    co = np.array([v.co[:] for v in obj.data.vertices], dtype=np.float64).reshape(-1, 3)
    if not len(co):
        raise DamageError(f"object {obj.name!r} has no geometry")
    (x0, y0, z0), (x1, y1, z1) = co.min(axis=0), co.max(axis=0)
    if x1 - x0 < 0.5 or y1 - y0 < 0.5 or z1 - z0 < 0.5:
        raise DamageError(f"object {obj.name!r} is too small to be a building (< 0.5 m in some direction)")
    storeys = max(1, int(pg.storeys))
    return ShellSpec(footprint=poly2d.rect(x0, y0, x1, y1).tolist(), storeys=storeys,
                     storey_height=(z1 - z0) / storeys, roof="flat",
                     material=pg.material, typology=pg.typology or "user", extra={"inferred": True})


def label_object(obj, building_id: int):
    """Give a mesh the add-on's face layers: building ID everywhere; where the mesh has no
    labels yet, walls are split at the storey levels and surface, part, storey and facade
    are inferred from the normals (the shell is then treated like a bounding-box shell)."""
    bm = read_bmesh(obj)
    ints = bm.faces.layers.int
    had_labels = ints.get(gm.PART_LAYER) is not None
    lab = gm.Labels(bm)
    pg = obj.qs_building
    zs = [v.co.z for v in bm.verts]
    zmin, zmax = (min(zs), max(zs)) if zs else (0.0, 0.0)
    ns = max(1, int(pg.storeys))
    hs = (zmax - zmin) / ns if zs else 3.0
    bm.normal_update()
    if not had_labels and hs > 0:
        for k in range(1, ns):
            walls = [f for f in bm.faces if abs(f.normal.z) <= 0.5]
            gm.bisect(bm, walls, (0.0, 0.0, zmin + k * hs), (0.0, 0.0, 1.0))
        bm.normal_update()
    for f in bm.faces:
        f[lab.bid] = int(building_id)
        if had_labels:
            continue
        n = f.normal
        c = f.calc_center_median()
        if n.z > 0.5:
            f[lab.surface], f[lab.part] = gm.ROOF, gm.P_ROOF
            f[lab.storey] = ns
        elif n.z < -0.5:
            f[lab.surface], f[lab.part] = gm.INTERIOR, gm.P_BASE
            f[lab.storey] = 0
        else:
            f[lab.surface], f[lab.part] = gm.WALL, gm.P_WALL
            f[lab.storey] = int(min(ns - 1, max(0, (c.z - zmin) // hs))) if hs > 0 else 0
            # facade index from the normal direction (matches a bounding-box footprint:
            # 0 south (-y), 1 east (+x), 2 north (+y), 3 west (-x))
            ang = math.atan2(n.y, n.x)
            f[lab.elem] = int(round((ang + math.pi / 2) / (math.pi / 2))) % 4
    write_bmesh(obj, bm)
    bm.free()


def assign_ids(objects, start_id: int | None = None, existing_ids=(), storeys: int = 0):
    """Make `objects` buildings with consecutive IDs (from `start_id`, default one above
    the highest existing ID) and label their faces; `storeys` > 0 sets the storey count,
    0 estimates it from the height (~3 m a storey). Returns the IDs given."""
    objs = [o for o in objects if o.type == 'MESH']
    if not objs:
        raise DamageError("select at least one mesh object")
    nxt = int(start_id) if start_id else (max(existing_ids, default=0) + 1)
    out = []
    for o in sorted(objs, key=lambda o: o.name):
        o.qs_building.role = "BUILDING"
        o.qs_building.building_id = nxt
        if storeys > 0:
            o.qs_building.storeys = storeys
        elif len(o.data.vertices):
            zs = [v.co.z for v in o.data.vertices]
            h = (max(zs) - min(zs)) * o.scale.z
            o.qs_building.storeys = max(1, int(round(h / 3.0)))
            o.qs_building.storey_height = max(2.0, h / o.qs_building.storeys)
        label_object(o, nxt)
        out.append(nxt)
        nxt += 1
    return out


def add_interior(obj):
    """Add floor slabs and coarse inner walls (surface 'interior') to a building mesh from
    its (stored or inferred) shell, so holes reveal something."""
    spec = shell_of(obj)
    bm = read_bmesh(obj)
    lab = gm.Labels(bm)
    if gm.faces_where(bm, lab, parts={gm.P_SLAB, gm.P_INNER}):
        bm.free()
        raise DamageError(f"{obj.name!r} already has slabs or inner walls")
    tmp = bmesh.new()
    build_shell(tmp, spec, obj.qs_building.building_id)
    tl = gm.Labels(tmp)
    keep = gm.faces_where(tmp, tl, parts={gm.P_SLAB, gm.P_INNER})
    for f in keep:
        vs = [bm.verts.new(v.co) for v in f.verts]
        nf = bm.faces.new(vs)
        tl_vals = (f[tl.surface], f[tl.bid], f[tl.part], f[tl.storey], f[tl.elem])
        lab.set(nf, *tl_vals)
    tmp.free()
    n = len(keep)
    write_bmesh(obj, bm)
    bm.free()
    return n


def add_roof_details(obj, seed=None) -> list:
    """Roof-top details (chimneys, antennas, solar panels, rooftop boxes, skylights) on the roof
    faces of a building mesh without a shell description (e.g. an imported CityJSON
    building), seeded by the building's seed. Returns the kinds added."""
    _check_building(obj)
    pg = obj.qs_building
    bm = read_bmesh(obj)
    try:
        kinds = details.add_roof_details(bm, pg.building_id, pg.seed if seed is None else seed, int(pg.storeys))
        write_bmesh(obj, bm)
    finally:
        bm.free()
    return kinds


def applied_patterns(obj) -> list:
    try:
        return json.loads(obj.qs_building.patterns_json or "[]")
    except json.JSONDecodeError:
        return []


def _check_building(obj):
    pg = obj.qs_building
    if obj.type != 'MESH' or pg.role != "BUILDING" or pg.building_id <= 0:
        raise DamageError(f"{obj.name!r} is not a building with an ID: use 'Assign IDs' first")


def _collapsed(records) -> bool:
    return any(ems98.PATTERNS[r["name"]].stage >= 2 for r in records if r.get("name") in ems98.PATTERNS)


def apply_pattern_to_object(obj, pattern: str, params: dict | None = None, randomize=False, grade=None):
    """Apply one pattern to a building object; returns the manifest record."""
    _check_building(obj)
    pg = obj.qs_building
    done = applied_patterns(obj)
    if _collapsed(done):
        raise DamageError(f"{obj.name!r} has already collapsed ({done[-1]['name']}); reset it first")
    if pattern not in ems98.PATTERNS:
        raise DamageError(f"unknown pattern {pattern!r}")
    spec = shell_of(obj)
    rng = gp.pattern_rng(pg.seed, ems98.pattern_salt(pattern), len(done))
    if randomize or params is None:
        g = grade if grade is not None else max(ems98.PATTERNS[pattern].grades)
        params = ems98.sample_params(pattern, rng, grade=g, material=spec.material) if randomize else \
            ems98.default_params(pattern, grade=g, material=spec.material)
    bm = read_bmesh(obj)
    trial = bm.copy()
    try:
        rec = gp.apply_pattern(trial, spec, pattern, params, rng, pg.building_id)
    except PatternNotApplicable as e:
        trial.free()
        bm.free()
        raise DamageError(f"{obj.name!r}: {pattern} does not apply: {e}") from None
    write_bmesh(obj, trial)
    trial.free()
    bm.free()
    done.append(rec)
    pg.patterns_json = json.dumps(done)
    return rec


def apply_grade_to_object(obj, grade: int | None = None, seed_salt: int = 0):
    """Damage a building as its EMS-98 grade (or `grade`) requires; returns the records.
    Grades 0-1 (and 2 without a chimney) leave the geometry as it is."""
    _check_building(obj)
    pg = obj.qs_building
    g = int(pg.grade if grade is None else grade)
    if _collapsed(applied_patterns(obj)):
        raise DamageError(f"{obj.name!r} has already collapsed; reset it first")
    spec = shell_of(obj)
    rng = gp.pattern_rng(pg.seed, g, 7919, seed_salt)
    bm = read_bmesh(obj)
    try:
        new, records = gp.damage_for_grade(bm, spec, g, rng, pg.building_id, pg.vulnerability_class)
    except (PatternNotApplicable, ValueError) as e:
        bm.free()
        raise DamageError(f"{obj.name!r}: {e}") from None
    write_bmesh(obj, new)
    new.free()
    bm.free()
    pg.grade = g
    pg.patterns_json = json.dumps(applied_patterns(obj) + records)
    return records


def reset_building(obj):
    """Rebuild an add-on shell intact (drops all applied patterns)."""
    _check_building(obj)
    pg = obj.qs_building
    if not pg.shell_json:
        raise DamageError(f"{obj.name!r} was not built by the add-on; undo to restore it")
    spec = ShellSpec.from_json(pg.shell_json)
    bm = bmesh.new()
    build_shell(bm, spec, pg.building_id)
    write_bmesh(obj, bm)
    bm.free()
    pg.patterns_json = "[]"


# --- scenes ---------------------------------------------------------------------------------

def scene_objects(collection):
    """Mesh objects of a collection and its children, sorted by name."""
    return sorted((o for o in collection.all_objects if o.type == 'MESH'), key=lambda o: o.name)


def building_objects(collection):
    return [o for o in scene_objects(collection) if o.qs_building.role == "BUILDING"]


def ensure_collection(scene, name, clear=False):
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
    if coll.name not in scene.collection.children:
        scene.collection.children.link(coll)
    if clear:
        remove_collection_objects(coll)
    return coll


def remove_collection_objects(coll):
    for o in list(coll.objects):
        me = o.data if o.type == 'MESH' else None
        bpy.data.objects.remove(o, do_unlink=True)
        if me is not None and me.users == 0:
            bpy.data.meshes.remove(me)
