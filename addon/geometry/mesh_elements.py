"""Structural elements from a building mesh's own geometry (numpy only, no bpy).

``fracture.building_elements`` builds walls, slabs and roof from a procedural shell
description; a user mesh or an imported (CityJSON) shell has none, only faces. This module
reads those faces and builds the same kind of elements (convex solids that do not overlap,
``fracture.Element``), so that an L-shaped or gabled building collapses as itself, not as
its bounding box:

- **footprint**: the outline of the building's lowest downward faces (ground surface), or
  else of its wall faces' bottom edges; vertices that deviate less than ``SIMPLIFY_TOL``
  from the line of their neighbours are dropped (measured outlines carry many), edges
  shorter than ``MIN_EDGE`` closed up, holes (courtyards) ignored;
- **roof**: the roof faces (labelled roof, facing up at most ``ROOF_MAX_PITCH`` steep), merged
  where adjacent faces are coplanar, each plane's outline cut into convex pieces and
  thickened downwards by the material's roof thickness (perpendicular to the plane), so a
  gable or hip roof stays one;
- **walls** along every footprint edge, the material's wall thickness inwards, mitred at the
  corners (as the procedural ones), from the ground to the eave under that edge: the lowest
  point of the roof's underside over the wall's strip (exact: a piecewise planar surface
  over a convex region is lowest at a vertex of one or the other, or where their edges
  cross). Above the eave the strip is split by the roof planes over it: each part rises to
  the lowest point of its plane (a step in the roof) and ends in a **gable** under the
  plane. Where the planes do not cover the strip (a skipped face), the gable is the strip
  under all of them if they form a ridge there, else nothing. Walls are cut where slabs pass;
- **slabs** at every storey level (``storeys`` and ``storey_height`` as given, else
  ``DEFAULT_STOREY_HEIGHT``; on up to the highest roof), over the footprint's convex pieces,
  or their parts under one roof plane, where the roof's underside lies above them;
- inner walls, walls between two roof levels inside the footprint and attic floors under
  pitched roofs are not modelled (a mesh does not say where inner walls stand; the others
  would need the roof's own vertical faces and the space under its plates).

Roof faces that are not planar (vertices farther than ``PLANAR_TOL`` from their plane),
degenerate (a plane's projected area below ``MIN_ROOF_AREA``), steeper than
``ROOF_MAX_PITCH`` or over another plane are skipped (counted in ``roof_faces_skipped``): no
element stands for them, the walls under them end at the eave found under the rest of the
roof, and outside a collapse's zone the building's own faces stay where they were.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import fracture as fr
from . import poly2d

DEFAULT_STOREY_HEIGHT = 3.0  # m: storeys of a mesh whose storey count is not known
SIMPLIFY_TOL = 0.1  # m: a footprint vertex closer to its neighbours' line is dropped
MIN_EDGE = 0.5  # m: shorter footprint edges are closed up (no wall thicker than its length)
GROUND_TOL = 0.3  # m: faces and edges this close to the lowest point are at the ground
PLANAR_TOL = 0.02  # m: a roof face with a vertex farther from its plane is not planar
ROOF_MAX_PITCH = 75.0  # degrees: steeper "roof" faces are walls of a mansard, not plates
MIN_ROOF_AREA = 0.05  # m² projected: smaller roof planes are degenerate
MIN_PIECE = 0.05  # m: wall pieces between slabs thinner than this are dropped
KEY = 1e-3  # m: vertices closer than this are one when outlines are traced
UP_NZ = math.cos(math.radians(ROOF_MAX_PITCH))
SURFACE_GROUND, SURFACE_ROOF, SURFACE_WALL = 0, 1, 2
# parts (geometry.mesh P_*): the roof itself, not a detail on it (chimney, dormer, ...); the
# base (a user mesh's bottom faces, labelled interior by label_object)
ROOF_PARTS = (0, 2)
P_BASE = 9


class MeshElementsError(ValueError):
    """The mesh does not give a building outline (the message says why)."""


@dataclass
class MeshBuilding:
    footprint: np.ndarray  # (n, 2) counter-clockwise, simplified
    eaves: np.ndarray  # (n,) wall top under each footprint edge
    base: float  # ground level (the mesh's lowest point)
    storeys: int
    storey_height: float
    elements: list  # fracture.Element
    roof_planes: int  # roof planes made into elements
    roof_faces_skipped: int
    footprint_source: str  # "ground" or "walls"


# --- outlines --------------------------------------------------------------------------------

def _keys(pts):
    return [tuple(k) for k in np.round(np.asarray(pts) / KEY).astype(np.int64).tolist()]


def _loops(segments):
    """Closed loops ([(x, y)] points) from undirected segments ((2, 2) arrays); segments used
    twice (between two faces of the same set) cancel. Vertices not on exactly two segments end
    a chain, which is then not a loop."""
    count, where = {}, {}
    for s in segments:
        ka, kb = _keys(s)
        if ka == kb:
            continue
        e = (ka, kb) if ka < kb else (kb, ka)
        count[e] = count.get(e, 0) + 1
        where[ka], where[kb] = s[0], s[1]
    adj = {}
    for (ka, kb), c in sorted(count.items()):
        if c % 2 == 1:
            adj.setdefault(ka, []).append(kb)
            adj.setdefault(kb, []).append(ka)
    loops, seen = [], set()
    for start in sorted(adj):
        if start in seen or len(adj[start]) != 2:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            nxt = [k for k in adj[cur] if k != prev]
            if len(adj[cur]) != 2 or not nxt:
                loop = None
                break
            prev, cur = cur, nxt[0]
            if cur == start:
                break
            if cur in seen:
                loop = None
                break
            seen.add(cur)
            loop.append(cur)
        if loop and len(loop) >= 3:
            loops.append(np.array([where[k] for k in loop], dtype=np.float64))
    return loops


def simplify(poly, tol=SIMPLIFY_TOL) -> np.ndarray:
    """Drop, one at a time and least deviating first, the vertices closer than `tol` to the
    line through their neighbours (collinear and near-duplicate points)."""
    p = [np.asarray(v, dtype=np.float64) for v in poly]
    while len(p) > 3:
        n = len(p)
        dev = []
        for i in range(n):
            a, v, b = p[i - 1], p[i], p[(i + 1) % n]
            ab = b - a
            L = float(np.hypot(*ab))
            d = float(np.hypot(*(v - a))) if L < 1e-12 else abs(fr._cross2(ab, v - a)) / L
            dev.append(d)
        i = int(np.argmin(dev))
        if dev[i] >= tol:
            break
        p.pop(i)
    return np.array(p)


def close_short_edges(poly, min_edge=MIN_EDGE) -> np.ndarray:
    """Drop, shortest edge first, one end of every edge shorter than `min_edge` (the end whose
    loss changes the area least): a mitred wall along an edge shorter than its thickness has
    crossing mitres. A small step in a facade becomes a slightly slanted facade."""
    p = [np.asarray(v, dtype=np.float64) for v in poly]
    while len(p) > 3:
        n = len(p)
        L = [float(np.hypot(*(p[(i + 1) % n] - p[i]))) for i in range(n)]
        i = int(np.argmin(L))
        if L[i] >= min_edge:
            break
        loss = [abs(fr._cross2(p[j] - p[j - 1], p[(j + 1) % n] - p[j])) for j in (i, (i + 1) % n)]
        p.pop(i if loss[0] <= loss[1] else (i + 1) % n)
    return np.array(p)


def _is_simple(p) -> bool:
    n = len(p)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        for j in range(i + 1, n):
            if j == i or (j + 1) % n == i or j == (i + 1) % n:
                continue
            c, d = p[j], p[(j + 1) % n]
            d1, d2 = fr._cross2(b - a, c - a), fr._cross2(b - a, d - a)
            d3, d4 = fr._cross2(d - c, a - c), fr._cross2(d - c, b - c)
            if d1 * d2 < 0 and d3 * d4 < 0:
                return False
    return True


def _face_geometry(verts, polys):
    """Per polygon: unit normal (Newell), area and centre."""
    normals, areas, centres = [], [], []
    for poly in polys:
        f = verts[poly]
        n = fr.cross(f, np.roll(f, -1, axis=0)).sum(axis=0) / 2.0
        a = fr.norm(n)
        normals.append(n / a if a > 0 else n)
        areas.append(a)
        centres.append(f.mean(axis=0))
    return np.array(normals).reshape(-1, 3), np.array(areas), np.array(centres).reshape(-1, 3)


def footprint(verts, polys, surface, part, normals, base):
    """The building's outline (counter-clockwise, simplified) and where it came from."""
    ground = [i for i, poly in enumerate(polys)
              if (surface[i] == SURFACE_GROUND or (part is not None and part[i] == P_BASE))
              and normals[i][2] < -0.5 and verts[poly][:, 2].max() <= base + GROUND_TOL]
    candidates = []
    if ground:
        segs = [verts[[polys[i][k], polys[i][(k + 1) % len(polys[i])]], :2]
                for i in ground for k in range(len(polys[i]))]
        candidates.append(("ground", _loops(segs)))
    walls = [i for i, poly in enumerate(polys) if surface[i] == SURFACE_WALL and abs(normals[i][2]) <= 0.5]
    segs = []
    for i in walls:
        poly = polys[i]
        for k in range(len(poly)):
            e = verts[[poly[k], poly[(k + 1) % len(poly)]]]
            if e[:, 2].max() <= base + GROUND_TOL:
                segs.append(e[:, :2])
    candidates.append(("walls", _loops(segs)))
    for source, loops in candidates:
        if not loops:
            continue
        best = max(loops, key=lambda lp: abs(poly2d.area(lp)))
        p = close_short_edges(simplify(poly2d.ccw(best)))
        if len(p) >= 3 and poly2d.area(p) >= 1.0 and _is_simple(p):
            return p, source
    raise MeshElementsError("no closed outline of at least 1 m² among its ground faces or its walls' "
                            "bottom edges (is the mesh closed at the bottom and are its walls labelled?)")


