"""Procedural roof and facade detail: what real roofs carry and clean boxes lack.

A classifier trained on clean boxes reads any real dormer, chimney or solar array as
damage; these functions add them to a shell so that undamaged buildings look like real
ones to an airborne laser scanner. Details are described in ``ShellSpec.details`` as
dicts ``{"kind": ..., params}`` (local frame, metres), so they are saved with the object
and rebuilt identically; ``build_shell`` calls ``build_details``.

Kinds (and the part they get):

- ``dormer``            box with a flat or small gable roof protruding from a roof slope (P_DETAIL)
- ``chimney``           stack on any roof, the shell's chimney box (P_DETAIL)
- ``skylight``          window raised ~0.1 m on a slope, or a 0.3 m rooflight on a flat roof (P_DETAIL)
- ``overhang``          eaves and verges extending the roof planes 0.3-0.8 m beyond the walls (P_OVERHANG)
- ``parapet``           a flat roof's parapet: drawn by ``build_shell`` as the shell's own
                        parapet (P_PARAPET), so parapet loss and the collapses treat it as such
- ``balcony``           slab + railing per storey on a facade (P_BALCONY, surface wall)
- ``antenna``           thin mast, or a satellite dish on a short stand (P_DETAIL)
- ``solar_panels``      tilted rows on flat roofs, flush panels 0.1 m above a slope (P_DETAIL)
- ``rooftop_structure`` stair/lift housing or HVAC box on a flat roof (P_DETAIL)
- ``annex``             one-storey shed or garage against a facade, same building ID (P_ANNEX)
- ``terrace``           recessed top storey with a railing on a flat roof, or an altana
                        (roof loggia with a railed deck) straddling a pitched roof (P_DETAIL)

Faces: roof-top tops are surface roof (1), their vertical sides wall (2); balconies and
railings wall (2). Roof-top details carry the roof's storey (``spec.storeys``), balconies
their storey, annexes storey 0; ``qs_elem`` is the detail's index in ``spec.details`` for
roof-top details and the facade edge for overhangs, balconies and annexes.

Damage (``settle``): every detail is a connected group of faces resting on an element.
After a pattern, a group whose vertices no longer find their support just below them
(the roof for roof-top details, the floor slab for balconies, the roof inside the
walls for overhangs) falls: its faces are removed and a small debris box (surface 3) is
put where it lands. Patterns that move elements move the details on them (a detail's
faces never reach below the element it sits on), so only details whose element fell
away become debris. Annexes stand on the ground and are left as they are.

Functions take a BMesh, a ShellSpec and numbers; none touches bpy.context.
"""
from __future__ import annotations

import math

import numpy as np
from mathutils import Vector
from mathutils.bvhtree import BVHTree

from . import debris as dbr
from . import poly2d
from .common import edge
from .mesh import (DEBRIS, P_ANNEX, P_BALCONY, P_DEBRIS, P_DETAIL, P_OVERHANG, P_PARAPET, P_ROOF, ROOF, WALL, Labels,
                   add_polygon, delete_faces, remove_loose)

KINDS = ("dormer", "chimney", "skylight", "overhang", "parapet", "balcony", "antenna", "solar_panels",
         "rooftop_structure", "annex", "terrace")
SETTLING_PARTS = {P_DETAIL, P_OVERHANG, P_BALCONY}  # details that rest on an element of the building
DETAIL_PARTS = SETTLING_PARTS | {P_ANNEX}

PIECE = 3.0  # m: overhangs, railings and panel rows are split into pieces of at most this length,
#              so that a partial roof collapse takes only the pieces over the fallen section
MAST = 0.06  # m: antenna mast width
BALCONY_SLAB = 0.15  # m: balcony slab thickness (above the floor level: it moves with its storey)
RAIL_HEIGHT = 1.0
RAIL_INSET = 0.15  # m: terrace railing inside the roof edge
SUPPORT_TOL = 0.3  # m: a detail vertex is supported when an element lies at most this far below it
PROBE_UP = 1.0  # m: probes start this high above a vertex (a chimney's base is embedded below the roof)
PROBE_IN = 0.3  # m: overhang and balcony probes look this far inside the facade


class DetailError(ValueError):
    """A detail does not fit the building (wrong roof, outside the footprint, unknown kind)."""


# --- small builders --------------------------------------------------------------------------

def _newell(points) -> Vector:
    n = Vector((0.0, 0.0, 0.0))
    for k, p in enumerate(points):
        q = points[(k + 1) % len(points)]
        n.x += (p.y - q.y) * (p.z + q.z)
        n.y += (p.z - q.z) * (p.x + q.x)
        n.z += (p.x - q.x) * (p.y + q.y)
    return n


def _face(bm, lab, verts, surface, bid, part, storey, elem, outward=None):
    """New face on existing verts, turned so that its normal points along `outward`."""
    if outward is not None and _newell([v.co for v in verts]).dot(Vector(outward)) < 0:
        verts = verts[::-1]
    return add_polygon(bm, lab, None, surface, bid, part, storey, elem, verts=list(verts))


