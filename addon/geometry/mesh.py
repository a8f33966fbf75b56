"""BMesh plumbing shared by the shell builder and the damage patterns.

Every face carries integer labels in bmesh face layers (they become int FACE attributes
of the Blender mesh, same names):

- ``qs_surface``      scene-contract surface code: 0 ground, 1 roof, 2 wall, 3 debris, 4 interior,
                      5 vegetation, 6 object
- ``qs_building_id``  building ID (0 = terrain / not a building)
- ``qs_part``         building element (PART_* below) the patterns select by
- ``qs_storey``       storey index of walls/slabs (slab k is the floor of storey k), -1 otherwise
- ``qs_elem``         element index (facade edge, roof plane, gable side)

Functions take a BMesh and numbers; none touches bpy.context.
"""
from __future__ import annotations

import math

import bmesh
import numpy as np
from mathutils import Vector
from mathutils.geometry import tessellate_polygon

SURFACE_LAYER = "qs_surface"
BUILDING_LAYER = "qs_building_id"
PART_LAYER = "qs_part"
STOREY_LAYER = "qs_storey"
ELEM_LAYER = "qs_elem"
LAYER_NAMES = (SURFACE_LAYER, BUILDING_LAYER, PART_LAYER, STOREY_LAYER, ELEM_LAYER)

# Scene-contract surface codes.
GROUND, ROOF, WALL, DEBRIS, INTERIOR = 0, 1, 2, 3, 4
VEGETATION, OBJECT = 5, 6  # trees and hedges; cars and street furniture (building ID 0)
# Optional int face layer: 1 on tree-crown faces a laser ray may pass (PLY `porous`).
POROUS_LAYER = "qs_porous"

# Building elements.
P_OTHER, P_WALL, P_ROOF, P_SLAB, P_INNER, P_GABLE, P_PARAPET, P_CHIMNEY, P_DEBRIS, P_BASE, P_STUB = range(11)
PART_NAMES = {P_OTHER: "other", P_WALL: "wall", P_ROOF: "roof", P_SLAB: "slab", P_INNER: "inner wall",
              P_GABLE: "gable", P_PARAPET: "parapet", P_CHIMNEY: "chimney", P_DEBRIS: "debris",
              P_BASE: "base", P_STUB: "wall stub"}
# Procedural details (geometry/details.py): roof-top details (dormers, chimney stacks,
# skylights, antennas, solar panels, rooftop structures, terraces), eaves overhangs,
# balconies, annexes. Appended so that the values above never change.
P_DETAIL, P_OVERHANG, P_BALCONY, P_ANNEX = range(11, 15)
PART_NAMES.update({P_DETAIL: "roof detail", P_OVERHANG: "overhang", P_BALCONY: "balcony", P_ANNEX: "annex"})

# Triangles at or below this area (m²) are dropped: the scene contract rejects <= 1e-10.
MIN_TRI_AREA = 1e-8


class Labels:
    """The five face layers of a BMesh (created when missing)."""

    __slots__ = ("surface", "bid", "part", "storey", "elem")

    def __init__(self, bm):
        ints = bm.faces.layers.int
        self.surface = ints.get(SURFACE_LAYER) or ints.new(SURFACE_LAYER)
        self.bid = ints.get(BUILDING_LAYER) or ints.new(BUILDING_LAYER)
        self.part = ints.get(PART_LAYER) or ints.new(PART_LAYER)
        self.storey = ints.get(STOREY_LAYER) or ints.new(STOREY_LAYER)
        self.elem = ints.get(ELEM_LAYER) or ints.new(ELEM_LAYER)

    def set(self, face, surface, bid, part=P_OTHER, storey=-1, elem=0):
        face[self.surface] = surface
        face[self.bid] = bid
        face[self.part] = part
        face[self.storey] = storey
        face[self.elem] = elem

    def copy(self, src, dst):
        for lay in (self.surface, self.bid, self.part, self.storey, self.elem):
            dst[lay] = src[lay]


# --- creation --------------------------------------------------------------------------------

def add_polygon(bm, lab: Labels, coords, surface, bid, part=P_OTHER, storey=-1, elem=0, verts=None):
    """New face from 3D coordinates (or existing `verts`); returns the face."""
    vs = verts if verts is not None else [bm.verts.new(tuple(map(float, c))) for c in coords]
    f = bm.faces.new(vs)
    lab.set(f, surface, bid, part, storey, elem)
    return f