# --- the roof --------------------------------------------------------------------------------

@dataclass
class RoofPiece:
    poly: np.ndarray  # (k, 2) convex, counter-clockwise (projection on the ground)
    co: np.ndarray  # a point of the roof plane
    no: np.ndarray  # its unit normal (upwards)
    thickness: float

    def top(self, xy) -> np.ndarray:
        xy = np.atleast_2d(xy)
        return self.co[2] - ((xy[:, 0] - self.co[0]) * self.no[0] + (xy[:, 1] - self.co[1]) * self.no[1]) / self.no[2]

    def underside(self, xy) -> np.ndarray:
        return self.top(xy) - self.thickness / self.no[2]


def _group_coplanar(verts, polys, idx, normals):
    """Connected groups of coplanar polygons among `idx` (sharing an edge, same plane)."""
    parent = {i: i for i in idx}

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    off = {i: float(normals[i] @ verts[polys[i]].mean(axis=0)) for i in idx}
    edges = {}
    for i in idx:
        ks = _keys(verts[polys[i]])
        for k in range(len(ks)):
            a, b = ks[k], ks[(k + 1) % len(ks)]
            edges.setdefault((a, b) if a < b else (b, a), []).append(i)
    for share in edges.values():
        for j in share[1:]:
            i = share[0]
            if float(np.abs(normals[i] - normals[j]).max()) < 1e-3 and abs(off[i] - off[j]) < PLANAR_TOL:
                ri, rj = find(i), find(j)
                if ri != rj:
                    parent[max(ri, rj)] = min(ri, rj)
    groups = {}
    for i in idx:
        groups.setdefault(find(i), []).append(i)
    return [groups[k] for k in sorted(groups)]