def _prism(bm, lab, xy, z_bottom, z_top, bid, part, storey, elem, top_surface=ROOF, side_elems=None, top_elem=None):
    """Vertical-sided prism over the counter-clockwise polygon `xy` (bottom open): sides
    wall, top `top_surface`. `z_bottom`/`z_top`: a number or one per vertex. Returns
    (bottom verts, top verts) in the order of `xy`."""
    n = len(xy)
    zb = np.broadcast_to(np.asarray(z_bottom, dtype=np.float64), (n,))
    zt = np.broadcast_to(np.asarray(z_top, dtype=np.float64), (n,))
    bv = [bm.verts.new((float(x), float(y), float(z))) for (x, y), z in zip(xy, zb)]
    tv = [bm.verts.new((float(x), float(y), float(z))) for (x, y), z in zip(xy, zt)]
    for i in range(n):
        j = (i + 1) % n
        add_polygon(bm, lab, None, WALL, bid, part, storey, elem if side_elems is None else side_elems[i],
                    verts=[bv[i], bv[j], tv[j], tv[i]])
    add_polygon(bm, lab, None, top_surface, bid, part, storey, elem if top_elem is None else top_elem, verts=tv)
    return bv, tv


def _ccw(xy):
    xy = [tuple(map(float, p)) for p in xy]
    return xy if poly2d.area(np.asarray(xy)) > 0 else xy[::-1]


def roof_box(bm, lab, zfun, x, y, sx, sy, above, bid, part, storey, elem, floor_z=None, side_elems=None,
             top_elem=None):
    """A box standing on a roof surface z = zfun(x, y): its walls start 5 cm below the lowest
    roof point under it (not below `floor_z`) and its flat top is `above` over the highest.
    The shell's chimney and every roof-top box use it. Returns (bottom verts, top verts)."""
    hx, hy = sx / 2, sy / 2
    xs = np.array([x - hx, x + hx, x + hx, x - hx])
    ys = np.array([y - hy, y - hy, y + hy, y + hy])
    zr = np.asarray(zfun(xs, ys), dtype=np.float64) * np.ones(4)
    zb = float(np.min(zr)) - 0.05
    if floor_z is not None:
        zb = max(zb, floor_z)
    zt = float(np.max(zr)) + above
    return _prism(bm, lab, list(zip(xs, ys)), zb, zt, bid, part, storey, elem, side_elems=side_elems,
                  top_elem=top_elem)


def _railing(bm, lab, base_verts, height, bid, part, storey, elem, outwards, closed=False):
    """Zero-thickness railing panels rising `height` from consecutive `base_verts` (shared, so
    the railing is one piece with what it stands on)."""
    up = [bm.verts.new(v.co + Vector((0.0, 0.0, height))) for v in base_verts]
    n = len(base_verts)
    for i in range(n if closed else n - 1):
        j = (i + 1) % n
        _face(bm, lab, [base_verts[i], base_verts[j], up[j], up[i]], WALL, bid, part, storey, elem, outwards[i])


def spec_zfun(spec):
    def z(x, y):
        return np.asarray(spec.roof_z(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)),
                          dtype=np.float64)
    return z


# --- roof slopes -----------------------------------------------------------------------------

def slope_edges(spec) -> list[int]:
    """Footprint edges under a quadrilateral roof slope (the eaves of a gable roof, the long
    sides of a hip roof): where dormers, skylights and flush panels go."""
    t = spec.roof_type
    if t == "flat":
        return []
    x0, y0, x1, y1 = spec.bbox
    p = spec.poly
    out = []
    for i in range(len(p)):
        along_x = abs(p[i][1] - p[(i + 1) % len(p)][1]) < 1e-6
        if (t == "gable" and along_x) or (t == "hip" and along_x == ((x1 - x0) >= (y1 - y0))):
            out.append(i)
    return out


def half_span(spec) -> float:
    """Horizontal distance from an eave of a slope to the ridge."""
    x0, y0, x1, y1 = spec.bbox
    return 0.5 * ((y1 - y0) if spec.roof_type == "gable" else min(x1 - x0, y1 - y0))


class Slope:
    """Coordinates on the roof slope above footprint edge i: u along the eave from its start,
    v horizontal distance up-slope from the eave (negative: outside the walls)."""

    def __init__(self, spec, i):
        if i not in slope_edges(spec):
            raise DetailError(f"edge {i} carries no quadrilateral roof slope (roof {spec.roof_type!r}; "
                              f"slopes over edges {slope_edges(spec)})")
        self.a, _, self.d, self.n, self.length = edge(spec, i)
        self.H = spec.eave_height
        self.tan = math.tan(math.radians(spec.roof_pitch))
        self.depth = half_span(spec)
        self.hip = spec.roof_type == "hip"

    def xy(self, u, v):
        p = self.a + self.d * u - self.n * v
        return float(p[0]), float(p[1])

    def z(self, v):
        return self.H + self.tan * v

    def co(self, u, v, z=None):
        x, y = self.xy(u, v)
        return (x, y, self.z(v) if z is None else z)

    def check(self, u0, u1, v1, what):
        """Within the slope: u range inside the eave (and clear of the hips), v below the ridge."""
        lo, hi = (v1 + 0.2, self.length - v1 - 0.2) if self.hip else (0.3, self.length - 0.3)
        if u0 < lo - 1e-9 or u1 > hi + 1e-9 or v1 > self.depth - 0.2 + 1e-9:
            raise DetailError(f"{what} does not fit on the slope (u {u0:.2f}-{u1:.2f} of {lo:.2f}-{hi:.2f}, "
                              f"up to {v1:.2f} m of {self.depth - 0.2:.2f} m)")


