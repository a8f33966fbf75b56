"""Collapse by physics: a building fractured into Voronoi shards and settled by Blender's
rigid-body solver (Bullet), as the alternative to the parametric patterns.

What happens to one building (``collapse_object``):

1. the trigger of its grade (geometry/trigger.py: grade 4 a corner, a wall strip or part of a
   storey; grade 5 the ground storey or every storey) names a zone and the storeys whose walls
   fail there;
2. the structural elements inside the zone (from the shell description, or for a user mesh or
   imported shell from its own faces: ``collapse_basis``) are cut into convex shards
   (geometry/fracture.py),
   the failing walls' shards crushed in place to a fifth of their height;
3. a temporary scene with a rigid-body world: every shard an active body (convex hull, mass =
   volume × the material's density, friction 0.6, restitution 0), passive colliders for the
   ground, the part of the building outside the zone, neighbouring buildings and terrain
   objects (triangle meshes, as given: post_scene.PhysicsColliders gives a scene's
   neighbours as they stand when its collapses start, see standing_part); the world is
   stepped frame by frame (``scene.frame_set``) until no shard moved more than 5 cm within the last second, or the
   step limit, or after 5 s once the shards that moved 0.5 m or more within the last second
   hold at most 1 % of the volume (EARLY_STOP_STEPS);
4. the post-event mesh: the building's faces outside the zone as they were, plus the shards
   where they came to rest. A shard that moved less than 10 cm keeps its element's labels
   (fracture faces between two such shards are dropped: nothing can see them); one that moved
   more, or a crushed one, is debris (surface 3, part debris) of this building, wherever it
   lands (on a neighbour too). Chimneys and roof or facade details inside the zone are not
   simulated: they are removed with the zone (recorded as ``details_dropped``).

At the step limit (or an early stop), shards that still creep are written where they lie, faster ones are
dropped, and when those hold more than MAX_UNSETTLED_SHARE of the volume (or fell through the
ground) the simulation is not written: ``collapse_object`` raises DamageError and the object
is left as it was.
Within one Blender version the same seed gives the same bytes (Bullet is deterministic for
the same bodies created in the same order).
"""
from __future__ import annotations

import dataclasses
import json
import logging

import bmesh
import bpy
import numpy as np

from . import scene_tools
from .geometry import fracture as fr
from .geometry import mesh as gm
from .geometry import mesh_elements as mel
from .geometry import patterns as gp
from .geometry import trigger as tg
from .geometry.shell import ShellSpec
from .scene_tools import DamageError

log = logging.getLogger(__name__)

PATTERN_NAME = "physics_collapse"
SETTLE_DRIFT = 0.05  # m: a shard that moved less within the last second is at rest
# At the step limit, shards that still creep (moved less than CREEP_DRIFT in the last second)
# are written as debris where they lie; faster ones are dropped, and when those hold more than
# MAX_UNSETTLED_SHARE of the volume the simulation is not written. Piles of thin convex shards
# in Bullet keep creeping at 5-50 cm/s for many seconds (measured; not resolved here).
CREEP_DRIFT = 0.5  # m
MAX_UNSETTLED_SHARE = 0.1
# Such piles are no closer to rest at the step limit than seconds earlier (shards faster than
# CREEP_DRIFT come and go), so from EARLY_STOP_STEPS on the simulation also ends as soon as
# the faster shards hold at most EARLY_STOP_SHARE of the volume: then as at the step limit
# (creeping shards written, faster ones dropped), without the frames it would step in vain.
EARLY_STOP_STEPS = 120  # frames: 5 s, when the falls of the grade-4/5 triggers are over
EARLY_STOP_SHARE = 0.01
DISPLACED = 0.1  # m: a shard that moved more is debris
FPS = 24
SUBSTEPS = 10  # per frame: 5 lets thin shards jitter forever; 20 settles a box pile no sooner in time
SOLVER_ITERATIONS = 10
FRICTION = 0.6
LINEAR_DAMPING, ANGULAR_DAMPING = 0.1, 0.2  # heavier damping slows the fall, the pile then takes longer
SLEEP_LINEAR, SLEEP_ANGULAR = 0.4, 0.8  # m/s, rad/s: Bullet puts slower bodies to sleep
# Bodies for the solver are the shards moved inwards by INSET, and Bullet adds the margin back:
# neighbours start a few millimetres apart. Touching hulls with a margin overlap, which Bullet
# resolves by pushing them apart (the building bursts); hulls without a margin jitter.
INSET = 0.02  # m
COLLISION_MARGIN = 0.015  # m
DEFAULT_SETTLE_STEPS = 250
_SALT = 4243  # keeps the physics draws apart from the patterns' (pattern_rng salts)

