"""Import a QuakeScan scene bundle (scene.json + mesh.ply) as Blender objects, prepare the
imported buildings for damage, and export them again without losing float64 precision.

The bundle format is the project's contract (docs/DESIGN.md, "Scene bundle"). This module has
its own numpy PLY reader: the add-on never imports the core package.

- ``import_bundle`` creates one object per building (the faces whose ``building_id`` is
  the building's ID; face layers ``qs_surface`` / ``qs_building_id`` from the file; ID,
  grade, material, storeys, typology, seed from scene.json) and one terrain object
  (``building_id`` 0). Each building object is placed at its footprint's centre and ground
  level and turned to its minimum-area bounding rectangle, so its local frame is what the
  damage patterns expect (z = 0 ground, facades along local x/y). The bundle's origin and
  CRS go to the scene's export settings (``scene.qs_scene.origin`` / ``crs``).
- Blender stores vertices as float32 (~1e-5 m at 100 m from the object). The float64
  remainder of every imported vertex is kept in point attributes (``qs_co_ref``: the
  float32 local coordinate at import, ``qs_co_res``: world residual); ``export_bundle``
  adds it back for vertices that were not moved, so import → export reproduces the file's
  coordinates to ~1e-12 m. (``io_export.export_objects`` ignores these attributes and is
  exact to float32 only.)
- ``prepare_for_damage`` turns an imported LoD2 shell into something the add-on's damage
  patterns can work on: element labels from the file's surfaces, walls split at storey
  levels, and coarse floor slabs and inner walls from a flat-roofed box shell (the
  building's oriented bounding rectangle, up to the eaves). See docs/addon.md for the limits.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import bpy
import numpy as np

from . import ems98, io_export, scene_tools
from .geometry import mesh as gm
from .geometry import poly2d
from .geometry.shell import ShellSpec

REF_ATTR = "qs_co_ref"
RES_ATTR = "qs_co_res"
EXTRA_PROP = "qs_bundle_extra"
CONTRACT_MIN_AREA = 1e-10  # the contract rejects faces with area <= 1e-10 m²
_BUILDING_KEYS = {"id", "grade", "material", "storeys", "typology", "patterns", "seed", "vulnerability_class",
                  "storey_height", "planned_grade"}


class BundleError(ValueError):
    """A malformed scene bundle; the message names the file and the problem."""


# --- readers (numpy only) -------------------------------------------------------------------

def read_ply(path):
    """Read the contract's PLY: returns (vertices (n, 3) float64, faces: list of index arrays,
    building_id (m,) int64, surface (m,) int64, porous (m,) bool or None when the file has no
    ``porous`` face property). Polygons are allowed."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise BundleError(f"{path}: cannot read the mesh ({e.strerror or e})") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise BundleError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    try:
        lines = raw[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise BundleError(f"{path}: PLY header is not ASCII") from None
    fmt, elements = None, []
    for ln in lines:
        t = ln.split()
        if not t or t[0] in ("comment", "obj_info"):
            continue
        if t[0] == "format":
            fmt = t[1] if len(t) > 1 else None
        elif t[0] == "element" and len(t) == 3:
            try:
                elements.append([t[1], int(t[2]), []])
            except ValueError:
                raise BundleError(f"{path}: bad element line {ln!r}") from None
        elif t[0] == "property" and elements:
            elements[-1][2].append(tuple(t[1:]))
        else:
            raise BundleError(f"{path}: unexpected PLY header line {ln!r}")
    if fmt != "binary_little_endian":
        raise BundleError(f"{path}: PLY format must be binary_little_endian, got {fmt!r}")
    names = [e[0] for e in elements]
    if names != ["vertex", "face"]:
        raise BundleError(f"{path}: expected elements 'vertex' then 'face', got {names}")
    (_, nv, vprops), (_, nf, fprops) = elements
    if vprops != [("double", "x"), ("double", "y"), ("double", "z")]:
        raise BundleError(f"{path}: vertex properties must be 'double x, double y, double z', got {vprops}")
    want = [("list", "uchar", "int", "vertex_indices"), ("int", "building_id"), ("uchar", "surface")]
    has_porous = fprops == want + [("uchar", "porous")]
    if fprops != want and not has_porous:
        raise BundleError(f"{path}: face properties must be 'list uchar int vertex_indices, int building_id, "
                          f"uchar surface' (and optionally 'uchar porous'), got {fprops}")
    tail = 6 if has_porous else 5  # bytes after a face's index list
    data = memoryview(raw)[end + len(b"end_header\n"):]
    vbytes = nv * 24
    if len(data) < vbytes:
        raise BundleError(f"{path}: file ends inside the vertex data ({nv} vertices announced)")
    verts = np.frombuffer(data[:vbytes], dtype="<f8").reshape(nv, 3).astype(np.float64)
    fdata = data[vbytes:]
    tri = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("b", "<i4"), ("s", "u1")] + ([("p", "u1")] if has_porous else []))
    porous = np.zeros(nf, bool) if has_porous else None
    if len(fdata) == nf * tri.itemsize and (nf == 0 or
                                            (np.frombuffer(fdata, dtype=tri, count=nf)["n"] == 3).all()):
        rec = np.frombuffer(fdata, dtype=tri, count=nf)
        faces = [r for r in rec["v"].astype(np.int64)]
        bid, surf = rec["b"].astype(np.int64), rec["s"].astype(np.int64)
        if has_porous:
            porous = rec["p"] != 0
    else:
        faces, bid, surf = [], np.empty(nf, np.int64), np.empty(nf, np.int64)
        buf, pos = bytes(fdata), 0
        for k in range(nf):
            if pos >= len(buf):
                raise BundleError(f"{path}: file ends inside face {k} of {nf}")
            n = buf[pos]
            stop = pos + 1 + 4 * n + tail
            if stop > len(buf):
                raise BundleError(f"{path}: file ends inside face {k} of {nf}")
            faces.append(np.frombuffer(buf, dtype="<i4", count=n, offset=pos + 1).astype(np.int64))
            b0 = pos + 1 + 4 * n
            bid[k] = int.from_bytes(buf[b0:b0 + 4], "little", signed=True)
            surf[k] = buf[b0 + 4]
            if has_porous:
                porous[k] = buf[b0 + 5] != 0
            pos = stop
        if pos != len(buf):
            raise BundleError(f"{path}: {len(buf) - pos} unexpected bytes after the last face")
    for k, f in enumerate(faces):
        if len(f) < 3:
            raise BundleError(f"{path}: face {k} has {len(f)} vertices (at least 3 needed)")
        if f.min() < 0 or f.max() >= nv:
            raise BundleError(f"{path}: face {k} points at vertex {f.tolist()} but the mesh has {nv} vertices")
    if not np.isfinite(verts).all():
        raise BundleError(f"{path}: vertices with NaN/inf coordinates")
    if (surf > gm.OBJECT).any():
        k = int(np.flatnonzero(surf > gm.OBJECT)[0])
        raise BundleError(f"{path}: face {k} has surface code {int(surf[k])}; valid codes are 0..6 "
                          f"({io_export.SURFACE_CODES})")
    if (bid < 0).any():
        raise BundleError(f"{path}: negative building_id on face {int(np.flatnonzero(bid < 0)[0])}")
    return verts, faces, bid, surf, porous