def _flush_slab(bm, lab, xy, zfun, lift, bid, part, storey, elem):
    """A thin slab following a roof surface `lift` above it (skylight, flush solar panel)."""
    xy = _ccw(xy)
    zb = zfun(np.array([p[0] for p in xy]), np.array([p[1] for p in xy]))
    zb = np.asarray(zb, dtype=np.float64) * np.ones(len(xy))
    return _prism(bm, lab, xy, zb, zb + lift, bid, part, storey, elem)


# --- kinds -----------------------------------------------------------------------------------

def dormer(bm, lab, spec, bid, index, d):
    """d: edge, t (centre along the eave), width, height (front wall above the roof),
    setback (front wall from the eave line), roof "flat" | "gable", pitch (of its gable)."""
    s = Slope(spec, int(d["edge"]))
    w, h, vf = float(d["width"]), float(d["height"]), float(d["setback"])
    u0, u1 = float(d["t"]) - w / 2, float(d["t"]) + w / 2
    zf = s.z(vf)
    zt = zf + h
    vb = vf + h / s.tan  # where the main roof reaches the dormer's eaves
    gable = d.get("roof", "gable") == "gable"
    r = 0.5 * w * math.tan(math.radians(float(d.get("pitch", 35.0)))) if gable else 0.0
    vr = vb + r / s.tan
    s.check(u0, u1, vr, "dormer")
    ns = spec.storeys
    V = bm.verts.new
    fl, fr = V(s.co(u0, vf, zf)), V(s.co(u1, vf, zf))
    tl, tr = V(s.co(u0, vf, zt)), V(s.co(u1, vf, zt))
    bl, br = V(s.co(u0, vb, zt)), V(s.co(u1, vb, zt))
    out = (float(s.n[0]), float(s.n[1]), 0.0)
    side = (float(s.d[0]), float(s.d[1]), 0.0)
    if gable:
        um = 0.5 * (u0 + u1)
        rf, rb = V(s.co(um, vf, zt + r)), V(s.co(um, vr, zt + r))
        _face(bm, lab, [fl, fr, tr, rf, tl], WALL, bid, P_DETAIL, ns, index, out)
        _face(bm, lab, [tl, rf, rb, bl], ROOF, bid, P_DETAIL, ns, index, (0, 0, 1))
        _face(bm, lab, [rf, tr, br, rb], ROOF, bid, P_DETAIL, ns, index, (0, 0, 1))
    else:
        _face(bm, lab, [fl, fr, tr, tl], WALL, bid, P_DETAIL, ns, index, out)
        _face(bm, lab, [tl, tr, br, bl], ROOF, bid, P_DETAIL, ns, index, (0, 0, 1))
    _face(bm, lab, [fl, tl, bl], WALL, bid, P_DETAIL, ns, index, tuple(-c for c in side))
    _face(bm, lab, [fr, br, tr], WALL, bid, P_DETAIL, ns, index, side)


def chimney(bm, lab, spec, bid, index, d):
    """d: x, y, size, height (above the highest roof point under it)."""
    _inside(spec, d["x"], d["y"], d["size"], d["size"], "chimney")
    roof_box(bm, lab, spec_zfun(spec), float(d["x"]), float(d["y"]), float(d["size"]), float(d["size"]),
             float(d["height"]), bid, P_DETAIL, spec.storeys, index, floor_z=spec.eave_height)


def skylight(bm, lab, spec, bid, index, d):
    """Pitched: d: edge, t, v (centre up-slope), width, length; flat: x, y, width, length
    (a 0.3 m rooflight box)."""
    w, ln = float(d["width"]), float(d["length"])
    if spec.roof_type == "flat":
        _inside(spec, d["x"], d["y"], w, ln, "skylight")
        roof_box(bm, lab, spec_zfun(spec), float(d["x"]), float(d["y"]), w, ln, float(d.get("raise", 0.3)), bid,
                 P_DETAIL, spec.storeys, index, floor_z=spec.eave_height)
        return
    s = Slope(spec, int(d["edge"]))
    t, v = float(d["t"]), float(d["v"])
    u0, u1, v0, v1 = t - w / 2, t + w / 2, v - ln / 2, v + ln / 2
    if v0 < 0.3:
        raise DetailError("skylight reaches the eave")
    s.check(u0, u1, v1, "skylight")
    xy = [s.xy(u0, v0), s.xy(u1, v0), s.xy(u1, v1), s.xy(u0, v1)]
    _flush_slab(bm, lab, xy, spec_zfun(spec), float(d.get("raise", 0.1)), bid, P_DETAIL, spec.storeys, index)