def _np_matrix(m) -> np.ndarray:
    return np.array([list(r) for r in m], dtype=np.float64)


def _mesh_from_polys(name, faces):
    """A Blender mesh from polygons ((k, 3) arrays); vertices not shared between faces."""
    verts, polys, off = [], [], 0
    for f in faces:
        verts.extend(map(tuple, f))
        polys.append(list(range(off, off + len(f))))
        off += len(f)
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], polys)
    return me


def world_matrix(obj) -> np.ndarray:
    """The object's world matrix from its location, rotation and scale (and its parents'):
    matrix_world is stale until the depsgraph runs, which a script that has just placed the
    object has not done."""
    M = _np_matrix(obj.matrix_basis)
    if obj.parent is not None:
        M = world_matrix(obj.parent) @ _np_matrix(obj.matrix_parent_inverse) @ M
    return M


def _world_arrays(obj, M=None):
    """Triangles of an object in world coordinates: (verts (n, 3), polys list)."""
    M = world_matrix(obj) if M is None else M
    me = obj.data
    co = np.array([v.co[:] for v in me.vertices], dtype=np.float64).reshape(-1, 3)
    co = co @ M[:3, :3].T + M[:3, 3]
    return co, [list(p.vertices) for p in me.polygons]


def _bbox_xy(obj):
    co, _ = _world_arrays(obj)
    if not len(co):
        return None
    return co[:, 0].min(), co[:, 1].min(), co[:, 0].max(), co[:, 1].max(), co[:, 2].min(), co[:, 2].max()


def neighbours(obj, candidates, reach: float):
    """Objects among `candidates` whose xy bounding box comes within `reach` of `obj`'s."""
    b = _bbox_xy(obj)
    out = []
    for o in candidates:
        if o is obj or o.type != 'MESH':
            continue
        c = _bbox_xy(o)
        if c is None or b is None:
            continue
        if c[0] <= b[2] + reach and c[2] >= b[0] - reach and c[1] <= b[3] + reach and c[3] >= b[1] - reach:
            out.append(o)
    return sorted(out, key=lambda o: o.name)


class _World:
    """A temporary scene with a rigid-body world; removed (with everything in it) on close."""

    def __init__(self, steps: int):
        self.scene = bpy.data.scenes.new("qs_physics")
        with bpy.context.temp_override(scene=self.scene):
            bpy.ops.rigidbody.world_add()
        rw = self.scene.rigidbody_world
        self.coll = bpy.data.collections.new("qs_physics_objects")
        self.scene.collection.children.link(self.coll)
        rw.collection = bpy.data.collections.new("qs_physics_bodies")
        rw.substeps_per_frame = SUBSTEPS
        rw.solver_iterations = SOLVER_ITERATIONS
        # penetration recovery without the velocity it would add: otherwise piles keep creeping
        rw.use_split_impulse = True
        self.scene.render.fps = FPS
        self.scene.frame_start = 1
        self.scene.frame_end = steps + 1
        rw.point_cache.frame_start = 1
        rw.point_cache.frame_end = steps + 1
        self.rw = rw
        self.objects = []

    def add(self, name, me, location, active: bool, mass=1.0, shape='CONVEX_HULL'):
        o = bpy.data.objects.new(name, me)
        o.location = location
        self.coll.objects.link(o)
        self.rw.collection.objects.link(o)
        rb = o.rigid_body
        rb.type = 'ACTIVE' if active else 'PASSIVE'
        rb.collision_shape = shape
        rb.mass = float(max(mass, 1e-3))
        rb.friction = FRICTION
        rb.restitution = 0.0
        rb.use_margin = True
        rb.collision_margin = COLLISION_MARGIN if shape == 'CONVEX_HULL' else 0.0
        rb.linear_damping = LINEAR_DAMPING
        rb.angular_damping = ANGULAR_DAMPING
        rb.use_deactivation = False
        rb.deactivate_linear_velocity = SLEEP_LINEAR
        rb.deactivate_angular_velocity = SLEEP_ANGULAR
        self.objects.append(o)
        return o

    def matrices(self, first: int) -> np.ndarray:
        """World matrices (k, 4, 4) of the objects added from the `first`-th on, read at once
        (reading them one by one costs more than a frame of the simulation)."""
        n = len(self.coll.objects)
        flat = np.empty(n * 16, dtype=np.float64)
        self.coll.objects.foreach_get("matrix_world", flat)
        # Blender stores matrices column by column
        return flat.reshape(n, 4, 4).transpose(0, 2, 1)[first:]

    def close(self):
        rbc = self.rw.collection
        for o in self.objects:
            me = o.data
            bpy.data.objects.remove(o, do_unlink=True)
            if me is not None and me.users == 0:
                bpy.data.meshes.remove(me)
        bpy.data.collections.remove(self.coll)
        bpy.data.scenes.remove(self.scene)
        if rbc is not None and rbc.users == 0:
            bpy.data.collections.remove(rbc)


