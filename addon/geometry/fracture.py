"""Fracture: a building's structural elements as solids, cut into convex Voronoi shards.

Pure maths (numpy only, no bpy): what Blender's Cell Fracture does, where each cell is the
element clipped by the half-spaces of its Voronoi neighbours, here on explicit convex
polyhedra so that volumes and containment are exact and testable without Blender.

A convex polyhedron is a list of planar faces ((k, 3) float64 arrays, counter-clockwise
seen from outside) with one integer tag per face: ``-1 - i`` for a face on the element's
i-th bounding plane, ``j >= 0`` for a face cut by the bisector towards Voronoi seed j (so
the caller knows which shard lies on the other side of a fracture face).

Elements (``building_elements``) are built from a ``ShellSpec``, the add-on's description of
a procedural building, as solids that do not overlap (a user mesh or an imported shell has
no such description: mesh_elements.py builds its elements from its faces):

- outer walls per storey and facade, extruded inwards by the wall thickness, mitred at the
  corners, from the slab below to the underside of the slab (or flat roof) above: slabs bear
  on the walls, so that the stack stands under gravity alone; gable triangles likewise,
  under the roof planes; parapets on top of the flat roof over the walls;
- floor slabs (and a flat roof) under their level over the whole footprint (cut into convex
  pieces when it is not convex); their edges are the facade between two storeys' walls;
- pitched roof planes extruded downwards, each trimmed where it meets its neighbours
  (ridge, hips), above the eaves and, for gables, inside the gable walls;
- inner walls (the shell's cross and spine walls) between the slabs, inside the outer
  walls, the spine cut where cross walls pass.

Assumed sizes (engineering estimates, like the catalogue's; editable in ``MATERIAL``): wall
thickness 0.4 m masonry, 0.25 m reinforced concrete (infill and frame smeared into one
wall); slabs and roofs 0.2 m; inner walls 0.15 m; densities 1,900 and 2,400 kg/m³. Cells are
smaller where the damage starts: masonry breaks into pieces of ~0.6 m there and ~2 m far
from it, RC into ~1 m and ~3 m slabs (RC elements hold together in larger parts).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import poly2d

SURFACE_ROOF, SURFACE_WALL, SURFACE_INTERIOR = 1, 2, 4
# Building element codes: the same values as geometry.mesh's P_* (kept numeric here so this
# module needs no bmesh).
P_WALL, P_ROOF, P_SLAB, P_INNER, P_GABLE, P_PARAPET = 1, 2, 3, 4, 5, 6

MATERIAL = {
    "masonry": {"wall": 0.4, "slab": 0.2, "roof": 0.2, "inner": 0.15, "parapet": 0.25,
                "density": 1900.0, "cell_near": 0.6, "cell_far": 2.0},
    "reinforced_concrete": {"wall": 0.25, "slab": 0.2, "roof": 0.2, "inner": 0.15, "parapet": 0.2,
                            "density": 2400.0, "cell_near": 1.0, "cell_far": 3.0},
}
CELL_FALLOFF = 4.0  # m: distance over which cells grow from the near to the far size
EPS = 1e-9


# --- convex polyhedra ------------------------------------------------------------------------

@dataclass
class Polyhedron:
    faces: list  # [(k, 3) float64], counter-clockwise seen from outside
    tags: list  # one int per face (see module docstring)

    @property
    def vertices(self) -> np.ndarray:
        return np.unique(np.round(np.concatenate(self.faces), 12), axis=0)

    def volume(self) -> float:
        return polyhedron_volume(self.faces)

    def centroid(self) -> np.ndarray:
        return polyhedron_centroid(self.faces)

    def contains(self, pts, tol=1e-9) -> np.ndarray:
        """(m,) bool: points inside or on the boundary."""
        q = np.atleast_2d(np.asarray(pts, dtype=np.float64))
        ok = np.ones(len(q), bool)
        for f in self.faces:
            n = face_normal(f)
            ok &= (q - f[0]) @ n <= tol
        return ok


def cross(a, b) -> np.ndarray:
    """np.cross of (..., 3) arrays with the same arithmetic (the same bits), without its
    generic checks and axis moves: fracturing a building calls it tens of thousands of times."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    cp = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    np.multiply(a1, b2, out=cp[..., 0])
    cp[..., 0] -= a2 * b1
    np.multiply(a2, b0, out=cp[..., 1])
    cp[..., 1] -= a0 * b2
    np.multiply(a0, b1, out=cp[..., 2])
    cp[..., 2] -= a1 * b0
    return cp