def overhang(bm, lab, spec, bid, index, d):
    """d: depth (0.3-0.8 m). Eaves: the slopes continue `depth` beyond every eave wall, with a
    0.15 m fascia; gable roofs also get verges beyond the gable walls. Nothing reaches over
    a party wall (the neighbour's roof is there)."""
    t = spec.roof_type
    if t == "flat":
        raise DetailError("an eaves overhang needs a pitched roof")
    o = float(d["depth"])
    H = spec.eave_height
    tan = math.tan(math.radians(spec.roof_pitch))
    gables = spec.gable_edges()
    party = set(spec.party_walls)
    ns = spec.storeys
    m = len(spec.poly)
    for i in range(m):
        if i in party:  # the neighbour's roof continues there
            continue
        a, _, dd, n, L = edge(spec, i)
        if i in gables:
            _verge(bm, lab, spec, bid, i, o, tan)
            continue
        # run on past the corners, except into a neighbour at a party wall
        ext0, ext1 = (0.0 if (i - 1) % m in party else o), (0.0 if (i + 1) % m in party else o)
        us = np.linspace(0.0, L, max(1, int(math.ceil(L / PIECE))) + 1)
        for k in range(len(us) - 1):
            out0, out1 = (-ext0 if k == 0 else us[k]), (L + ext1 if k == len(us) - 2 else us[k + 1])
            in0 = out0 if (t == "gable" and k == 0) else us[k]  # gable eaves run on under the verges
            in1 = out1 if (t == "gable" and k == len(us) - 2) else us[k + 1]

            def P(u, v, z):
                p = a + dd * u - n * v
                return bm.verts.new((float(p[0]), float(p[1]), float(z)))
            zo = H - tan * o
            o0, o1, i1, i0 = P(out0, -o, zo), P(out1, -o, zo), P(in1, 0.0, H), P(in0, 0.0, H)
            _face(bm, lab, [o0, o1, i1, i0], ROOF, bid, P_OVERHANG, ns, i, (0, 0, 1))
            f0, f1 = P(out0, -o, zo - 0.15), P(out1, -o, zo - 0.15)
            _face(bm, lab, [f0, f1, o1, o0], WALL, bid, P_OVERHANG, ns, i, (float(n[0]), float(n[1]), 0.0))


def _verge(bm, lab, spec, bid, i, o, tan):
    """Roof planes continued `o` beyond gable wall i, in pieces (no barge board: a piece must
    lie wholly above or below the eave level to move with the storeys under it)."""
    a, _, dd, n, Lg = edge(spec, i)
    H = spec.eave_height
    for lo, hi in ((0.0, Lg / 2), (Lg / 2, Lg)):
        us = np.linspace(lo, hi, max(1, int(math.ceil((hi - lo) / PIECE))) + 1)
        for k in range(len(us) - 1):
            vs = []
            for u, v in ((us[k], 0.0), (us[k + 1], 0.0), (us[k + 1], -o), (us[k], -o)):
                p = a + dd * u - n * v
                vs.append(bm.verts.new((float(p[0]), float(p[1]), H + tan * min(u, Lg - u))))
            _face(bm, lab, vs, ROOF, bid, P_OVERHANG, spec.storeys, i, (0, 0, 1))


def balcony(bm, lab, spec, bid, index, d):
    """d: edge, positions (centres along the facade), storeys (>= 1), width, depth, railing.
    Each balcony: a slab from the floor level up BALCONY_SLAB, railing on its three free sides."""
    i = int(d["edge"])
    a, _, dd, n, L = edge(spec, i)
    w, dep, rail = float(d["width"]), float(d["depth"]), float(d.get("railing", RAIL_HEIGHT))
    for k in d["storeys"]:
        k = int(k)
        if not 1 <= k < spec.storeys:
            raise DetailError(f"balcony on storey {k}: the building has storeys 1..{spec.storeys - 1} above ground")
        z0 = spec.z_level(k)
        for t in d["positions"]:
            u0, u1 = float(t) - w / 2, float(t) + w / 2
            if u0 < 0.2 or u1 > L - 0.2:
                raise DetailError(f"balcony at {t:.2f} m does not fit on facade {i} ({L:.2f} m)")
            pts = {"bl": a + dd * u0, "br": a + dd * u1, "fr": a + dd * u1 + n * dep, "fl": a + dd * u0 + n * dep}
            order = ["bl", "fl", "fr", "br"]  # counter-clockwise: the outward normal is right of dd
            _, tv = _prism(bm, lab, [pts[k_] for k_ in order], z0, z0 + BALCONY_SLAB, bid, P_BALCONY, k, i,
                           top_surface=WALL)
            top = dict(zip(order, tv))
            outs = [(-float(dd[0]), -float(dd[1]), 0.0), (float(n[0]), float(n[1]), 0.0),
                    (float(dd[0]), float(dd[1]), 0.0)]
            _railing(bm, lab, [top["bl"], top["fl"], top["fr"], top["br"]], rail, bid, P_BALCONY, k, i, outs)


def antenna(bm, lab, spec, bid, index, d):
    """d: x, y, type "mast" | "dish", height (mast height, or the dish stand's), size (dish
    diameter), azimuth (radians, where the dish faces)."""
    _inside(spec, d["x"], d["y"], 0.2, 0.2, "antenna")
    _antenna(bm, lab, spec_zfun(spec), spec.eave_height, float(d["x"]), float(d["y"]), d.get("type", "mast"),
             float(d["height"]), float(d.get("size", 0.8)), float(d.get("azimuth", 0.0)), bid, spec.storeys, index)


