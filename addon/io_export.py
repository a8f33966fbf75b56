"""Export Blender objects as a QuakeScan scene bundle (scene.json + mesh.ply).

The bundle format is the project's contract (docs/DESIGN.md, "Scene bundle"): binary
little-endian PLY with double vertices relative to the scene origin, triangles with an int
``building_id`` and a uchar ``surface``; scene.json lists the buildings with grade,
material, storeys, typology, applied patterns and seed. This module has its own numpy PLY
writer: the add-on never imports the core package.

Objects take part by their ``qs_building.role``: BUILDING objects are one building each
(ID from the object's properties), TERRAIN objects give building_id 0; others are skipped.
Face surfaces come from the ``qs_surface`` face attribute, or from the face normal when an
object has none (up: roof, down: interior, else wall; terrain: ground). Trees, hedges, cars
and street furniture are TERRAIN objects (building_id 0) with surfaces 5 (vegetation) and
6 (object); an int face attribute ``qs_porous`` = 1 marks tree-crown faces a laser ray may
pass, written as the PLY face property ``porous`` (only when some face is porous, so
scenes without vegetation keep their bytes) with scene.json ``"vegetation":
{"transmission": 0.5}``.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

FORMAT = "quakescan-scene"
VERSION = 1
EPOCHS = ("pre", "post")
SURFACE_ATTR = "qs_surface"
GROUND, ROOF, WALL, DEBRIS, INTERIOR = 0, 1, 2, 3, 4
VEGETATION, OBJECT = 5, 6
SURFACE_CODES = "ground, roof, wall, debris, interior, vegetation, object"
POROUS_ATTR = "qs_porous"
# Share of a laser ray passing one porous crown face (quakescan.formats.scene.DEFAULT_TRANSMISSION).
DEFAULT_TRANSMISSION = 0.5
# The contract rejects faces with area <= 1e-10 m²; drop anything near that.
MIN_AREA = 1e-9


class ExportError(ValueError):
    """The objects cannot be written as a valid scene bundle; the message says why."""


# --- PLY / JSON writers (numpy only) --------------------------------------------------------

def write_ply(path, vertices, faces, building_id, surface, comment="quakescan scene mesh (blender add-on)",
              porous=None):
    """Write the contract's binary little-endian PLY atomically (temp file + os.replace);
    `porous` (per face, optional) adds the face property ``porous``."""
    path = Path(path)
    v = np.ascontiguousarray(vertices, dtype="<f8").reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    m = len(f)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"comment {comment}\n"
              f"element vertex {len(v)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {m}\n"
              "property list uchar int vertex_indices\n"
              "property int building_id\n"
              "property uchar surface\n"
              + ("property uchar porous\n" if porous is not None else "")
              + "end_header\n").encode("ascii")
    fields = [("n", "u1"), ("v", "<i4", (3,)), ("b", "<i4"), ("s", "u1")]
    if porous is not None:
        fields.append(("p", "u1"))
    rec = np.empty(m, dtype=np.dtype(fields))
    rec["n"] = 3
    rec["v"] = f
    rec["b"] = building_id
    rec["s"] = surface
    if porous is not None:
        rec["p"] = porous
    _write_atomically(path, lambda fh: (fh.write(header), fh.write(v.tobytes()), fh.write(rec.tobytes())))


def write_json(path, data):
    text = (json.dumps(data, indent=1) + "\n").encode("utf-8")
    _write_atomically(Path(path), lambda fh: fh.write(text))


def _write_atomically(path: Path, write) -> None:
    """`write(file)` into a temporary of its own beside `path` (created exclusively under an
    unpredictable name: a link planted at a guessable name is never followed), renamed onto
    `path` when complete, removed when not. A `path` that is a symbolic link is refused: the
    bundle is written where it is, not where a link points."""
    if path.is_symlink():
        raise OSError(f"{path}: is a symbolic link; the export writes its own files only, give another folder")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fh.fileno(), 0o666 & ~umask)  # a file as open() makes it, not mkstemp's private 0600
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def parse_origin(text) -> list[float]:
    """'x, y, z' (or 'x y z', or a sequence) → three finite floats (kept as float64)."""
    if isinstance(text, str):
        parts = text.replace(",", " ").split()
    else:
        parts = list(text)
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ExportError(f"origin must be three numbers 'x, y, z', got {text!r}") from None
    if len(vals) != 3 or not all(math.isfinite(x) for x in vals):
        raise ExportError(f"origin must be three finite numbers 'x, y, z', got {text!r}")
    return vals


def write_bundle(folder, vertices, faces, building_id, surface, buildings, epoch="pre", origin=(0.0, 0.0, 0.0),
                 crs=None, extra=None, porous=None, transmission=DEFAULT_TRANSMISSION):
    """Validate and write a bundle: mesh.ply first, scene.json last (both atomic), so a
    folder holding a scene.json is complete. Returns the folder path. `porous` (per face,
    optional): tree-crown faces, written with the scene's `transmission` only when some
    face is porous."""
    folder = Path(folder)
    if epoch not in EPOCHS:
        raise ExportError(f"epoch must be one of {EPOCHS}, got {epoch!r}")
    origin = parse_origin(origin)
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    building_id = np.asarray(building_id, dtype=np.int32)
    surface = np.asarray(surface, dtype=np.int64)
    porous = None if porous is None or not np.any(porous) else np.asarray(porous, dtype=np.uint8) != 0
    _validate(vertices, faces, building_id, surface, buildings, porous)
    if not 0.0 <= float(transmission) <= 1.0:
        raise ExportError(f"vegetation transmission must be in [0, 1], got {transmission!r}")
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "mesh.ply", vertices, faces, building_id, surface.astype(np.uint8),
              porous=None if porous is None else porous.astype(np.uint8))
    manifest = {"format": FORMAT, "version": VERSION, "epoch": epoch, "origin": origin, "crs": crs or None,
                "units": "m", "mesh": "mesh.ply", "buildings": buildings}
    if porous is not None:
        manifest["vegetation"] = {"transmission": float(transmission)}
    if extra:
        manifest.update(extra)
    write_json(folder / "scene.json", manifest)
    return folder


def _validate(v, f, bid, surf, buildings, porous=None):
    if not np.isfinite(v).all():
        bad = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise ExportError(f"vertex {bad} has NaN/inf coordinates")
    if len(f) and ((f < 0) | (f >= len(v))).any():
        raise ExportError("a face points at a vertex that does not exist")
    if len(f):
        a = v[f[:, 0]]
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - a, v[f[:, 2]] - a), axis=1)
        if (area <= 1e-10).any():
            raise ExportError(f"{int((area <= 1e-10).sum())} degenerate faces left after cleaning")
    if ((surf < 0) | (surf > OBJECT)).any():
        bad = int(np.flatnonzero((surf < 0) | (surf > OBJECT))[0])
        raise ExportError(f"face {bad} has surface code {int(surf[bad])}; valid codes are 0..6 "
                          f"({SURFACE_CODES})")
    not_building = (surf >= VEGETATION) & (bid != 0)
    if not_building.any():
        bad = int(np.flatnonzero(not_building)[0])
        raise ExportError(f"face {bad} is vegetation or an object on building {int(bid[bad])}: trees, cars and "
                          "street furniture must be Terrain objects (building ID 0)")
    if porous is not None and (porous & (surf != VEGETATION)).any():
        bad = int(np.flatnonzero(porous & (surf != VEGETATION))[0])
        raise ExportError(f"face {bad} is porous but not vegetation (surface {int(surf[bad])})")
    ids = [b["id"] for b in buildings]
    if len(set(ids)) != len(ids):
        raise ExportError("duplicate building IDs in the manifest")
    for b in buildings:
        if not isinstance(b["id"], int) or b["id"] <= 0:
            raise ExportError(f"building ID must be an integer > 0, got {b['id']!r}")
        if not 0 <= b["grade"] <= 5:
            raise ExportError(f"building {b['id']}: grade must be 0..5, got {b['grade']}")
    mesh_ids = set(np.unique(bid).tolist()) - {0}
    missing = sorted(set(ids) - mesh_ids)
    if missing:
        raise ExportError(f"buildings {missing[:10]} have no faces")
    unknown = sorted(mesh_ids - set(ids))
    if unknown:
        raise ExportError(f"faces carry building IDs {unknown[:10]} that no building object declares")


# --- Blender objects → arrays ---------------------------------------------------------------

def world_matrix(obj) -> np.ndarray:
    """4x4 object-to-world matrix from location/rotation/scale and parents (float64).
    Unlike obj.matrix_world it does not wait for a depsgraph update (constraints and
    drivers are ignored; pass a depsgraph to export_objects to include them)."""
    M = np.array(obj.matrix_basis, dtype=np.float64)
    if obj.parent is not None:
        M = world_matrix(obj.parent) @ np.array(obj.matrix_parent_inverse, dtype=np.float64) @ M
    return M


def _mesh_arrays(obj, depsgraph=None):
    """World-space vertices (float64), triangles, per-triangle surface code or None."""
    if depsgraph is not None:
        ob = obj.evaluated_get(depsgraph)
        me = ob.to_mesh()
    else:
        ob, me = obj, obj.data
    try:
        n = len(me.vertices)
        co = np.empty(n * 3, dtype=np.float32)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3).astype(np.float64)
        M = np.array(ob.matrix_world, dtype=np.float64) if depsgraph is not None else world_matrix(obj)
        world = co @ M[:3, :3].T + M[:3, 3]
        me.calc_loop_triangles()
        nt = len(me.loop_triangles)
        tris = np.empty(nt * 3, dtype=np.int32)
        me.loop_triangles.foreach_get("vertices", tris)
        poly = np.empty(nt, dtype=np.int32)
        me.loop_triangles.foreach_get("polygon_index", poly)
        surf_face = None
        attr = me.attributes.get(SURFACE_ATTR)
        if attr is not None and attr.domain == 'FACE' and attr.data_type == 'INT':
            surf_face = np.empty(len(me.polygons), dtype=np.int32)
            attr.data.foreach_get("value", surf_face)
        porous_face = None
        attr = me.attributes.get(POROUS_ATTR)
        if attr is not None and attr.domain == 'FACE' and attr.data_type == 'INT':
            porous_face = np.empty(len(me.polygons), dtype=np.int32)
            attr.data.foreach_get("value", porous_face)
        normals = None
        if surf_face is None:
            normals = np.empty(len(me.polygons) * 3, dtype=np.float32)
            me.polygons.foreach_get("normal", normals)
            normals = normals.reshape(-1, 3).astype(np.float64) @ np.linalg.inv(M[:3, :3])  # normal transform
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        return world, tris.reshape(-1, 3).astype(np.int64), poly, surf_face, normals, porous_face
    finally:
        if depsgraph is not None:
            ob.to_mesh_clear()


def _infer_surface(normals, terrain: bool):
    if terrain:
        return np.full(len(normals), GROUND, np.int64)
    nz = normals[:, 2]
    return np.where(nz > 0.5, ROOF, np.where(nz < -0.5, INTERIOR, WALL)).astype(np.int64)


def building_record(obj, epoch: str) -> dict:
    """The manifest entry for a building object (see props.DAMAGE_PG_building)."""
    pg = obj.qs_building
    try:
        patterns = json.loads(pg.patterns_json or "[]")
    except json.JSONDecodeError:
        raise ExportError(f"object {obj.name!r}: applied patterns are not valid JSON") from None
    grade = int(pg.grade)
    rec = {"id": int(pg.building_id), "grade": grade, "material": pg.material, "storeys": int(pg.storeys),
           "typology": pg.typology or "generic", "patterns": patterns, "seed": int(pg.seed),
           "vulnerability_class": pg.vulnerability_class, "storey_height": round(float(pg.storey_height), 4)}
    if epoch == "pre":
        # A pre-event scene shows the intact building: its grade is 0 whatever is planned.
        rec["grade"] = 0
        rec["patterns"] = []
        if grade > 0:
            rec["planned_grade"] = grade
    return rec


def collect(objects, epoch="pre", depsgraph=None, with_porous=False):
    """Arrays and manifest entries of the BUILDING and TERRAIN objects among `objects`.
    Returns (vertices, faces, building_id, surface, buildings, report), and with
    `with_porous` also the per-face porous flags (tree crowns) as a seventh item."""
    vs, fs, bs, ss, ps = [], [], [], [], []
    buildings = {}
    owner = {}
    offset = 0
    dropped = 0
    objects = sorted((o for o in objects if o.type == 'MESH'), key=lambda o: o.name)
    for obj in objects:
        role = obj.qs_building.role
        if role not in ("BUILDING", "TERRAIN"):
            continue
        world, tris, poly, surf_face, normals, porous_face = _mesh_arrays(obj, depsgraph)
        if surf_face is not None:
            surf = surf_face[poly].astype(np.int64)
        else:
            surf = _infer_surface(normals, role == "TERRAIN")[poly]
        porous = porous_face[poly] != 0 if porous_face is not None else np.zeros(len(poly), bool)
        if role == "BUILDING":
            bid = int(obj.qs_building.building_id)
            if bid <= 0:
                raise ExportError(f"object {obj.name!r} is a building without an ID (assign IDs first)")
            rec = building_record(obj, epoch)
            if bid in buildings:
                prev = buildings[bid]
                if (prev["grade"], prev["material"]) != (rec["grade"], rec["material"]):
                    raise ExportError(f"building {bid} is on objects {owner[bid]!r} and {obj.name!r} "
                                      "with different grade or material")
            else:
                buildings[bid] = rec
                owner[bid] = obj.name
            if not len(tris):
                continue
        else:
            bid = 0
        if len(tris):
            a = world[tris[:, 0]]
            area = 0.5 * np.linalg.norm(np.cross(world[tris[:, 1]] - a, world[tris[:, 2]] - a), axis=1)
            keep = area > MIN_AREA
            dropped += int((~keep).sum())
            tris, surf, porous = tris[keep], surf[keep], porous[keep]
        vs.append(world)
        fs.append(tris + offset)
        bs.append(np.full(len(tris), bid, np.int32))
        ss.append(surf)
        ps.append(porous)
        offset += len(world)
    if not vs:
        raise ExportError("nothing to export: no object has the role Building or Terrain")
    v = np.concatenate(vs)
    f = np.concatenate(fs) if fs else np.zeros((0, 3), np.int64)
    b = np.concatenate(bs)
    s = np.concatenate(ss)
    p = np.concatenate(ps)
    # drop unused vertices
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    v = v[used]
    f = remap[f]
    recs = [buildings[k] for k in sorted(buildings)]
    report = {"objects": len(objects), "buildings": len(recs), "faces": int(len(f)), "vertices": int(len(v)),
              "dropped_degenerate": dropped}
    if with_porous:
        return v, f, b, s, recs, report, p
    return v, f, b, s, recs, report


def export_objects(folder, objects, epoch="pre", origin=(0.0, 0.0, 0.0), crs=None, depsgraph=None, extra=None):
    """Export BUILDING/TERRAIN objects as a scene bundle in `folder`; returns a report."""
    v, f, b, s, recs, report, porous = collect(objects, epoch, depsgraph, with_porous=True)
    write_bundle(folder, v, f, b, s, recs, epoch=epoch, origin=origin, crs=crs, extra=extra, porous=porous)
    report["folder"] = str(folder)
    return report