def read_manifest(folder):
    """scene.json of a bundle folder as a dict (checked); raises BundleError naming the file."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BundleError(f"{folder}: scene bundle folder does not exist")
    path = folder / "scene.json"
    try:
        m = json.loads(path.read_text())
    except FileNotFoundError:
        raise BundleError(f"{path}: scene.json is missing (a scene bundle is a folder with scene.json "
                          "and mesh.ply)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BundleError(f"{path}: not a readable JSON file ({e})") from None
    if not isinstance(m, dict) or m.get("format") != io_export.FORMAT:
        raise BundleError(f"{path}: not a QuakeScan scene manifest (format must be {io_export.FORMAT!r})")
    if m.get("version") != io_export.VERSION:
        raise BundleError(f"{path}: version {m.get('version')!r} is not supported (expected {io_export.VERSION})")
    if m.get("units", "m") != "m":
        raise BundleError(f"{path}: units must be 'm', got {m.get('units')!r}")
    origin = m.get("origin", [0.0, 0.0, 0.0])
    if (not isinstance(origin, list) or len(origin) != 3 or
            not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in origin)):
        raise BundleError(f"{path}: origin must be three finite numbers, got {origin!r}")
    if m.get("crs") is not None and not isinstance(m.get("crs"), str):
        raise BundleError(f"{path}: crs must be a string or null, got {m.get('crs')!r}")
    bl = m.get("buildings")
    if not isinstance(bl, list):
        raise BundleError(f"{path}: 'buildings' must be a list")
    seen = set()
    for i, b in enumerate(bl):
        bid = b.get("id") if isinstance(b, dict) else None
        if not isinstance(bid, int) or isinstance(bid, bool) or bid <= 0:
            raise BundleError(f"{path}: buildings[{i}].id must be an integer > 0, got {bid!r}")
        if bid in seen:
            raise BundleError(f"{path}: duplicate building ID {bid}")
        seen.add(bid)
        if b.get("grade", 0) not in range(6):
            raise BundleError(f"{path}: building {bid}: grade must be 0..5, got {b.get('grade')!r}")
        if b.get("material", ems98.MASONRY) not in (ems98.MASONRY, ems98.RC):
            raise BundleError(f"{path}: building {bid}: unknown material {b.get('material')!r}")
    mesh = m.get("mesh", "mesh.ply")
    if not isinstance(mesh, str) or Path(mesh).name != mesh:
        raise BundleError(f"{path}: mesh must be a file name inside the bundle, got {mesh!r}")
    return m


def read_bundle(folder):
    """(manifest dict, vertices, faces, building_id, surface, porous or None), cross-checked."""
    folder = Path(folder)
    m = read_manifest(folder)
    mesh_path = folder / m.get("mesh", "mesh.ply")
    if not mesh_path.is_file():
        raise BundleError(f"{mesh_path}: mesh file named in scene.json is missing")
    v, f, b, s, p = read_ply(mesh_path)
    ids = {int(x["id"]) for x in m["buildings"]}
    in_mesh = set(np.unique(b).tolist()) - {0}
    if in_mesh - ids:
        raise BundleError(f"{mesh_path}: faces carry building IDs {sorted(in_mesh - ids)[:10]} that "
                          f"{folder / 'scene.json'} does not list")
    if ids - in_mesh:
        raise BundleError(f"{folder / 'scene.json'}: buildings {sorted(ids - in_mesh)[:10]} have no faces in "
                          f"{mesh_path}")
    return m, v, f, b, s, p


# --- geometry helpers -----------------------------------------------------------------------

def min_area_rect_angle(xy) -> float:
    """Rotation (radians, in [-pi/4, pi/4]) of the minimum-area rectangle around points xy."""
    xy = np.unique(np.round(np.asarray(xy, dtype=np.float64), 6), axis=0)
    if len(xy) < 3:
        return 0.0
    hull = _hull(xy)
    best, angle = math.inf, 0.0
    for i in range(len(hull)):
        e = hull[(i + 1) % len(hull)] - hull[i]
        if np.hypot(*e) < 1e-6:
            continue
        a = math.atan2(e[1], e[0])
        a = (a + math.pi / 4) % (math.pi / 2) - math.pi / 4
        c, s = math.cos(a), math.sin(a)
        p = hull @ np.array([[c, -s], [s, c]])  # rotate by -a
        area = float(np.ptp(p[:, 0]) * np.ptp(p[:, 1]))
        if area < best - 1e-9:
            best, angle = area, a
    return angle


def _cross2(a, b):
    return a[0] * b[1] - a[1] * b[0]


def _hull(p):
    p = p[np.lexsort((p[:, 1], p[:, 0]))]

    def half(pts):
        h = []
        for q in pts:
            while len(h) >= 2 and _cross2(h[-1] - h[-2], q - h[-2]) <= 0:
                h.pop()
            h.append(q)
        return h[:-1]
    return np.array(half(p) + half(p[::-1]))


def _set_points(me, co32, res):
    me.vertices.foreach_set("co", np.ascontiguousarray(co32, dtype=np.float32).ravel())
    a = me.attributes.new(REF_ATTR, 'FLOAT_VECTOR', 'POINT')
    a.data.foreach_set("vector", np.ascontiguousarray(co32, dtype=np.float32).ravel())
    a = me.attributes.new(RES_ATTR, 'FLOAT_VECTOR', 'POINT')
    a.data.foreach_set("vector", np.ascontiguousarray(res, dtype=np.float32).ravel())


def _make_object(collection, name, verts, faces, bid, surf, align, porous=None):
    """Object holding `faces` (index arrays into `verts`, float64 bundle coordinates)."""
    used = np.unique(np.concatenate(faces))
    remap = np.full(int(used.max()) + 1, -1, np.int64)
    remap[used] = np.arange(len(used))
    x = verts[used]
    me = bpy.data.meshes.new(name)
    me.from_pydata([(0.0, 0.0, 0.0)] * len(x), [], [remap[f].tolist() for f in faces])
    obj = bpy.data.objects.new(name, me)
    collection.objects.link(obj)
    lo = x.min(axis=0)
    if align:
        ang = float(np.float32(min_area_rect_angle(x[:, :2])))
        c, s = math.cos(ang), math.sin(ang)
        p = x[:, :2] @ np.array([[c, -s], [s, c]])
        mid = (p.min(axis=0) + p.max(axis=0)) / 2
        cxy = np.array([[c, -s], [s, c]]) @ mid
        loc = (cxy[0], cxy[1], lo[2])
    else:
        ang, loc = 0.0, (lo[0], lo[1], lo[2])
    obj.location = tuple(float(np.float32(t)) for t in loc)
    obj.rotation_euler = (0.0, 0.0, ang)
    M = io_export.world_matrix(obj)
    co = ((x - M[:3, 3]) @ np.linalg.inv(M[:3, :3]).T).astype(np.float32)
    world = co.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    _set_points(me, co, x - world)
    layers = [(gm.SURFACE_LAYER, surf), (gm.BUILDING_LAYER, bid)]
    if porous is not None and np.any(porous):
        layers.append((gm.POROUS_LAYER, porous))
    for layer, values in layers:
        a = me.attributes.new(layer, 'INT', 'FACE')
        a.data.foreach_set("value", np.ascontiguousarray(values, dtype=np.int32))
    me.update()
    return obj


# --- import ---------------------------------------------------------------------------------

def import_bundle(folder, collection, scene=None, building_ids=None, align=True):
    """Create the bundle's objects in `collection`; returns a dict with origin, crs, epoch,
    the manifest, the building objects (sorted by ID) and the terrain object (or None).

    `building_ids`: import only these buildings (default all); the terrain is always
    imported. `scene`: when given, its export settings get the bundle's origin and CRS.
    """
    folder = Path(folder)
    m, verts, faces, bid, surf, porous = read_bundle(folder)
    recs = {int(b["id"]): b for b in m["buildings"]}
    want = sorted(recs) if building_ids is None else sorted(int(i) for i in building_ids)
    missing = [i for i in want if i not in recs]
    if missing:
        raise BundleError(f"{folder / 'scene.json'}: no building(s) {missing[:10]}")
    order = np.argsort(bid, kind="stable")
    sb = bid[order]
    objs = []
    for i in want:
        rec = recs[i]
        sel = order[np.searchsorted(sb, i, "left"):np.searchsorted(sb, i, "right")]
        obj = _make_object(collection, f"building_{i:04d}", verts, [faces[k] for k in sel], bid[sel], surf[sel],
                           align)
        mat = rec.get("material", ems98.MASONRY)
        storeys = int(rec.get("storeys", 0) or 0)
        height = max(v.co.z for v in obj.data.vertices) if len(obj.data.vertices) else 3.0
        if storeys < 1:
            storeys = max(1, int(round(height / 3.0)))
        scene_tools.set_building_props(
            obj, i, grade=int(rec.get("grade", 0)), material=mat, seed=int(rec.get("seed", 0)),
            vulnerability_class=rec.get("vulnerability_class") or ("B" if mat == ems98.MASONRY else "C"),
            typology=str(rec.get("typology") or "generic"), storeys=storeys,
            storey_height=max(2.0, float(rec.get("storey_height") or height / storeys)))
        obj.qs_building.patterns_json = json.dumps(rec.get("patterns", []))
        extra = {k: v for k, v in rec.items() if k not in _BUILDING_KEYS}
        if extra:
            obj[EXTRA_PROP] = json.dumps(extra)
        objs.append(obj)
    terrain = None
    tsel = np.flatnonzero(bid == 0)
    if len(tsel):
        terrain = _make_object(collection, "terrain", verts, [faces[k] for k in tsel], bid[tsel], surf[tsel], False,
                               porous[tsel] if porous is not None else None)
        terrain.qs_building.role = "TERRAIN"
    origin = [float(x) for x in m.get("origin", [0.0, 0.0, 0.0])]
    crs = m.get("crs")
    if scene is not None and hasattr(scene, "qs_scene"):
        scene.qs_scene.origin = ", ".join(repr(x) for x in origin)  # repr: exact float64
        scene.qs_scene.crs = crs or ""
        scene.qs_scene.epoch = m.get("epoch", "pre") if m.get("epoch") in io_export.EPOCHS else "pre"
    return {"origin": origin, "crs": crs, "epoch": m.get("epoch"), "manifest": m, "buildings": objs,
            "terrain": terrain, "folder": str(folder)}


# --- damage preparation ---------------------------------------------------------------------

_PART_OF_SURFACE = {gm.ROOF: gm.P_ROOF, gm.WALL: gm.P_WALL, gm.GROUND: gm.P_BASE, gm.DEBRIS: gm.P_DEBRIS,
                    gm.INTERIOR: gm.P_INNER}


def prepare_for_damage(obj, interior=True):
    """Make an imported building (local frame: z = 0 ground) damageable: store a box shell
    description (oriented bounding rectangle, flat roof at the eaves = lowest roof vertex),
    split walls at storey levels, label elements from the file's surfaces (roof, wall,
    ground → base) and facades from the normals, and add coarse slabs and inner walls.
    Returns the ShellSpec used."""
    pg = obj.qs_building
    if pg.shell_json:
        return ShellSpec.from_json(pg.shell_json)
    bm = scene_tools.read_bmesh(obj)
    lab = gm.Labels(bm)
    if not bm.verts:
        bm.free()
        raise scene_tools.DamageError(f"{obj.name!r} has no geometry")
    co = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    (x0, y0, z0), (x1, y1, z1) = co.min(axis=0), co.max(axis=0)
    if x1 - x0 < 1.0 or y1 - y0 < 1.0 or z1 - z0 < 1.0:
        bm.free()
        raise scene_tools.DamageError(f"{obj.name!r} is too small to damage (< 1 m in some direction)")
    has_interior = any(f[lab.surface] == gm.INTERIOR for f in bm.faces)
    roof_z = [v.co.z for f in bm.faces if f[lab.surface] == gm.ROOF for v in f.verts]
    eave = min(roof_z) - z0 if roof_z else z1 - z0
    if eave < 2.0:
        eave = z1 - z0
    ns = max(1, min(int(pg.storeys) or 1, int(eave // 2.0) or 1))
    hs = eave / ns
    mat = pg.material
    spec = ShellSpec(footprint=poly2d.rect(x0, y0, x1, y1).tolist(), storeys=ns, storey_height=hs, roof="flat",
                     material=mat, typology=pg.typology or "imported",
                     bay_width=4.5 if mat == ems98.RC else 0.0, extra={"inferred": True, "source": "scene_bundle"})
    for k in range(1, ns):
        walls = [f for f in bm.faces if f[lab.surface] == gm.WALL]
        gm.bisect(bm, walls, (0.0, 0.0, z0 + k * hs), (0.0, 0.0, 1.0))
    bm.normal_update()
    for f in bm.faces:
        s = f[lab.surface]
        f[lab.bid] = int(pg.building_id)
        f[lab.part] = _PART_OF_SURFACE.get(s, gm.P_OTHER)
        f[lab.elem] = 0
        if s == gm.ROOF:
            f[lab.storey] = ns
        elif s == gm.WALL:
            c = f.calc_center_median()
            f[lab.storey] = int(min(ns - 1, max(0, (c.z - z0) // hs)))
            n = f.normal
            f[lab.elem] = int(round((math.atan2(n.y, n.x) + math.pi / 2) / (math.pi / 2))) % 4
        elif s == gm.GROUND:
            f[lab.storey] = 0
        else:
            f[lab.storey] = -1
    scene_tools.write_bmesh(obj, bm)
    bm.free()
    pg.storeys = ns
    pg.storey_height = hs
    pg.shell_json = spec.to_json()
    if interior and not has_interior:  # a source made by the add-on may already have slabs/inner walls
        scene_tools.add_interior(obj)
    return spec


# --- exact export ---------------------------------------------------------------------------

def _arrays(obj):
    me = obj.data
    n = len(me.vertices)
    co = np.empty(n * 3, np.float32)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    M = io_export.world_matrix(obj)
    world = co.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    ref, res = me.attributes.get(REF_ATTR), me.attributes.get(RES_ATTR)
    if ref is not None and res is not None and ref.domain == res.domain == 'POINT' and len(ref.data) == n:
        r = np.empty(n * 3, np.float32)
        ref.data.foreach_get("vector", r)
        d = np.empty(n * 3, np.float32)
        res.data.foreach_get("vector", d)
        same = (r.reshape(-1, 3) == co).all(axis=1)
        world[same] += d.reshape(-1, 3)[same].astype(np.float64)
    me.calc_loop_triangles()
    nt = len(me.loop_triangles)
    tris = np.empty(nt * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    poly = np.empty(nt, np.int32)
    me.loop_triangles.foreach_get("polygon_index", poly)
    attr = me.attributes.get(gm.SURFACE_LAYER)
    if attr is not None and attr.domain == 'FACE' and attr.data_type == 'INT':
        sf = np.empty(len(me.polygons), np.int32)
        attr.data.foreach_get("value", sf)
    else:
        nrm = np.empty(len(me.polygons) * 3, np.float32)
        me.polygons.foreach_get("normal", nrm)
        nz = nrm.reshape(-1, 3)[:, 2]
        sf = np.where(nz > 0.5, gm.ROOF, np.where(nz < -0.5, gm.INTERIOR, gm.WALL))
        if obj.qs_building.role == "TERRAIN":
            sf[:] = gm.GROUND
    pattr = me.attributes.get(gm.POROUS_LAYER)
    porous = np.zeros(len(poly), bool)
    if pattr is not None and pattr.domain == 'FACE' and pattr.data_type == 'INT':
        pf = np.empty(len(me.polygons), np.int32)
        pattr.data.foreach_get("value", pf)
        porous = pf[poly] != 0
    return world, tris.reshape(-1, 3).astype(np.int64), sf[poly].astype(np.int64), porous


def export_bundle(folder, objects, epoch="pre", origin=(0.0, 0.0, 0.0), crs=None, extra=None):
    """Like io_export.export_objects (no depsgraph), but vertices keep the float64 precision
    they had at import when they were not moved, and manifest keys the add-on does not know
    (e.g. CityJSON ``source_id``) are written back. Returns a report."""
    vs, fs, bs, ss, ps, recs = [], [], [], [], [], {}
    off = 0
    objs = sorted((o for o in objects if o.type == 'MESH' and o.qs_building.role in ("BUILDING", "TERRAIN")),
                  key=lambda o: o.name)
    if not objs:
        raise io_export.ExportError("nothing to export: no object has the role Building or Terrain")
    for obj in objs:
        world, tris, surf, porous = _arrays(obj)
        if obj.qs_building.role == "BUILDING":
            b = int(obj.qs_building.building_id)
            if b <= 0:
                raise io_export.ExportError(f"object {obj.name!r} is a building without an ID")
            rec = io_export.building_record(obj, epoch)
            try:
                items = json.loads(obj.get(EXTRA_PROP, "{}")).items()
            except (json.JSONDecodeError, TypeError, AttributeError):
                # the source bundle's extra keys would be lost without a word: refuse instead
                raise io_export.ExportError(f"object {obj.name!r}: property {EXTRA_PROP!r} is not a JSON "
                                            f"object ({str(obj.get(EXTRA_PROP))[:60]!r})") from None
            for k, val in items:
                rec.setdefault(k, val)
            if b in recs:
                raise io_export.ExportError(f"building {b} is on more than one object ({obj.name!r})")
            recs[b] = rec
        else:
            b = 0
        if len(tris):
            a = world[tris[:, 0]]
            area = 0.5 * np.linalg.norm(np.cross(world[tris[:, 1]] - a, world[tris[:, 2]] - a), axis=1)
            keep = area > CONTRACT_MIN_AREA
            tris, surf, porous = tris[keep], surf[keep], porous[keep]
        vs.append(world)
        fs.append(tris + off)
        bs.append(np.full(len(tris), b, np.int32))
        ss.append(surf)
        ps.append(porous)
        off += len(world)
    v, f = np.concatenate(vs), np.concatenate(fs)
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    buildings = [recs[k] for k in sorted(recs)]
    io_export.write_bundle(folder, v[used], remap[f], np.concatenate(bs), np.concatenate(ss), buildings,
                           epoch=epoch, origin=origin, crs=crs, extra=extra, porous=np.concatenate(ps))
    return {"folder": str(folder), "buildings": len(buildings), "faces": len(f), "vertices": len(used)}