def _is_object(o) -> bool:
    return not isinstance(o, tuple)


def _collider_mesh(name, objs):
    """One passive triangle mesh (world coordinates) from several objects, or (vertices,
    polygons) pairs already in world coordinates (standing_part)."""
    verts, polys, off = [], [], 0
    for o in objs:
        co, ps = _world_arrays(o) if _is_object(o) else o
        verts.extend(map(tuple, co))
        polys.extend([[i + off for i in p] for p in ps])
        off += len(co)
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], polys)
    return me


def simulate(shards_world, masses, passive_meshes, ground_z, steps: int):
    """Step a rigid-body world with the shards (polygons in world coordinates) as active
    bodies until none moved more than SETTLE_DRIFT within the last second, or `steps` frames,
    or from EARLY_STOP_STEPS on until those that moved CREEP_DRIFT or more hold at most
    EARLY_STOP_SHARE of the mass.
    Returns (final 4x4 matrices of each shard relative to its start, each shard's drift over
    the last second (inf for one that fell through the ground), frames stepped, settled)."""
    world = _World(steps)
    try:
        lo = np.min([np.concatenate(f).min(axis=0) for f in shards_world], axis=0)
        hi = np.max([np.concatenate(f).max(axis=0) for f in shards_world], axis=0)
        span = float(max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - ground_z)) * 3 + 20.0
        c = (lo + hi) / 2
        g = bmesh.new()
        bmesh.ops.create_cube(g, size=1.0)
        for v in g.verts:
            v.co.x, v.co.y, v.co.z = v.co.x * span, v.co.y * span, v.co.z * 2.0
        gme = bpy.data.meshes.new("qs_ground")
        g.to_mesh(gme)
        g.free()
        world.add("qs_ground", gme, (float(c[0]), float(c[1]), ground_z - 1.0), active=False, shape='BOX')
        for k, me in enumerate(passive_meshes):
            world.add(f"qs_passive_{k:03d}", me, (0.0, 0.0, 0.0), active=False, shape='MESH')
        bodies, radii = [], []
        for k, (faces, mass) in enumerate(zip(shards_world, masses)):
            cen = fr.polyhedron_centroid(faces)
            me = _mesh_from_polys(f"qs_shard_{k:05d}", [f - cen for f in _inset(faces)])
            bodies.append(world.add(f"qs_shard_{k:05d}", me, tuple(map(float, cen)), active=True, mass=mass))
            radii.append(float(np.linalg.norm(np.concatenate(faces) - cen, axis=1).max()))
        radii = np.array(radii)
        weight = np.asarray(masses, dtype=np.float64)
        total = float(weight.sum())
        frame = 1
        world.scene.frame_set(1)  # evaluates the bodies' start transforms
        start = world.matrices(len(world.objects) - len(bodies))
        history = [start]
        drift = np.full(len(bodies), np.inf)
        for frame in range(2, steps + 2):
            world.scene.frame_set(frame)
            history.append(world.matrices(len(world.objects) - len(bodies)))
            if len(history) > FPS:
                history.pop(0)
                cur, old = history[-1], history[0]
                # how far each shard's points moved within the last second
                drift = (np.linalg.norm(cur[:, :3, 3] - old[:, :3, 3], axis=1)
                         + np.linalg.norm(cur[:, :3, :3] - old[:, :3, :3], axis=(1, 2)) * radii)
                if frame % FPS == 0:
                    log.debug("frame %d: %d of %d shards moved more than %.2f m in the last second", frame,
                              int((drift >= SETTLE_DRIFT).sum()), len(bodies), SETTLE_DRIFT)
                if drift.max() < SETTLE_DRIFT:
                    break
                if frame > EARLY_STOP_STEPS and weight[drift >= CREEP_DRIFT].sum() <= EARLY_STOP_SHARE * total:
                    break
        prev = history[-1]
        fell = prev[:, 2, 3] < ground_z - 1.0
        rel = np.array([p @ np.linalg.inv(s) for p, s in zip(prev, start)])
        drift = np.where(fell, np.inf, drift)
        return rel, drift, frame, bool(drift.max(initial=0.0) < SETTLE_DRIFT)
    finally:
        world.close()