def add_mesh(bm, lab: Labels, verts, tris, surface, bid, part=P_OTHER, storey=-1, elem=0):
    """Add an indexed triangle (or polygon) mesh: verts (n, 3), tris list of index tuples.
    Faces with (near) zero area are skipped. Returns the new faces."""
    verts = np.asarray(verts, dtype=np.float64)
    used = sorted({int(i) for t in tris for i in t})
    bv = {i: bm.verts.new((float(verts[i, 0]), float(verts[i, 1]), float(verts[i, 2]))) for i in used}
    faces = []
    for t in tris:
        if len(t) == 3 and tri_area(verts[t[0]], verts[t[1]], verts[t[2]]) <= MIN_TRI_AREA:
            continue
        try:
            f = bm.faces.new([bv[int(i)] for i in t])
        except ValueError:  # duplicate face
            continue
        lab.set(f, surface, bid, part, storey, elem)
        faces.append(f)
    for v in bv.values():
        if not v.link_faces:
            bm.verts.remove(v)
    return faces


def tri_area(a, b, c) -> float:
    a = np.asarray(a, dtype=np.float64)
    return 0.5 * float(np.linalg.norm(np.cross(np.asarray(b) - a, np.asarray(c) - a)))


# --- selection -------------------------------------------------------------------------------

def faces_where(bm, lab: Labels, parts=None, storeys=None, elems=None, bid=None, exclude_parts=None):
    """Faces (in mesh order) whose labels match; None means any."""
    out = []
    for f in bm.faces:
        if parts is not None and f[lab.part] not in parts:
            continue
        if exclude_parts is not None and f[lab.part] in exclude_parts:
            continue
        if storeys is not None and f[lab.storey] not in storeys:
            continue
        if elems is not None and f[lab.elem] not in elems:
            continue
        if bid is not None and f[lab.bid] != bid:
            continue
        out.append(f)
    return out


def verts_of(faces):
    """Unique vertices of faces, in first-seen order (deterministic)."""
    return list(dict.fromkeys(v for f in faces for v in f.verts))


def edges_of(faces):
    return list(dict.fromkeys(e for f in faces for e in f.edges))


# --- cutting ---------------------------------------------------------------------------------

def bisect(bm, faces, co, no, dist=1e-5):
    """Split `faces` along the plane (co, no); faces elsewhere are untouched (an edge they
    share with `faces` may gain a vertex)."""
    if not faces:
        return
    geom = list(faces) + edges_of(faces) + verts_of(faces)
    bmesh.ops.bisect_plane(bm, geom=geom, plane_co=Vector(co), plane_no=Vector(no), dist=dist,
                           clear_inner=False, clear_outer=False)


def inside_all(face, planes, tol=1e-6) -> bool:
    c = face.calc_center_median()
    return all((c - Vector(co)).dot(Vector(no)) < -tol for co, no in planes)


def carve(bm, select, planes):
    """Cut the faces chosen by `select(bm)` with every plane and return those lying on the
    negative side of all planes (dot(x - co, no) < 0): a convex region carved out."""
    for co, no in planes:
        bisect(bm, select(bm), co, no)
    return [f for f in select(bm) if inside_all(f, planes)]


def delete_faces(bm, faces):
    """Delete faces and the edges/vertices only they used."""
    if faces:
        bmesh.ops.delete(bm, geom=list(faces), context='FACES')


def remove_loose(bm):
    loose_e = [e for e in bm.edges if not e.link_faces]
    if loose_e:
        bmesh.ops.delete(bm, geom=loose_e, context='EDGES')
    loose_v = [v for v in bm.verts if not v.link_edges]
    if loose_v:
        bmesh.ops.delete(bm, geom=loose_v, context='VERTS')


def detach(bm, faces):
    """Give `faces` their own vertices (split from neighbours); returns the faces."""
    if not faces:
        return []
    res = bmesh.ops.split(bm, geom=list(faces) + edges_of(faces) + verts_of(faces), use_only_faces=False)
    return [g for g in res["geom"] if isinstance(g, bmesh.types.BMFace)]


def face_frame(face):
    """(origin, u, v, n) of a planar face: u horizontal when the face is not horizontal."""
    n = face.normal.copy()
    if n.length < 1e-12:
        n = Vector((0, 0, 1))
    n.normalize()
    if abs(n.z) < 0.999:
        u = Vector((-n.y, n.x, 0.0))
    else:
        u = (face.verts[1].co - face.verts[0].co)
        u = u - n * u.dot(n)
        if u.length < 1e-9:
            u = Vector((1, 0, 0))
    u.normalize()
    v = n.cross(u)
    v.normalize()
    return face.verts[0].co.copy(), u, v, n