def norm(v) -> float:
    """np.linalg.norm of a vector (the same bits: the square root of v.dot(v)), faster."""
    return math.sqrt(float(v.dot(v)))


def face_normal(f) -> np.ndarray:
    """Unit normal of a planar polygon (Newell's method)."""
    n = cross(f, np.roll(f, -1, axis=0)).sum(axis=0)
    L = norm(n)
    return n / L if L > 0 else n


def polyhedron_volume(faces) -> float:
    r = np.concatenate(faces).mean(axis=0)
    v = 0.0
    for f in faces:
        a = f[0] - r
        b, c = f[1:-1] - r, f[2:] - r
        v += float(np.einsum("j,ij->", a, cross(b, c)))
    return v / 6.0


def polyhedron_centroid(faces) -> np.ndarray:
    r = np.concatenate(faces).mean(axis=0)
    vol, acc = 0.0, np.zeros(3)
    for f in faces:
        a = f[0] - r
        b, c = f[1:-1] - r, f[2:] - r
        dv = np.einsum("j,ij->i", a, cross(b, c)) / 6.0
        vol += float(dv.sum())
        acc += (dv[:, None] * (a + b + c) / 4.0).sum(axis=0)
    return r + acc / vol if vol > 0 else r


def box(lo, hi) -> Polyhedron:
    """Axis-aligned box; tags -1 … -6 for -x, +x, -y, +y, -z, +z."""
    x0, y0, z0 = map(float, lo)
    x1, y1, z1 = map(float, hi)
    P = np.array
    faces = [P([[x0, y0, z0], [x0, y0, z1], [x0, y1, z1], [x0, y1, z0]]),
             P([[x1, y0, z0], [x1, y1, z0], [x1, y1, z1], [x1, y0, z1]]),
             P([[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]]),
             P([[x0, y1, z0], [x0, y1, z1], [x1, y1, z1], [x1, y1, z0]]),
             P([[x0, y0, z0], [x0, y1, z0], [x1, y1, z0], [x1, y0, z0]]),
             P([[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])]
    return Polyhedron([f.astype(np.float64) for f in faces], [-1, -2, -3, -4, -5, -6])


def clip(poly: Polyhedron | None, co, no, tag: int) -> Polyhedron | None:
    """The part of `poly` where dot(x - co, no) <= 0 (None when empty); the new face on the
    plane gets `tag`."""
    if poly is None:
        return None
    co = np.asarray(co, dtype=np.float64)
    no = np.asarray(no, dtype=np.float64)
    no = no / np.linalg.norm(no)
    allv = np.concatenate(poly.faces)
    scale = max(1.0, float(np.abs(allv - co).max()))
    eps = EPS * scale
    d_all = (allv - co) @ no
    if d_all.max() <= eps:
        return poly
    if d_all.min() >= -eps:
        return None
    faces, tags, cap = [], [], []
    for f, t in zip(poly.faces, poly.tags):
        d = (f - co) @ no
        if d.max() <= eps:
            faces.append(f)
            tags.append(t)
            cap.extend(f[np.abs(d) <= eps])
            continue
        if d.min() >= -eps:
            continue
        out = []
        n = len(f)
        for i in range(n):
            a, b = f[i], f[(i + 1) % n]
            da, db = d[i], d[(i + 1) % n]
            if da <= eps:
                out.append(a)
                if da >= -eps:
                    cap.append(a)
            if (da < -eps and db > eps) or (da > eps and db < -eps):
                p = a + (da / (da - db)) * (b - a)
                out.append(p)
                cap.append(p)
        out = _dedupe3(np.array(out), eps)
        if len(out) >= 3:
            faces.append(out)
            tags.append(t)
    if len(cap) >= 3:
        c = _order_on_plane(_unique_points(np.array(cap), eps * 10), no)
        if len(c) >= 3:
            faces.append(c)
            tags.append(int(tag))
    if len(faces) < 4:
        return None
    return Polyhedron(faces, tags)


def _dedupe3(p, eps):
    keep = [0]
    for i in range(1, len(p)):
        if norm(p[i] - p[keep[-1]]) > eps:
            keep.append(i)
    if len(keep) > 1 and norm(p[keep[-1]] - p[keep[0]]) <= eps:
        keep.pop()
    return p[keep]


def _unique_points(p, eps):
    out = []
    for q in p:
        if not any(norm(q - r) <= eps for r in out):
            out.append(q)
    return np.array(out)


def _order_on_plane(p, no):
    """Points of a convex polygon on a plane, counter-clockwise seen from the +no side."""
    c = p.mean(axis=0)
    u = np.cross(no, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(no, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(no, u)
    ang = np.arctan2((p - c) @ v, (p - c) @ u)
    return p[np.argsort(ang, kind="stable")]


def from_planes(planes, lo, hi) -> Polyhedron | None:
    """Intersection of half-spaces dot(x - co, no) <= 0 (within the box lo..hi); plane i's
    face gets tag -1 - i."""
    poly = box(np.asarray(lo) - 1.0, np.asarray(hi) + 1.0)
    poly.tags = [-1000] * 6  # faces of the bounding box: must all be cut away
    for i, (co, no) in enumerate(planes):
        poly = clip(poly, co, no, -1 - i)
        if poly is None:
            return None
    if any(t == -1000 for t in poly.tags):
        raise ValueError("element is not bounded by its planes")
    return poly


# --- Voronoi cells -----------------------------------------------------------------------------

def voronoi_cells(solid: Polyhedron, seeds) -> list:
    """[(seed index, cell)]: `solid` cut into the Voronoi cells of `seeds` ((n, 3)); cells
    that miss the solid are left out. Faces cut by the bisector towards seed j get tag j."""
    s = np.asarray(seeds, dtype=np.float64).reshape(-1, 3)
    out = []
    for i in range(len(s)):
        d = np.linalg.norm(s - s[i], axis=1)
        order = np.argsort(d, kind="stable")
        cell = solid
        reach = float(np.linalg.norm(np.concatenate(cell.faces) - s[i], axis=1).max())
        for j in order:
            if j == i:
                continue
            if d[j] / 2.0 > reach:
                break  # every further bisector lies beyond the cell
            if d[j] < 1e-12:
                if j < i:  # duplicate seed: the first one owns the cell
                    cell = None
                    break
                continue
            no = s[j] - s[i]
            cell = clip(cell, (s[i] + s[j]) / 2.0, no, int(j))
            if cell is None:
                break
            reach = float(np.linalg.norm(np.concatenate(cell.faces) - s[i], axis=1).max())
        if cell is not None:
            out.append((i, cell))
    return out


def cell_size(points, origin, near, far, falloff=CELL_FALLOFF) -> np.ndarray:
    """Local cell size: `near` at the damage origin, growing to `far` with distance."""
    d = np.linalg.norm(np.atleast_2d(points) - np.asarray(origin, dtype=np.float64), axis=1)
    return near + (far - near) * (1.0 - np.exp(-d / falloff))


def seed_points(solid: Polyhedron, rng, origin, near, far, max_cells=60, candidates=400) -> np.ndarray:
    """Seeds inside `solid`, denser near `origin`: their number is the solid's volume over
    the local cell volume (thin elements, such as walls and slabs, count their area instead),
    at most `max_cells`; at least one."""
    v = np.concatenate(solid.faces)
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = np.sort(hi - lo)
    vol = solid.volume()
    pts = np.zeros((0, 3))
    for _ in range(20):  # rejection sampling in the bounding box
        q = lo + rng.random((candidates, 3)) * (hi - lo)
        pts = np.concatenate([pts, q[solid.contains(q)]])
        if len(pts) >= candidates:
            break
    if not len(pts):
        return ((lo + hi) / 2.0)[None]
    pts = pts[:candidates]
    c = cell_size(pts, origin, near, far)
    thin = np.minimum(ext[0], c)
    dens = 1.0 / (thin * c * c)
    n = int(np.clip(round(vol * float(dens.mean())), 1, min(max_cells, len(pts))))
    if n == 1:
        return pts[:1]
    idx = rng.choice(len(pts), size=n, replace=False, p=dens / dens.sum())
    return _mid_surface(pts[np.sort(idx)], v)


def _mid_surface(seeds, verts, thin=0.6):
    """Seeds of a thin element (a wall, slab or roof plane: thinner than `thin` across) moved
    onto its mid-surface, so that every crack runs through the thickness: shards are prisms
    across the element, not wedges (which stack badly and which masonry and RC do not make)."""
    c = verts.mean(axis=0)
    w, vec = np.linalg.eigh(np.cov((verts - c).T))
    n = vec[:, 0]
    span = (verts - c) @ n
    if float(span.max() - span.min()) >= thin:
        return seeds
    mid = c + n * (span.max() + span.min()) / 2.0
    return seeds - np.outer((seeds - mid) @ n, n)


# --- building elements ---------------------------------------------------------------------------

@dataclass
class Element:
    """One structural element: a convex solid and its labels."""
    part: int
    storey: int
    elem: int
    surface: int
    planes: list  # [(co, no)]: the solid is where dot(x - co, no) <= 0 for all
    solid: Polyhedron | None = None
    plane_surface: dict = field(default_factory=dict)  # plane index -> surface, where not `surface`

    def face_surface(self, tag: int) -> int:
        """Surface code of a shard face with this tag (fracture faces: the element's)."""
        return self.plane_surface.get(-1 - tag, self.surface) if tag < 0 else self.surface

    @property
    def volume(self) -> float:
        return self.solid.volume() if self.solid is not None else 0.0


def _pl(co, no):
    return (np.asarray(co, dtype=np.float64), np.asarray(no, dtype=np.float64))


def z_between(z0, z1):
    return [_pl((0, 0, z0), (0, 0, -1)), _pl((0, 0, z1), (0, 0, 1))]


def inset_corners(poly, t) -> np.ndarray:
    """Vertices of the counter-clockwise polygon offset inwards by t (the walls' inner
    corners)."""
    p = poly2d.ccw(poly)
    n = len(p)
    out = []
    for i in range(n):
        a, v, b = p[i - 1], p[i], p[(i + 1) % n]
        d0 = (v - a) / np.linalg.norm(v - a)
        d1 = (b - v) / np.linalg.norm(b - v)
        n0 = np.array([-d0[1], d0[0]])  # inward (left) normals
        n1 = np.array([-d1[1], d1[0]])
        den = d0[0] * d1[1] - d0[1] * d1[0]
        if abs(den) < 1e-9:
            out.append(v + t * n0)
            continue
        # a0 + s d0 = a1 + u d1 with a0 = v + t n0, a1 = v + t n1
        w = (v + t * n1) - (v + t * n0)
        s = (w[0] * d1[1] - w[1] * d1[0]) / den
        out.append(v + t * n0 + s * d0)
    return np.array(out)


def _wall_planes(p, inner, i, t):
    """Half-spaces of the wall prism along footprint edge i (outer face on the edge, inner
    face t inwards, mitred through the inner corners)."""
    n = len(p)
    a, b = p[i], p[(i + 1) % n]
    d = (b - a) / np.linalg.norm(b - a)
    out_n = np.array([d[1], -d[0]])
    planes = [_pl((a[0], a[1], 0), (out_n[0], out_n[1], 0)),
              _pl((a[0] - t * out_n[0], a[1] - t * out_n[1], 0), (-out_n[0], -out_n[1], 0))]
    mid = (a + b) / 2 - 0.5 * t * out_n
    for v, c in ((a, inner[i]), (b, inner[(i + 1) % n])):
        m = c - v
        no = np.array([m[1], -m[0]])
        if float(np.dot(mid - v, no)) > 0:
            no = -no
        planes.append(_pl((v[0], v[1], 0), (no[0], no[1], 0)))
    return planes


def _roof_planes(spec):
    """Outward (up) planes of a pitched roof as (point, unit normal), and whether gables end it."""
    t = spec.roof_type
    x0, y0, x1, y1 = spec.bbox
    H = spec.eave_height
    tp = math.tan(math.radians(spec.roof_pitch))
    out = []

    def add(point, slope_dir):  # roof rises along slope_dir (unit, horizontal) with tan = tp
        g = np.array([slope_dir[0] * tp, slope_dir[1] * tp, -1.0])  # grad of (h(x, y) - z)
        out.append(_pl(point, -g / np.linalg.norm(g)))
    add((x0, y0, H), (0, 1))
    add((x0, y1, H), (0, -1))
    if t == "hip":
        add((x0, y0, H), (1, 0))
        add((x1, y0, H), (-1, 0))
    return out


def convex_pieces(poly) -> list:
    """A simple polygon cut into convex counter-clockwise pieces (ear clipping, then
    neighbouring triangles merged while the union stays convex: Hertel–Mehlhorn)."""
    p = _clean_polygon(poly2d.ccw(np.asarray(poly, dtype=np.float64)))
    if _is_convex(p):
        return [p]
    idx = list(range(len(p)))
    tris = []
    guard = 0
    while len(idx) > 3 and guard < 10000:
        guard += 1
        m = len(idx)
        for k in range(m):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
            a, b, c = p[i0], p[i1], p[i2]
            if _cross2(b - a, c - b) <= 1e-12:
                continue
            tri = np.array([a, b, c])
            if any(poly2d.contains(tri, [p[j]])[0] for j in idx if j not in (i0, i1, i2)):
                continue
            tris.append([i0, i1, i2])
            idx.pop(k)
            break
        else:
            break
    tris.append(idx[:3])
    pieces = [list(t) for t in tris]
    merged = True
    while merged:
        merged = False
        for a in range(len(pieces)):
            for b in range(a + 1, len(pieces)):
                u = _merge(pieces[a], pieces[b])
                if u is not None and _is_convex(p[u]):
                    pieces[a] = u
                    pieces.pop(b)
                    merged = True
                    break
            if merged:
                break
    return [p[q] for q in pieces]


def _clean_polygon(p):
    keep = []
    n = len(p)
    for i in range(n):
        a, v, b = p[i - 1], p[i], p[(i + 1) % n]
        if abs(_cross2(v - a, b - v)) > 1e-12 or np.dot(v - a, b - v) < 0:
            keep.append(i)
    return p[keep]


def _cross2(u, v) -> float:
    return float(u[0] * v[1] - u[1] * v[0])


def _is_convex(p) -> bool:
    n = len(p)
    return all(_cross2(p[(i + 1) % n] - p[i], p[(i + 2) % n] - p[(i + 1) % n]) >= -1e-12 for i in range(n))


def _merge(a, b):
    """Union of two counter-clockwise index polygons sharing one edge (None otherwise)."""
    na, nb = len(a), len(b)
    for i in range(na):
        u, v = a[i], a[(i + 1) % na]
        for j in range(nb):
            if b[j] == v and b[(j + 1) % nb] == u:
                return a[:i + 1] + [b[(j + k) % nb] for k in range(2, nb)] + a[i + 1:]
    return None


def _facade_planes(poly, piece) -> dict:
    """{edge index of `piece`: wall surface} for the piece's edges on the footprint outline
    (a slab's edge between two storeys' walls is facade)."""
    out = {}
    n = len(piece)
    for i in range(n):
        a, b = piece[i], piece[(i + 1) % n]
        probe = np.array([a, b, (a + b) / 2])
        if float(poly2d.boundary_distance(poly, probe).max()) < 1e-7:
            out[i] = SURFACE_WALL
    return out


def _prism_planes(piece, z0, z1):
    n = len(piece)
    planes = []
    for i in range(n):
        a, b = piece[i], piece[(i + 1) % n]
        d = (b - a) / np.linalg.norm(b - a)
        planes.append(_pl((a[0], a[1], 0), (d[1], -d[0], 0)))
    return planes + z_between(z0, z1)


def building_elements(spec, material=None) -> list:
    """The structural elements of a shell as non-overlapping convex solids (module docstring).
    Chimneys and the roof and facade details are not elements (see physics.py)."""
    m = MATERIAL[material or spec.material]
    tw, ts, tr, ti, tpp = m["wall"], m["slab"], m["roof"], m["inner"], m["parapet"]
    p = poly2d.ccw(spec.poly)
    n = len(p)
    ns = spec.storeys
    H = spec.eave_height
    inner = inset_corners(p, tw)
    lo = np.array([p[:, 0].min(), p[:, 1].min(), 0.0])
    hi = np.array([p[:, 0].max(), p[:, 1].max(), spec.height + 1.0])
    roof_type = spec.roof_type
    gables = set(spec.gable_edges())
    els = []
    for i in range(n):
        wp = _wall_planes(p, inner, i, tw)
        for k in range(ns):
            top = spec.z_level(k + 1) - (tr if (k + 1 == ns and roof_type == "flat") else ts)
            els.append(Element(P_WALL, k, i, SURFACE_WALL, wp + z_between(spec.z_level(k), top)))
        if i in gables:
            els.append(Element(P_GABLE, ns, i, SURFACE_WALL, wp + [_pl((0, 0, H), (0, 0, -1))] + _roof_planes(spec)))
    ph = spec.effective_parapet_height if roof_type == "flat" else 0.0
    if ph > 0:
        pin = inset_corners(p, tpp)
        for i in range(n):
            els.append(Element(P_PARAPET, ns, i, SURFACE_WALL, _wall_planes(p, pin, i, tpp) + z_between(H, H + ph)))
    pieces = convex_pieces(p)
    top_slab = ns if roof_type != "flat" else ns - 1
    for k in range(1, top_slab + 1):
        z = spec.z_level(k)
        for j, piece in enumerate(pieces):
            els.append(Element(P_SLAB, k, j, SURFACE_INTERIOR, _prism_planes(piece, z - ts, z),
                               plane_surface=_facade_planes(p, piece)))
    if roof_type == "flat":
        for j, piece in enumerate(pieces):
            ps = _facade_planes(p, piece)
            ps[len(piece) + 1] = SURFACE_ROOF  # the top
            els.append(Element(P_ROOF, ns, j, SURFACE_INTERIOR, _prism_planes(piece, H - tr, H), plane_surface=ps))
    else:
        rp = _roof_planes(spec)
        x0, y0, x1, y1 = spec.bbox
        ends = []
        if roof_type == "gable":
            ends = [_pl((x0 + tw, 0, 0), (-1, 0, 0)), _pl((x1 - tw, 0, 0), (1, 0, 0))]
        box_planes = [_pl((x0, 0, 0), (-1, 0, 0)), _pl((x1, 0, 0), (1, 0, 0)),
                      _pl((0, y0, 0), (0, -1, 0)), _pl((0, y1, 0), (0, 1, 0)), _pl((0, 0, H), (0, 0, -1))]
        for e, (co, no) in enumerate(rp):
            planes = [(co, no), (co - tr * no, -no)]
            for co2, no2 in rp:
                if co2 is co:
                    continue
                # closer to its own plane than to the other: s_other - s_own <= 0
                dn = no2 - no
                off = float(np.dot(co2, no2) - np.dot(co, no))
                k = int(np.argmax(np.abs(dn)))
                point = np.zeros(3)
                point[k] = off / dn[k]
                planes.append(_pl(point, dn))
            els.append(Element(P_ROOF, ns, e, SURFACE_ROOF, planes + box_planes + ends,
                               plane_surface={1: SURFACE_INTERIOR}))
    els += _inner_wall_elements(spec, inner, ti, ts, tr)
    for el in els:
        el.solid = from_planes(el.planes, lo, hi)
    return [el for el in els if el.solid is not None and el.volume > 1e-9]


def _inner_wall_elements(spec, inner, ti, ts, tr):
    s = spec.inner_wall_spacing
    x0, y0, x1, y1 = spec.bbox
    xs = []
    if s > 0:
        L = x1 - x0
        k = int(L // s)
        xs = [x0 + L * j / (k + 1) for j in range(1, k + 1)]
    segs = []  # (x or y fixed, along-axis interval, axis)
    for x in xs:
        for t0, t1 in poly2d.line_segments_inside(inner, (x, y0 - 1.0), (0.0, 1.0)):
            segs.append(("x", x, y0 - 1.0 + t0, y0 - 1.0 + t1))
    if spec.spine_wall and (y1 - y0) >= 8.0:
        y = (y0 + y1) / 2
        for t0, t1 in poly2d.line_segments_inside(inner, (x0 - 1.0, y), (1.0, 0.0)):
            a, b = x0 - 1.0 + t0, x0 - 1.0 + t1
            cuts = sorted(x for x in xs if a < x < b)
            bounds = [a] + [c for x in cuts for c in (x - ti / 2, x + ti / 2)] + [b]
            for u, v in zip(bounds[::2], bounds[1::2]):
                if v - u > 0.05:
                    segs.append(("y", y, u, v))
    ns = spec.storeys
    out = []
    for e, (axis, c, u, v) in enumerate(segs):
        if v - u < 0.5:
            continue
        if axis == "x":
            side = [_pl((c - ti / 2, 0, 0), (-1, 0, 0)), _pl((c + ti / 2, 0, 0), (1, 0, 0)),
                    _pl((0, u, 0), (0, -1, 0)), _pl((0, v, 0), (0, 1, 0))]
        else:
            side = [_pl((0, c - ti / 2, 0), (0, -1, 0)), _pl((0, c + ti / 2, 0), (0, 1, 0)),
                    _pl((u, 0, 0), (-1, 0, 0)), _pl((v, 0, 0), (1, 0, 0))]
        for k in range(ns):
            top = spec.z_level(k + 1) - (tr if (k + 1 == ns and spec.roof_type == "flat") else ts)
            out.append(Element(P_INNER, k, e, SURFACE_INTERIOR, side + z_between(spec.z_level(k), top)))
    return out


def clip_to_zone(el: Element, zone_planes) -> Polyhedron | None:
    """The part of an element inside a convex zone (dot(x - co, no) <= 0 for its planes);
    faces on the zone's planes get tags -1001, -1002, …"""
    solid = el.solid
    for i, (co, no) in enumerate(zone_planes):
        solid = clip(solid, co, no, -1001 - i)
        if solid is None:
            return None
    return solid