def collapse_object(obj, grade: int | None = None, seed: int | None = None,
                    settle_steps: int = DEFAULT_SETTLE_STEPS, colliders=(), mode: str | None = None,
                    max_shards: int = 250) -> dict:
    """Collapse a building by simulation as its EMS-98 grade (4 or 5) requires; returns the
    manifest record and appends it to the building's patterns. `colliders`: other objects
    (neighbours, terrain) debris may land on, or (vertices, polygons) in world coordinates
    (standing_part). Raises DamageError (object unchanged) when the
    grade has no physics trigger or the shards do not settle within `settle_steps` frames."""
    scene_tools._check_building(obj)
    pg = obj.qs_building
    g = int(pg.grade if grade is None else grade)
    if g not in tg.GRADE_MODES:
        raise DamageError(f"{obj.name!r}: physics makes grades 4 and 5 (grade {g} is local damage: use the patterns)")
    done = scene_tools.applied_patterns(obj)
    if done:
        raise DamageError(f"{obj.name!r} is already damaged ({done[-1].get('name')}); reset it first")
    spec, own_elements, source, base, source_info = collapse_basis(obj)
    s = int(pg.seed if seed is None else seed)
    rng = gp.pattern_rng(s, g, _SALT)
    try:
        trig = _lifted(tg.make_trigger(spec, g, rng, mode), base)
    except ValueError as e:
        raise DamageError(f"{obj.name!r}: {e}") from None
    elements, shards, (near, far) = tg.zone_shards(spec, trig, rng, max_shards=max_shards, elements=own_elements)
    if not shards:
        raise DamageError(f"{obj.name!r}: the {trig.mode} zone holds no structural element")
    density = fr.MATERIAL[spec.material]["density"]
    M = world_matrix(obj)
    Minv = np.linalg.inv(M)
    local = []
    for sh in shards:
        faces = [f.copy() for f in sh.solid.faces]
        if sh.support:  # crushed in place: the load above loses its bearing
            zb = min(float(f[:, 2].min()) for f in faces)
            for f in faces:
                f[:, 2] = zb + (f[:, 2] - zb) * tg.CRUSH
        local.append(faces)
    world = [[f @ M[:3, :3].T + M[:3, 3] for f in faces] for faces in local]
    volumes = np.array([fr.polyhedron_volume(f) for f in local])
    ground_z = float(M[2, 3])
    # the part of the building that stands (outside the zone), as a collider
    bm = None
    try:
        bm, dropped_parts = _standing_bmesh(obj, trig)
        lab = gm.Labels(bm)
        passive = []
        if len(bm.faces):
            co = np.array([v.co[:] for v in bm.verts], dtype=np.float64) @ M[:3, :3].T + M[:3, 3]
            bm.verts.index_update()
            me = bpy.data.meshes.new("qs_standing")
            me.from_pydata([tuple(c) for c in co], [], [[v.index for v in f.verts] for f in bm.faces])
            passive.append(me)
        others = [o for o in colliders if (o is not obj and o.type == 'MESH' and len(o.data.polygons)
                                           if _is_object(o) else len(o[1]))]
        if others:
            passive.append(_collider_mesh("qs_neighbours", others))
        rel, drift, frames, settled = simulate(world, volumes * density, passive, ground_z, int(settle_steps))
        moving = drift >= CREEP_DRIFT
        creeping = (drift >= SETTLE_DRIFT) & ~moving
        share = float(volumes[moving].sum() / volumes.sum())
        if share > MAX_UNSETTLED_SHARE:
            raise DamageError(f"{obj.name!r}: the collapse did not settle in {settle_steps} steps "
                              f"({int(moving.sum())} of {len(shards)} shards, {100 * share:.1f} % of the volume, moved more than "
                              f"{CREEP_DRIFT} m in the last second or fell through the ground); not written: raise "
                              "the settle steps")
        # settled shards back into the building's frame, labelled
        in_place = np.zeros(len(shards), bool)
        placed = []
        for k, (sh, faces) in enumerate(zip(shards, world)):
            R = Minv @ rel[k] @ M
            moved = [f @ R[:3, :3].T + R[:3, 3] for f in local[k]]
            disp = max(float(np.linalg.norm(a - b, axis=1).max()) for a, b in zip(moved, local[k]))
            in_place[k] = (not sh.support) and disp <= DISPLACED and not moving[k] and not creeping[k]
            placed.append(moved)
        key = {(sh.element, sh.seed): k for k, sh in enumerate(shards)}
        debris_vol = 0.0
        n_faces = 0
        for k, (sh, faces) in enumerate(zip(shards, placed)):
            el = elements[sh.element]
            if moving[k]:
                continue  # still moving at the step limit: reported in the record, not written
            if not in_place[k]:
                debris_vol += volumes[k]
            for f, t in zip(faces, sh.solid.tags):
                if in_place[k]:
                    labels = (el.face_surface(t), pg.building_id, el.part, el.storey, el.elem)
                else:
                    labels = (gm.DEBRIS, pg.building_id, gm.P_DEBRIS, -1, 0)
                if in_place[k] and t >= 0 and in_place[key.get((sh.element, t), k)]:
                    continue  # a fracture face between two shards that did not move
                if in_place[k] and t <= -1001:
                    continue  # the zone's boundary: the standing element continues there
                if _area(f) <= gm.MIN_TRI_AREA:
                    continue
                try:
                    gm.add_polygon(bm, lab, f, *labels)
                    n_faces += 1
                except ValueError:
                    continue
        bm.normal_update()
        scene_tools.write_bmesh(obj, bm)
    finally:
        if bm is not None:
            bm.free()
    rec = {"name": PATTERN_NAME, "params": gp.rnd({
        "mode": trig.mode, **{k: v for k, v in trig.params.items()},
        "support_storeys": trig.support_storeys, "seed": s, "settle_steps": int(settle_steps),
        "frames": int(frames), "shards": len(shards), "support_shards": int(sum(sh.support for sh in shards)),
        "debris_shards": int((~in_place & ~moving).sum()), "in_place_shards": int(in_place.sum()),
        "settled": bool(settled), "creeping_shards": int(creeping.sum()),
        "unsettled_shards_dropped": int(moving.sum()), "unsettled_volume_share": share,
        "zone_volume": float(sum(sh.solid.volume() for sh in shards)), "debris_solid_volume": float(debris_vol),
        "cell_near": near, "cell_far": far, "material": spec.material,
        "element_source": source, **source_info,
        "density": density, "details_dropped": dropped_parts, "blender": bpy.app.version_string})}
    pg.grade = g
    pg.patterns_json = json.dumps(done + [rec])
    return rec