def roof_pieces(verts, polys, surface, part, normals, areas, thickness):
    """Convex roof pieces and the number of roof faces skipped."""
    skipped = 0
    good = []
    for i, poly in enumerate(polys):
        if surface[i] != SURFACE_ROOF or (part is not None and part[i] not in ROOF_PARTS):
            continue
        f = verts[poly]
        if areas[i] <= 1e-9 or normals[i][2] < UP_NZ:
            skipped += 1
            continue
        if float(np.abs((f - f.mean(axis=0)) @ normals[i]).max()) > PLANAR_TOL:
            skipped += 1
            continue
        good.append(i)
    pieces = []
    for g in _group_coplanar(verts, polys, good, normals):
        w = areas[g]
        no = (normals[g] * w[:, None]).sum(axis=0)
        no /= np.linalg.norm(no)
        co = (np.array([verts[polys[i]].mean(axis=0) for i in g]) * w[:, None]).sum(axis=0) / w.sum()
        segs = [verts[[polys[i][k], polys[i][(k + 1) % len(polys[i])]], :2] for i in g for k in range(len(polys[i]))]
        loops = _loops(segs)
        outline = max(loops, key=lambda lp: abs(poly2d.area(lp))) if loops else None
        if outline is None or abs(poly2d.area(outline)) < MIN_ROOF_AREA:
            skipped += len(g)
            continue
        outline = simplify(poly2d.ccw(outline), KEY)
        if len(outline) < 3 or not _is_simple(outline):
            skipped += len(g)
            continue
        new = [RoofPiece(piece, co, no, thickness) for piece in fr.convex_pieces(outline)
               if abs(poly2d.area(piece)) >= 1e-6]
        # a plane over another (a dormer's roof over the main roof, an overhang over a lower
        # roof): plates stacked in one column would overlap; the first plane found keeps it
        if any(_overlap(a.poly, b.poly) > 1e-4 for a in new for b in pieces):
            skipped += len(g)
            continue
        pieces.extend(new)
    return pieces, skipped