def to_2d(points, frame):
    o, u, v, _ = frame
    return np.array([[(p - o).dot(u), (p - o).dot(v)] for p in points], dtype=np.float64)


def from_2d(xy, frame):
    o, u, v, _ = frame
    return [o + u * float(x) + v * float(y) for x, y in xy]


def cut_holes(bm, lab: Labels, face, holes_2d, frame=None):
    """Replace a planar `face` by triangles covering it minus the hole polygons (2D in the
    face's frame, strictly inside the face and disjoint). Boundary vertices are reused, so
    neighbours stay connected. Returns the new faces."""
    frame = frame or face_frame(face)
    outer = [v.co.copy() for v in face.verts]
    outer_verts = list(face.verts)
    holes3 = [from_2d(h, frame) for h in holes_2d]
    loops = [outer] + holes3
    tris = tessellate_polygon(loops)
    hole_verts = [bm.verts.new(p) for h in holes3 for p in h]
    all_verts = outer_verts + hole_verts
    normal = frame[3]
    new = []
    for t in tris:
        a, b, c = (all_verts[i] for i in t)
        if len({a, b, c}) < 3:
            continue
        if (b.co - a.co).cross(c.co - a.co).length * 0.5 <= MIN_TRI_AREA:
            continue
        if (b.co - a.co).cross(c.co - a.co).dot(normal) < 0:
            a, c = c, a
        try:
            f = bm.faces.new((a, b, c))
        except ValueError:
            continue
        lab.copy(face, f)
        new.append(f)
    bmesh.ops.delete(bm, geom=[face], context='FACES_ONLY')
    for v in hole_verts:
        if not v.link_faces:
            bm.verts.remove(v)
    return new


# --- transforms ------------------------------------------------------------------------------

def rotation_matrix(axis, angle) -> np.ndarray:
    """3x3 rotation by `angle` (radians) about unit `axis` (right-handed)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    x, y, z = a
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def transform_verts(verts, rot=None, pivot=(0, 0, 0), translate=(0, 0, 0)):
    """x' = rot @ (x - pivot) + pivot + translate for the given BMVerts."""
    piv = np.asarray(pivot, dtype=np.float64)
    t = np.asarray(translate, dtype=np.float64)
    for v in verts:
        p = np.array(v.co, dtype=np.float64)
        if rot is not None:
            p = rot @ (p - piv) + piv
        p = p + t
        v.co = Vector(p.tolist())


# --- read-out and measures -------------------------------------------------------------------

def arrays(bm, lab: Labels | None = None):
    """Triangulated arrays of a BMesh: vertices (n, 3) float64, triangles (m, 3) int64,
    surface (m,) uint8, building id (m,) int32, part (m,) int32. Degenerate triangles dropped."""
    lab = lab or Labels(bm)
    bm.verts.index_update()
    verts = np.array([v.co[:] for v in bm.verts], dtype=np.float64).reshape(-1, 3)
    loops = bm.calc_loop_triangles()
    tris = np.array([[l.vert.index for l in lt] for lt in loops], dtype=np.int64).reshape(-1, 3)
    surf = np.array([lt[0].face[lab.surface] for lt in loops], dtype=np.uint8)
    bid = np.array([lt[0].face[lab.bid] for lt in loops], dtype=np.int32)
    part = np.array([lt[0].face[lab.part] for lt in loops], dtype=np.int32)
    if len(tris):
        a = verts[tris[:, 0]]
        ar = 0.5 * np.linalg.norm(np.cross(verts[tris[:, 1]] - a, verts[tris[:, 2]] - a), axis=1)
        keep = ar > MIN_TRI_AREA
        tris, surf, bid, part = tris[keep], surf[keep], bid[keep], part[keep]
    return verts, tris, surf, bid, part


def faces_area(faces) -> float:
    return float(sum(f.calc_area() for f in faces))


def heightfield_volume(faces, base_z=0.0) -> float:
    """Volume between up-facing faces and the plane z = base_z (projected area × mean
    height, sign by facing); for a closed mesh it is the enclosed volume."""
    vol = 0.0
    for f in faces:
        cos = [v.co for v in f.verts]
        for i in range(1, len(cos) - 1):
            a, b, c = cos[0], cos[i], cos[i + 1]
            axy = 0.5 * ((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y))
            vol += axy * ((a.z + b.z + c.z) / 3.0 - base_z)
    return vol