def collapse_basis(obj):
    """What a collapse by physics of `obj` works from: (the shell description its trigger
    reads, its elements (None: built from that description by fracture.building_elements),
    the element source ``"shell"`` or ``"mesh"``, its ground level, extras for the record).

    The add-on's procedural buildings use their shell description. A building without one
    (a user mesh, an imported CityJSON shell: the description is inferred, a box) uses its own
    faces (geometry/mesh_elements.py); its trigger then reads a flat-roofed description with
    the mesh's outline and storeys. When the faces give no outline (an open or unlabelled
    mesh) the inferred box is used, and the record says why."""
    pg = obj.qs_building
    spec = scene_tools.shell_of(obj)
    if not spec.extra.get("inferred"):
        return spec, None, "shell", 0.0, {}
    bm = scene_tools.read_bmesh(obj)
    try:
        lab = gm.Labels(bm)
        bm.verts.index_update()
        verts = np.array([v.co[:] for v in bm.verts], dtype=np.float64).reshape(-1, 3)
        polys = [[v.index for v in f.verts] for f in bm.faces]
        surface = np.array([f[lab.surface] for f in bm.faces], dtype=np.int64)
        part = np.array([f[lab.part] for f in bm.faces], dtype=np.int64)
    finally:
        bm.free()
    try:
        mb = mel.mesh_elements(verts, polys, surface, part, spec.material, pg.storeys, pg.storey_height)
    except mel.MeshElementsError as e:
        log.warning("%s: elements from the inferred box, not its own faces: %s", obj.name, e)
        return spec, None, "shell", 0.0, {"element_source_note": f"own faces gave no elements: {e}"}
    own = ShellSpec(footprint=mb.footprint.tolist(), storeys=mb.storeys, storey_height=mb.storey_height,
                    roof="flat", material=spec.material, typology=spec.typology,
                    extra={"inferred": True, "source": "mesh"})
    info = {"footprint_source": mb.footprint_source, "footprint_vertices": len(mb.footprint),
            "roof_planes": mb.roof_planes, "roof_faces_skipped": mb.roof_faces_skipped}
    return own, mb.elements, "mesh", mb.base, info