def _inside_convex(poly, pts, tol=1e-7) -> np.ndarray:
    q = np.atleast_2d(pts)
    ok = np.ones(len(q), bool)
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ok &= (b[0] - a[0]) * (q[:, 1] - a[1]) - (b[1] - a[1]) * (q[:, 0] - a[0]) >= -tol
    return ok


def _crossings(p, q):
    """Points where the edges of polygons p and q cross."""
    out = []
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        for j in range(len(q)):
            c, d = q[j], q[(j + 1) % len(q)]
            den = fr._cross2(b - a, d - c)
            if abs(den) < 1e-12:
                continue
            t = fr._cross2(c - a, d - c) / den
            u = fr._cross2(c - a, b - a) / den
            if -1e-9 <= t <= 1 + 1e-9 and -1e-9 <= u <= 1 + 1e-9:
                out.append(a + t * (b - a))
    return out


def _overlap(p, q) -> float:
    """Area shared by two convex counter-clockwise polygons."""
    r = np.asarray(p, dtype=np.float64)
    for i in range(len(q)):
        if not len(r):
            return 0.0
        a, b = q[i], q[(i + 1) % len(q)]
        r = poly2d.clip_halfplane(r, a, (b[1] - a[1], a[0] - b[0]))
    return abs(poly2d.area(r)) if len(r) >= 3 else 0.0


def underside_samples(region, pieces):
    """Points of the convex `region` where the roof's underside over it can be lowest, each
    with the lowest underside over it among the pieces covering it (NaN: no roof above)."""
    pts = [np.asarray(v, dtype=np.float64) for v in region]
    for pc in pieces:
        if _overlap(region, pc.poly) <= 0.0 and not _crossings(region, pc.poly):
            continue
        pts.extend(v for v in pc.poly if _inside_convex(region, v)[0])
        pts.extend(_crossings(region, pc.poly))
    pts = np.array(pts)
    u = np.full(len(pts), np.inf)
    for pc in pieces:
        inside = _inside_convex(pc.poly, pts)
        if inside.any():
            u[inside] = np.minimum(u[inside], pc.underside(pts[inside]))
    u[np.isinf(u)] = np.nan
    return pts, u


def lowest_underside(region, pieces):
    _, u = underside_samples(region, pieces)
    return float(np.nanmin(u)) if np.isfinite(u).any() else None


# --- elements --------------------------------------------------------------------------------

def _strip(p, inner, i):
    n = len(p)
    return poly2d.ccw(np.array([p[i], p[(i + 1) % n], inner[(i + 1) % n], inner[i]]))


def _wall_top_fallback(verts, polys, surface, normals, a, b, base):
    """Top of the wall faces standing on the edge a-b (no roof found above it)."""
    top = None
    for i, poly in enumerate(polys):
        if surface[i] != SURFACE_WALL or abs(normals[i][2]) > 0.5:
            continue
        f = verts[poly]
        if float(poly2d.boundary_distance(np.array([a, b]), f[:, :2]).max()) <= 0.5:
            z = float(f[:, 2].max())
            top = z if top is None else max(top, z)
    return top if top is not None else float(verts[:, 2].max())