def _antenna(bm, lab, zfun, floor_z, x, y, kind, height, size, azimuth, bid, storey, elem):
    _, tv = roof_box(bm, lab, zfun, x, y, MAST, MAST, height, bid, P_DETAIL, storey, elem, floor_z=floor_z)
    if kind != "dish":
        return
    hub = tv[0]  # the dish hangs on the stand's top: one piece with it
    el = math.radians(35.0)
    nrm = Vector((math.cos(azimuth) * math.cos(el), math.sin(azimuth) * math.cos(el), math.sin(el)))
    e1 = nrm.cross(Vector((0.0, 0.0, 1.0))).normalized()
    e2 = nrm.cross(e1).normalized()
    R = size / 2
    rim = [bm.verts.new(hub.co + (e1 * math.cos(k * math.pi / 4) + e2 * math.sin(k * math.pi / 4)) * R)
           for k in range(8)]
    for k in range(8):
        _face(bm, lab, [hub, rim[k], rim[(k + 1) % 8]], ROOF, bid, P_DETAIL, storey, elem, nrm)


def solar_panels(bm, lab, spec, bid, index, d):
    """Flat roofs, d: mode "rows", x0, y0, x1, y1 (area), tilt (deg), depth (panel length up
    the tilt), pitch (row spacing): rows facing -y, 0.15 m above the roof. Pitched roofs, d:
    mode "flush", edge, u0, u1, v0, v1: panels 0.1 m above the slope."""
    if d.get("mode", "rows") == "flush":
        s = Slope(spec, int(d["edge"]))
        u0, u1, v0, v1 = (float(d[k]) for k in ("u0", "u1", "v0", "v1"))
        if v0 < 0.3:
            raise DetailError("solar panels reach the eave")
        s.check(u0, u1, v1, "solar panels")
        us = np.linspace(u0, u1, max(1, int(math.ceil((u1 - u0) / PIECE))) + 1)
        for k in range(len(us) - 1):
            a, b = us[k] + 0.02, us[k + 1] - 0.02  # small gaps between panel groups
            _flush_slab(bm, lab, [s.xy(a, v0), s.xy(b, v0), s.xy(b, v1), s.xy(a, v1)], spec_zfun(spec),
                        float(d.get("lift", 0.1)), bid, P_DETAIL, spec.storeys, index)
        return
    if spec.roof_type != "flat":
        raise DetailError("solar panel rows need a flat roof (use mode 'flush' on a slope)")
    x0, y0, x1, y1 = (float(d[k]) for k in ("x0", "y0", "x1", "y1"))
    _inside(spec, (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, "solar panels")
    tilt = math.radians(float(d.get("tilt", 20.0)))
    dep, pitch = float(d.get("depth", 1.0)), float(d.get("pitch", 1.8))
    H = spec.eave_height
    lift = float(d.get("lift", 0.15))
    xs = np.linspace(x0, x1, max(1, int(math.ceil((x1 - x0) / PIECE))) + 1)
    yf = y0
    while yf + dep * math.cos(tilt) <= y1 + 1e-9:
        yb = yf + dep * math.cos(tilt)
        for k in range(len(xs) - 1):
            _panel_row(bm, lab, xs[k] + 0.02, xs[k + 1] - 0.02, yf, yb, H, H + lift, H + lift + dep * math.sin(tilt),
                       bid, spec.storeys, index)
        yf += pitch


def _panel_row(bm, lab, xa, xb, yf, yb, H, zf, zb, bid, storey, elem):
    """A tilted panel on its frame: a closed wedge standing on the roof."""
    V = bm.verts.new
    A0, B0, C0, D0 = V((xa, yf, H)), V((xa, yf, zf)), V((xa, yb, zb)), V((xa, yb, H))
    A1, B1, C1, D1 = V((xb, yf, H)), V((xb, yf, zf)), V((xb, yb, zb)), V((xb, yb, H))
    _face(bm, lab, [B0, B1, C1, C0], ROOF, bid, P_DETAIL, storey, elem, (0, -0.3, 1))
    _face(bm, lab, [A0, A1, B1, B0], WALL, bid, P_DETAIL, storey, elem, (0, -1, 0))
    _face(bm, lab, [D0, C0, C1, D1], WALL, bid, P_DETAIL, storey, elem, (0, 1, 0))
    _face(bm, lab, [A0, B0, C0, D0], WALL, bid, P_DETAIL, storey, elem, (-1, 0, 0))
    _face(bm, lab, [A1, D1, C1, B1], WALL, bid, P_DETAIL, storey, elem, (1, 0, 0))


def rooftop_structure(bm, lab, spec, bid, index, d):
    """d: x, y, sx, sy, height, type ("stair" housing or "hvac" box; the type is informative)."""
    _inside(spec, d["x"], d["y"], d["sx"], d["sy"], "rooftop structure")
    roof_box(bm, lab, spec_zfun(spec), float(d["x"]), float(d["y"]), float(d["sx"]), float(d["sy"]),
             float(d["height"]), bid, P_DETAIL, spec.storeys, index, floor_z=spec.eave_height)


def annex(bm, lab, spec, bid, index, d):
    """d: edge, t (centre along it), width, depth (outward), height (< the ground storey),
    roof "flat" | "shed" (falls 8 degrees away from the building)."""
    i = int(d["edge"])
    a, _, dd, n, L = edge(spec, i)
    w, dep, h = float(d["width"]), float(d["depth"]), float(d["height"])
    u0, u1 = float(d["t"]) - w / 2, float(d["t"]) + w / 2
    if u0 < -1e-9 or u1 > L + 1e-9:
        raise DetailError(f"annex does not fit along facade {i} ({L:.2f} m)")
    if h >= spec.storey_height:
        raise DetailError("an annex must be lower than the ground storey")
    hf = h - dep * math.tan(math.radians(8.0)) if d.get("roof", "flat") == "shed" else h
    pts = [a + dd * u0, a + dd * u0 + n * dep, a + dd * u1 + n * dep, a + dd * u1]  # bl, fl, fr, br
    zs = [h, hf, hf, h]
    bot = [bm.verts.new((float(p[0]), float(p[1]), 0.0)) for p in pts]
    top = [bm.verts.new((float(p[0]), float(p[1]), float(z))) for p, z in zip(pts, zs)]
    outs = [(-float(dd[0]), -float(dd[1]), 0.0), (float(n[0]), float(n[1]), 0.0), (float(dd[0]), float(dd[1]), 0.0)]
    for k in range(3):  # no wall against the building
        _face(bm, lab, [bot[k], bot[k + 1], top[k + 1], top[k]], WALL, bid, P_ANNEX, 0, i, outs[k])
    _face(bm, lab, top, ROOF, bid, P_ANNEX, 0, i, (0, 0, 1))


def terrace(bm, lab, spec, bid, index, d):
    """Flat roof, d: mode "penthouse", x0, y0, x1, y1, height, railing (bool: railing along
    the roof edge, for roofs without a parapet). Pitched roof, d: mode "altana", x, y, sx,
    sy: a roof loggia whose flat top, `deck` m over the highest roof point, has a railing."""
    ns = spec.storeys
    if d.get("mode", "penthouse") == "altana":
        if spec.roof_type == "flat":
            raise DetailError("an altana stands on a pitched roof")
        _inside(spec, d["x"], d["y"], d["sx"], d["sy"], "altana")
        _, tv = roof_box(bm, lab, spec_zfun(spec), float(d["x"]), float(d["y"]), float(d["sx"]), float(d["sy"]),
                         float(d.get("deck", 0.5)), bid, P_DETAIL, ns, index, floor_z=spec.eave_height)
        outs = [(0, -1, 0), (1, 0, 0), (0, 1, 0), (-1, 0, 0)]
        _railing(bm, lab, tv, RAIL_HEIGHT, bid, P_DETAIL, ns, index, outs, closed=True)
        return
    if spec.roof_type != "flat":
        raise DetailError("a recessed top storey (penthouse) needs a flat roof")
    x0, y0, x1, y1 = (float(d[k]) for k in ("x0", "y0", "x1", "y1"))
    _inside(spec, (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, "penthouse")
    H = spec.eave_height
    _prism(bm, lab, [(x0, y0), (x1, y0), (x1, y1), (x0, y1)], H, H + float(d["height"]), bid, P_DETAIL, ns, index)
    if d.get("railing") and spec.is_rect:
        bx0, by0, bx1, by1 = spec.bbox
        r = RAIL_INSET
        ring = [(bx0 + r, by0 + r), (bx1 - r, by0 + r), (bx1 - r, by1 - r), (bx0 + r, by1 - r)]
        outs = [(0, -1, 0), (1, 0, 0), (0, 1, 0), (-1, 0, 0)]
        for k in range(4):
            p, q = np.array(ring[k]), np.array(ring[(k + 1) % 4])
            ts = np.linspace(0.0, 1.0, max(1, int(math.ceil(np.linalg.norm(q - p) / PIECE))) + 1)
            for j in range(len(ts) - 1):
                a, b = p + (q - p) * ts[j], p + (q - p) * ts[j + 1]
                base = [bm.verts.new((float(a[0]), float(a[1]), H)), bm.verts.new((float(b[0]), float(b[1]), H))]
                _railing(bm, lab, base, RAIL_HEIGHT, bid, P_DETAIL, ns, index, [outs[k]])


def parapet(bm, lab, spec, bid, height):
    """A flat roof's parapet, one wall strip per footprint edge (the shell's own parapet)."""
    p = spec.poly
    n = len(p)
    H = spec.eave_height
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        add_polygon(bm, lab, [(a[0], a[1], H), (b[0], b[1], H), (b[0], b[1], H + height), (a[0], a[1], H + height)],
                    WALL, bid, P_PARAPET, spec.storeys, i)


def _inside(spec, x, y, sx, sy, what, margin=0.1):
    """The axis-aligned rectangle lies inside the footprint, `margin` from its outline."""
    x, y, hx, hy = float(x), float(y), float(sx) / 2, float(sy) / 2
    corners = np.array([[x - hx, y - hy], [x + hx, y - hy], [x + hx, y + hy], [x - hx, y + hy]])
    p = spec.poly
    ok = poly2d.contains(p, corners).all() and poly2d.boundary_distance(p, corners).min() >= margin - 1e-9
    eps = 1e-9
    inner = (p[:, 0] > x - hx + eps) & (p[:, 0] < x + hx - eps) & (p[:, 1] > y - hy + eps) & (p[:, 1] < y + hy - eps)
    if not ok or inner.any():
        raise DetailError(f"{what} at ({x:.2f}, {y:.2f}) of {sx:.2f} x {sy:.2f} m is not inside the footprint")


BUILDERS = {"dormer": dormer, "chimney": chimney, "skylight": skylight, "overhang": overhang, "balcony": balcony,
            "antenna": antenna, "solar_panels": solar_panels, "rooftop_structure": rooftop_structure,
            "annex": annex, "terrace": terrace}


def parapet_height(spec) -> float:
    """The flat roof's parapet height: the shell's own, else the highest parapet detail."""
    if spec.roof_type != "flat":
        return 0.0
    if spec.parapet_height > 0:
        return float(spec.parapet_height)
    return max((float(d.get("height", 0.0)) for d in spec.details if d.get("kind") == "parapet"), default=0.0)


def build_details(bm, lab, spec, bid):
    """Add every detail of `spec.details` (parapets excepted: build_shell draws them)."""
    for index, d in enumerate(spec.details):
        kind = d.get("kind")
        if kind == "parapet":
            continue
        if kind not in BUILDERS:
            raise DetailError(f"unknown detail kind {kind!r}; known: {', '.join(KINDS)}")
        BUILDERS[kind](bm, lab, spec, bid, index, d)


# --- damage: details follow their element or fall -------------------------------------------

def _components(faces):
    """Groups of faces connected through shared vertices (deterministic order)."""
    parent = {}

    def find(x):
        while parent[x] is not x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x
    for f in faces:
        parent[f] = f
    first = {}
    for f in faces:
        for v in f.verts:
            g = first.setdefault(v, f)
            ra, rb = find(f), find(g)
            if ra is not rb:
                parent[ra] = rb
    groups = {}
    for f in faces:
        groups.setdefault(find(f), []).append(f)
    return list(groups.values())


def _bvh(faces):
    if not faces:
        return None
    index = {}
    coords, polys = [], []
    for f in faces:
        poly = []
        for v in f.verts:
            if v not in index:
                index[v] = len(coords)
                coords.append(v.co.copy())
            poly.append(index[v])
        polys.append(poly)
    return BVHTree.FromPolygons(coords, polys, all_triangles=False)


def _probe_shift(spec, part, elem):
    """Horizontal shift of a unit's probes: inside the facade for overhangs and balconies."""
    if part in (P_OVERHANG, P_BALCONY) and spec is not None and 0 <= elem < len(spec.poly):
        n = edge(spec, elem)[3]
        return Vector((-float(n[0]) * PROBE_IN, -float(n[1]) * PROBE_IN, 0.0))
    return Vector((0.0, 0.0, 0.0))


def supported(unit, tree, shift) -> bool:
    """Some vertex of the unit finds an element (a face of `tree`) at most SUPPORT_TOL below it."""
    if tree is None:
        return False
    down = Vector((0.0, 0.0, -1.0))
    for v in {v for f in unit for v in f.verts}:
        origin = v.co + shift + Vector((0.0, 0.0, PROBE_UP))
        if tree.ray_cast(origin, down, PROBE_UP + SUPPORT_TOL)[0] is not None:
            return True
    return False


def settle(bm, spec, building_id) -> int:
    """After a pattern: details that lost their element become a debris box where they land
    (on what remains of the building, on debris, or on the ground). Returns how many fell.
    Nothing happens (and nothing is drawn from any random stream) without details."""
    lab = Labels(bm)
    dfaces = [f for f in bm.faces if f[lab.part] in SETTLING_PARTS]
    if not dfaces:
        return 0
    structure = [f for f in bm.faces if f[lab.part] not in SETTLING_PARTS | {P_DEBRIS, P_ANNEX}]
    tree = _bvh(structure)
    fallen = []
    for unit in _components(dfaces):
        if not supported(unit, tree, _probe_shift(spec, unit[0][lab.part], unit[0][lab.elem])):
            fallen.append(_footprint(unit))
            delete_faces(bm, unit)
    if not fallen:
        return 0
    remove_loose(bm)
    ground = _bvh([f for f in bm.faces if f[lab.part] not in SETTLING_PARTS])
    for k, (lo, hi) in enumerate(fallen):
        c = (lo + hi) / 2
        z = 0.0
        if ground is not None:
            hit = ground.ray_cast(Vector((c.x, c.y, hi.z + 0.5)), Vector((0.0, 0.0, -1.0)))[0]
            if hit is not None:
                z = max(float(hit.z), 0.0)
        size = (float(np.clip(hi.x - lo.x, 0.3, 2.5)), float(np.clip(hi.y - lo.y, 0.3, 2.5)),
                float(np.clip(0.3 * (hi.z - lo.z), 0.15, 0.5)))
        # a fixed orientation per fallen piece: settling draws nothing from the pattern's stream
        dbr.add_box(bm, lab, building_id, (c.x, c.y, z + size[2] / 2), size, yaw=0.7 * k, pitch=0.1,
                    surface=DEBRIS, part=P_DEBRIS)
    bm.normal_update()
    return len(fallen)


def _footprint(unit):
    cos = np.array([v.co[:] for f in unit for v in f.verts])
    return Vector(cos.min(axis=0).tolist()), Vector(cos.max(axis=0).tolist())


# --- imported meshes (no ShellSpec): roof-top details on the roof faces ----------------------

BUNDLE_KINDS = (("chimney", 0.4), ("antenna", 0.3), ("solar_panels", 0.25), ("rooftop_structure", 0.35),
                ("skylight", 0.25))


def _plane_zfun(face):
    c, n = face.calc_center_median(), face.normal

    def z(x, y):
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return c.z - (n.x * (x - c.x) + n.y * (y - c.y)) / n.z
    return z


def _spot(rng, poly, sx, sy, taken, margin=0.3, tries=30):
    """Centre of an axis-aligned sx x sy rectangle inside `poly` (2D) clear of `taken`."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    for _ in range(tries):
        x, y = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        r = np.array([x - sx / 2, y - sy / 2, x + sx / 2, y + sy / 2])
        corners = np.array([[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]])
        if not poly2d.contains(poly, corners).all() or poly2d.boundary_distance(poly, corners).min() < margin:
            continue
        if any(r[0] < t[2] + margin and t[0] < r[2] + margin and r[1] < t[3] + margin and t[1] < r[3] + margin
               for t in taken):
            continue
        taken.append(r)
        return float(x), float(y)
    return None


def add_roof_details(bm, building_id, seed, storey, min_area=6.0) -> list[str]:
    """Roof-top details on an imported building's roof faces (surface roof, part roof, facing
    up, at least `min_area` m²): chimneys, antennas, solar panels (rows on flat faces, flush
    on slopes), rooftop boxes (flat faces) and skylights, each drawn with the
    probability in BUNDLE_KINDS from the stream (seed, 4242). Returns the kinds added."""
    lab = Labels(bm)
    bm.normal_update()
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 4242])
    roofs = [f for f in bm.faces if f[lab.part] == P_ROOF and f.normal.z > 0.3 and f.calc_area() >= min_area]
    draws = [(kind, rng.uniform() < p) for kind, p in BUNDLE_KINDS]
    if not roofs:
        return []
    floor = min(v.co.z for f in roofs for v in f.verts)
    roofs.sort(key=lambda f: -f.calc_area())
    taken = {f: [] for f in roofs}
    added = []
    for elem, (kind, wanted) in enumerate(draws):
        if not wanted:
            continue
        flat = [f for f in roofs if f.normal.z > 0.97]
        pool = flat if kind == "rooftop_structure" else roofs
        if not pool:
            continue
        face = pool[int(rng.integers(0, len(pool)))]
        poly = poly2d.ccw(np.array([v.co[:2] for v in face.verts]))
        zfun = _plane_zfun(face)
        if _add_on_face(bm, lab, rng, kind, face, poly, zfun, floor, taken[face], building_id, storey, elem):
            added.append(kind)
    bm.normal_update()
    return added


def _add_on_face(bm, lab, rng, kind, face, poly, zfun, floor, taken, bid, storey, elem) -> bool:
    flat = face.normal.z > 0.97
    if kind == "chimney":
        s = float(rng.uniform(0.5, 0.8))
        at = _spot(rng, poly, s, s, taken)
        if at:
            roof_box(bm, lab, zfun, *at, s, s, float(rng.uniform(0.8, 1.5)), bid, P_DETAIL, storey, elem, floor_z=floor)
    elif kind == "antenna":
        at = _spot(rng, poly, 1.0, 1.0, taken)
        if at:
            dish = bool(rng.uniform() < 0.5)
            height = 1.0 if dish else float(rng.uniform(1.5, 3.5))
            _antenna(bm, lab, zfun, floor, *at, "dish" if dish else "mast", height, float(rng.uniform(0.6, 1.0)),
                     float(rng.uniform(0, 2 * math.pi)), bid, storey, elem)
    elif kind == "rooftop_structure":
        sx, sy = float(rng.uniform(1.0, 3.0)), float(rng.uniform(1.0, 2.5))
        at = _spot(rng, poly, sx, sy, taken)
        if at:
            roof_box(bm, lab, zfun, *at, sx, sy, float(rng.uniform(1.0, 2.5)), bid, P_DETAIL, storey, elem,
                     floor_z=floor)
    else:  # solar panels or a skylight: a slab following the face
        sx, sy = (float(rng.uniform(2.0, 5.0)), float(rng.uniform(1.5, 3.0))) if kind == "solar_panels" else \
            (float(rng.uniform(0.6, 1.2)), float(rng.uniform(0.8, 1.4)))
        at = _spot(rng, poly, sx, sy, taken)
        if at:
            x, y = at
            lift = 0.3 if (flat and kind == "skylight") else 0.12
            _flush_slab(bm, lab, [(x - sx / 2, y - sy / 2), (x + sx / 2, y - sy / 2), (x + sx / 2, y + sy / 2),
                                  (x - sx / 2, y + sy / 2)], zfun, lift, bid, P_DETAIL, storey, elem)
    return at is not None