def _lifted(trig, dz: float):
    """The trigger of a building whose ground is at z = dz in its frame (the description's
    storey levels start at 0)."""
    if dz == 0.0:
        return trig
    zone = [((c[0], c[1], c[2] + dz), n) for c, n in trig.zone]
    o = trig.origin
    return dataclasses.replace(trig, zone=zone, origin=(o[0], o[1], o[2] + dz))


def _standing_bmesh(obj, trig):
    """The object's mesh without the faces inside the trigger's zone (the part that stands),
    and the names of the non-structural parts removed with the zone."""
    bm = scene_tools.read_bmesh(obj)
    lab = gm.Labels(bm)
    if trig.zone:
        inside = gm.carve(bm, lambda b: list(b.faces), trig.zone)
    else:
        inside = list(bm.faces)
    dropped_parts = sorted({gm.PART_NAMES.get(f[lab.part], "other") for f in inside
                            if f[lab.part] not in (gm.P_WALL, gm.P_ROOF, gm.P_SLAB, gm.P_INNER, gm.P_GABLE,
                                                   gm.P_PARAPET)})
    gm.delete_faces(bm, inside)
    gm.remove_loose(bm)
    return bm, dropped_parts


def standing_part(obj, grade: int, seed: int | None = None, mode: str | None = None):
    """What stands of a building that collapses by physics (its mesh without its trigger's
    zone; nothing for grade 5), in world coordinates: (vertices (n, 3), polygons). A
    neighbour collapsing in the same scene is a collider as this, not as it stood nor as it
    lies afterwards: collapses are simultaneous, so none depends on another's outcome (and
    a scene's collapses can be simulated in any order or process). Without a trigger (the
    grade falls back to the patterns) the whole mesh."""
    pg = obj.qs_building
    s = int(pg.seed if seed is None else seed)
    try:
        spec, _, _, base, _ = collapse_basis(obj)
        trig = _lifted(tg.make_trigger(spec, int(grade), gp.pattern_rng(s, int(grade), _SALT), mode), base)
    except (ValueError, DamageError):
        return _world_arrays(obj)
    bm, _ = _standing_bmesh(obj, trig)
    try:
        M = world_matrix(obj)
        bm.verts.index_update()
        co = np.array([v.co[:] for v in bm.verts], dtype=np.float64).reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
        return co, [[v.index for v in f.verts] for f in bm.faces]
    finally:
        bm.free()


def _inset(faces):
    """A shard's faces moved inwards by INSET (its body for the solver): with the collision
    margin added back, neighbours start a few millimetres apart instead of touching, which
    Bullet would resolve as penetration and push apart."""
    poly = fr.Polyhedron(list(faces), list(range(len(faces))))
    for f in faces:
        no = fr.face_normal(f)
        smaller = fr.clip(poly, f[0] - INSET * no, no, 0)
        if smaller is None:
            return faces  # too thin to inset: keep it as it is
        poly = smaller
    return poly.faces


def _area(f) -> float:
    n = fr.cross(f, np.roll(f, -1, axis=0)).sum(axis=0)
    return 0.5 * fr.norm(n)