def mesh_elements(verts, polys, surface, part=None, material="masonry", storeys=None,
                  storey_height=None) -> MeshBuilding:
    """The structural elements of a building mesh (module docstring).

    verts : (n, 3) float, the object's local frame (z up)
    polys : list of vertex index lists, one per face
    surface : (m,) int, the faces' surface codes (ground 0, roof 1, wall 2; others ignored)
    part : (m,) int or None, the faces' part codes (details on the roof are not roof)
    storeys, storey_height : the building's, when known (else inferred from the eaves)
    """
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    polys = [list(map(int, p)) for p in polys if len(p) >= 3]
    surface = np.asarray(surface).astype(np.int64)
    part = None if part is None else np.asarray(part).astype(np.int64)
    keep = [i for i in range(len(polys)) if surface[i] in (SURFACE_GROUND, SURFACE_ROOF, SURFACE_WALL)
            or (part is not None and part[i] == P_BASE)]
    polys = [polys[i] for i in keep]
    surface = surface[keep]
    part = None if part is None else part[keep]
    if not polys:
        raise MeshElementsError("no ground, wall or roof faces")
    m = fr.MATERIAL[material]
    tw, ts, tr = m["wall"], m["slab"], m["roof"]
    used = np.unique(np.concatenate([np.asarray(p) for p in polys]))
    base = float(verts[used, 2].min())
    normals, areas, _ = _face_geometry(verts, polys)
    p, source = footprint(verts, polys, surface, part, normals, base)
    pieces, skipped = roof_pieces(verts, polys, surface, part, normals, areas, tr)
    n = len(p)
    inner = fr.inset_corners(p, tw)
    if not _is_simple(inner) or poly2d.area(inner) <= 0:
        raise MeshElementsError(f"the outline is too narrow somewhere for {tw} m walls")
    strips = [_strip(p, inner, i) for i in range(n)]
    eaves = np.array([lowest_underside(s, pieces) if pieces else None for s in strips], dtype=object)
    for i in range(n):
        if eaves[i] is None:
            eaves[i] = _wall_top_fallback(verts, polys, surface, normals, p[i], p[(i + 1) % n], base)
    eaves = np.array([float(e) for e in eaves])
    top = float(eaves.max())
    if top - base < 1.0:
        raise MeshElementsError(f"its walls are only {top - base:.2f} m high")
    if storeys and storeys >= 1:
        ns = int(storeys)
        hs = float(storey_height) if storey_height and storey_height > 0 else (top - base) / ns
    else:
        hs = float(storey_height) if storey_height and storey_height > 0 else DEFAULT_STOREY_HEIGHT
        ns = max(1, int(round((top - base) / hs)))
    zmax = max([top] + [float(pc.top(pc.poly).max()) for pc in pieces])
    # floors go on above the storeys counted where a higher part of a stepped roof has room
    # for them (slabs are kept only where the roof clears them)
    levels = [base + k * hs for k in range(1, max(ns, int((zmax - base) // hs)) + 1)]
    allxy = np.concatenate([p] + [pc.poly for pc in pieces])
    lo = np.array([allxy[:, 0].min(), allxy[:, 1].min(), base])
    hi = np.array([allxy[:, 0].max(), allxy[:, 1].max(), zmax + 1.0])
    els = []
    slabs = []  # (polygon, top) of the slabs made
    for j, piece in enumerate(fr.convex_pieces(p)):
        clear = lowest_underside(piece, pieces) if pieces else None
        clear = top if clear is None else clear
        subs = _under_each_plane(piece, pieces)
        for k, z in enumerate(levels, start=1):
            # the whole piece where the roof clears it; under a stepped roof, the parts
            # under the planes that clear it
            parts = [piece] if z <= clear + 1e-9 else [r for r, pc in subs if z <= lowest_underside(r, [pc]) + 1e-9]
            for r in parts:
                els.append(fr.Element(fr.P_SLAB, k, j, fr.SURFACE_INTERIOR, fr._prism_planes(r, z - ts, z),
                                      plane_surface=fr._facade_planes(p, r)))
                slabs.append((r, z))
    for i in range(n):
        wp = fr._wall_planes(p, inner, i, tw)
        els += _wall_pieces(wp, i, base, eaves[i], levels, ts, ns)
        subs = _under_each_plane(strips[i], pieces)
        if subs:
            # above the eave, each part of the wall under one roof plane follows that plane:
            # up to its lowest point (a step in the roof), then a gable under it
            for r, pc in subs:
                side = fr._prism_planes(r, 0.0, 0.0)[:len(r)]
                e = lowest_underside(r, [pc])
                els += _wall_pieces(side, i, eaves[i], e, levels, ts, ns)
                floor = max([e] + [z for q, z in slabs if _overlap(r, q) > 1e-9])
                els.append(fr.Element(fr.P_GABLE, ns, i, fr.SURFACE_WALL, side + [
                    fr._pl((0, 0, floor), (0, 0, -1)), fr._pl(pc.co - pc.thickness * pc.no, pc.no)]))
        else:
            gable = _gable_planes(strips[i], pieces)
            if gable:
                floor = max([eaves[i]] + [z for q, z in slabs if _overlap(strips[i], q) > 1e-9])
                els.append(fr.Element(fr.P_GABLE, ns, i, fr.SURFACE_WALL,
                                      wp + [fr._pl((0, 0, floor), (0, 0, -1))] + gable))
    for e, pc in enumerate(pieces):
        k = len(pc.poly)
        planes = fr._prism_planes(pc.poly, 0.0, 0.0)[:k]
        planes += [fr._pl(pc.co, pc.no), fr._pl(pc.co - pc.thickness * pc.no, -pc.no)]
        ps = {s: fr.SURFACE_INTERIOR for s in range(k)}
        ps.update(fr._facade_planes(p, pc.poly))
        ps[k + 1] = fr.SURFACE_INTERIOR
        els.append(fr.Element(fr.P_ROOF, ns, e, fr.SURFACE_ROOF, planes, plane_surface=ps))
    for el in els:
        try:
            el.solid = fr.from_planes(el.planes, lo, hi)
        except ValueError:
            raise MeshElementsError(f"element (part {el.part}, {el.elem}) is not a closed solid "
                                    "(an outline too ragged for its walls?)") from None
    els = [el for el in els if el.solid is not None and el.volume > 1e-6]
    return MeshBuilding(p, eaves, base, ns, hs, els, len(pieces), skipped, source)


def _wall_pieces(side, i, z0, z1, levels, ts, ns):
    """Wall elements with the lateral half-spaces `side` from z0 to z1, cut where the slabs
    at `levels` (tops) pass; storeys counted from the ground."""
    out = []
    cuts = sorted((z - ts, z) for z in levels if z0 < z and z - ts < z1)
    z = z0
    for c0, c1 in cuts + [(z1, z1)]:
        if min(c0, z1) - z > MIN_PIECE:
            k = sum(1 for lv in levels if lv <= z + 1e-9)
            out.append(fr.Element(fr.P_WALL, min(k, ns - 1), i, fr.SURFACE_WALL, side + fr.z_between(z, min(c0, z1))))
        z = max(z, c1)
    return out


def _under_each_plane(region, pieces, cover=0.9):
    """The convex `region` split by the roof pieces over it: [(part, piece)], or [] when they
    cover less than `cover` of it (a skipped roof face above it; slivers of the simplified
    outline outside the roof's own stay uncovered)."""
    out, area = [], 0.0
    for pc in pieces:
        r = np.asarray(region, dtype=np.float64)
        q = pc.poly
        for k in range(len(q)):
            if not len(r):
                break
            a, b = q[k], q[(k + 1) % len(q)]
            r = poly2d.clip_halfplane(r, a, (b[1] - a[1], a[0] - b[0]))
        if len(r) >= 3 and abs(poly2d.area(r)) > 1e-6:
            r = poly2d.ccw(r)
            out.append((r, pc))
            area += abs(poly2d.area(r))
    return out if area >= cover * abs(poly2d.area(region)) else []


def _gable_planes(strip, pieces, tol=0.01):
    """Underside planes of the roof pieces over a wall's strip, when the roof there is their
    lower envelope (a ridge, as over a gable or hip end); [] under a valley or step, where
    clipping by every plane would cut below the roof, or with no roof over the strip."""
    over = [pc for pc in pieces if _overlap(strip, pc.poly) > 1e-6]
    if not over:
        return []
    pts, u = underside_samples(strip, pieces)
    ok = np.isfinite(u)
    if not ok.all():
        return []
    env = np.min([pc.underside(pts) for pc in over], axis=0)
    if (env < u - tol).any():
        return []
    return [fr._pl(pc.co - pc.thickness * pc.no, pc.no) for pc in over]
