"""Roof and facade details of a city plan's buildings (pure Python + numpy, no bpy).

With ``details="typical"`` (default ``"none"`` leaves every plan as it was) each building's
details are drawn from a stream of its own, ``(building seed, 4242)``, so that footprints,
storeys, placements and grades do not change. Probability that a building gets an entry,
among the buildings it fits (DETAIL_FREQUENCIES, DETAIL_FITS):

=================  =====  ======  =====  ======  =====  ======  ====  =======  =======  =======  =====  =======
typology           over-  chim-   dor-   sky-    solar  stair/  HVAC  terrace  antenna  balcony  annex  parapet
                   hang   ney     mer    light          lift
=================  =====  ======  =====  ======  =====  ======  ====  =======  =======  =======  =====  =======
detached house     0.80   0.60    0.40   0.30    0.25   -       -     -        0.20     0.15     0.30   0.70
terraced house     0.60   0.50    0.35   0.35    0.20   -       -     -        0.20     0.10     0.15   -
small apartment    0.60   0.30    0.15   0.20    0.30   0.50    0.40  0.15     0.40     0.60     0.10   0.70
apartment block    -      -       -      -       0.30   0.80    0.60  0.20     0.40     0.60     -      0.70
L-shaped block     -      -       -      -       0.30   0.80    0.50  0.15     0.40     0.50     -      0.70
region masonry     0.70   0.50    0.10   0.15    0.05   -       -     0.12     0.35     0.25     0.05   -
region RC          0.60   -       -      -       0.10   0.50    0.30  0.30     0.40     0.50     -      0.70
small: garden shed 0.60   -       -      0.10    0.05   -       -     -        -        -        -      -
small: garage      -      -       -      0.15    0.10   -       -     -        -        -        -      -
small: row house   0.50   0.30    0.45   0.40    0.25   -       -     -        0.10     0.05     -      -
small: small house 0.70   0.40    0.30   0.30    0.30   -       -     -        0.15     -        0.10   0.50
=================  =====  ======  =====  ======  =====  ======  ====  =======  =======  =======  =====  =======

Fits: overhang and dormer need a pitched roof; chimney a shell without its own chimney
(the layouts, citygen, already give 60 % of pitched masonry houses one); stair/lift housing
and HVAC boxes a flat roof; terrace a pitched roof (an altana, as in L'Aquila's centre) or a
flat roof of 3+ storeys (a recessed top storey); balcony 2+ storeys and a free facade of 6+ m
(a stack on every upper storey, 1-2 facades); parapet a flat roof without one (the plans
give every flat roof a parapet, so only single buildings get it; the small set's sheds and
bare garages stay without: they have no parapet entry). Dormers come 1-2,
skylights 1-3, HVAC boxes 1-3 a building. A detail is dropped when there is no room for
it (roof space taken, an annex would come within 0.5 m of another building).
"""
from __future__ import annotations

import math

import numpy as np

from . import ems98
from .city_plan import CityPlan, world_polygon
from .geometry import poly2d


def _u(rng, a, b):
    return float(rng.uniform(a, b))


DETAIL_LEVELS = ("none", "typical")
DETAIL_SALT = 4242  # details come from their own stream per building: (building seed, 4242)

# Probability that a building of a typology gets an entry, among the buildings it fits
# (see DETAIL_FITS); "hvac" is a rooftop_structure of type "hvac". The module docstring
# has the same table.
DETAIL_FREQUENCIES = {
    "detached_house": {"overhang": 0.80, "chimney": 0.60, "dormer": 0.40, "skylight": 0.30, "solar_panels": 0.25,
                       "antenna": 0.20, "balcony": 0.15, "annex": 0.30, "parapet": 0.70},
    "terraced_house": {"overhang": 0.60, "chimney": 0.50, "dormer": 0.35, "skylight": 0.35, "solar_panels": 0.20,
                       "antenna": 0.20, "balcony": 0.10, "annex": 0.15},
    "small_apartment": {"overhang": 0.60, "chimney": 0.30, "dormer": 0.15, "skylight": 0.20, "solar_panels": 0.30,
                        "rooftop_structure": 0.50, "hvac": 0.40, "terrace": 0.15, "antenna": 0.40, "balcony": 0.60,
                        "annex": 0.10, "parapet": 0.70},
    "apartment_block": {"solar_panels": 0.30, "rooftop_structure": 0.80, "hvac": 0.60, "terrace": 0.20,
                        "antenna": 0.40, "balcony": 0.60, "parapet": 0.70},
    "l_block": {"solar_panels": 0.30, "rooftop_structure": 0.80, "hvac": 0.50, "terrace": 0.15, "antenna": 0.40,
                "balcony": 0.50, "parapet": 0.70},
    "courtyard_block_masonry": {"overhang": 0.70, "chimney": 0.50, "dormer": 0.10, "skylight": 0.15,
                                "solar_panels": 0.05, "terrace": 0.12, "antenna": 0.35, "balcony": 0.25,
                                "annex": 0.05},
    "courtyard_block_rc": {"overhang": 0.60, "solar_panels": 0.10, "rooftop_structure": 0.50, "hvac": 0.30,
                           "terrace": 0.30, "antenna": 0.40, "balcony": 0.50, "parapet": 0.70},
    # small set: outbuildings get eaves and now and then a rooflight or panels, no parapet
    # (those without one are meant bare); row houses are Dutch terraces (dormers, rooflights)
    "garden_shed": {"overhang": 0.60, "skylight": 0.10, "solar_panels": 0.05},
    "garage": {"skylight": 0.15, "solar_panels": 0.10},
    "row_house": {"overhang": 0.50, "chimney": 0.30, "dormer": 0.45, "skylight": 0.40, "solar_panels": 0.25,
                  "antenna": 0.10, "balcony": 0.05},
    "small_house": {"overhang": 0.70, "chimney": 0.40, "dormer": 0.30, "skylight": 0.30, "solar_panels": 0.30,
                    "antenna": 0.15, "annex": 0.10, "parapet": 0.50},
}
DETAIL_ENTRIES = ("overhang", "chimney", "dormer", "skylight", "solar_panels", "rooftop_structure", "hvac",
                  "terrace", "antenna", "balcony", "annex", "parapet")
DETAIL_FITS = {
    "overhang": "pitched roof", "dormer": "pitched roof", "chimney": "the shell has no chimney of its own",
    "rooftop_structure": "flat roof", "hvac": "flat roof",
    "terrace": "pitched roof (altana) or flat roof of 3+ storeys",
    "balcony": "2+ storeys and a free facade of 6+ m", "parapet": "flat roof without a parapet",
}


def entry_kind(entry: str) -> str:
    return "rooftop_structure" if entry == "hvac" else entry


def _is_axis_rect(p) -> bool:
    """Four corners on the bounding box (ShellSpec.is_rect): pitched roofs need it."""
    lo, hi = p.min(axis=0), p.max(axis=0)
    return len(p) == 4 and bool(np.all((np.abs(p - lo) < 1e-6) | (np.abs(p - hi) < 1e-6)))


class _Site:
    """What the detail placers need to know of a shell dict (pure numpy: details are drawn without bpy)."""

    def __init__(self, shell, world=None, obstacles=()):
        self.shell = shell
        self.poly = poly2d.ccw(np.asarray(shell["footprint"], dtype=np.float64))
        (self.x0, self.y0), (self.x1, self.y1) = self.poly.min(axis=0), self.poly.max(axis=0)
        rect = _is_axis_rect(self.poly)
        self.roof = shell.get("roof", "flat") if (shell.get("roof") in ("gable", "hip") and rect) else "flat"
        self.rect = rect
        self.ns = int(shell.get("storeys", 2))
        self.hs = float(shell.get("storey_height", 3.0))
        self.tan = math.tan(math.radians(float(shell.get("roof_pitch", 30.0))))
        L, W = self.x1 - self.x0, self.y1 - self.y0
        self.depth = 0.5 * (W if self.roof == "gable" else min(L, W))
        self.parapet = float(shell.get("parapet_height", 0.0)) if self.roof == "flat" else 0.0
        self.party = set(shell.get("party_walls", []))
        self.taken = []  # roof-top rectangles (local x0, y0, x1, y1) already used
        if shell.get("chimney"):  # the shell's own chimney
            cx, cy, size, _ = shell["chimney"]
            self.taken.append((cx - size / 2, cy - size / 2, cx + size / 2, cy + size / 2))
        self.world = world  # (location, rotation) for the annex's clearance test
        self.obstacles = list(obstacles)  # world polygons of the other buildings (and their annexes)

    def edge(self, i):
        a, b = self.poly[i], self.poly[(i + 1) % len(self.poly)]
        L = float(np.linalg.norm(b - a))
        d = (b - a) / L
        return a, d, np.array([d[1], -d[0]]), L

    def slope_edges(self):
        """Edges under a quadrilateral slope (geometry.details.slope_edges on a dict)."""
        if self.roof == "flat":
            return []
        out = []
        for i in range(len(self.poly)):
            along_x = abs(self.poly[i][1] - self.poly[(i + 1) % len(self.poly)][1]) < 1e-6
            if (self.roof == "gable" and along_x) or (
                    self.roof == "hip" and along_x == ((self.x1 - self.x0) >= (self.y1 - self.y0))):
                out.append(i)
        return out

    def exposed(self):
        n = len(self.poly)
        return [i for i in range(n) if i not in self.party] or list(range(n))

    def free_rect(self, rng, sx, sy, margin=0.6, region=None, tries=40):
        """Centre of an sx x sy rectangle on the roof, inside the footprint `margin` from its
        outline and clear of the details already placed; None when there is no room."""
        x0, y0, x1, y1 = region or (self.x0, self.y0, self.x1, self.y1)
        for _ in range(tries):
            x = _u(rng, x0 + sx / 2 + margin, x1 - sx / 2 - margin) if x1 - x0 > sx + 2 * margin else None
            y = _u(rng, y0 + sy / 2 + margin, y1 - sy / 2 - margin) if y1 - y0 > sy + 2 * margin else None
            if x is None or y is None:
                return None
            if self.claim(x - sx / 2, y - sy / 2, x + sx / 2, y + sy / 2, margin):
                return round(x, 2), round(y, 2)
        return None

    def claim(self, x0, y0, x1, y1, margin=0.3) -> bool:
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        if not poly2d.contains(self.poly, corners).all() or poly2d.boundary_distance(self.poly, corners).min() < margin:
            return False
        p = self.poly
        if ((p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)).any():  # a re-entrant corner inside
            return False
        if any(x0 < t[2] + 0.3 and t[0] < x1 + 0.3 and y0 < t[3] + 0.3 and t[1] < y1 + 0.3 for t in self.taken):
            return False
        self.taken.append((x0, y0, x1, y1))
        return True

    def claim_slope(self, i, u0, u1, v0, v1) -> bool:
        a, d, n, _ = self.edge(i)
        pts = np.array([a + d * u - n * v for u in (u0, u1) for v in (v0, v1)])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return self.claim(lo[0], lo[1], hi[0], hi[1], margin=0.0)

    def slope_range(self, v1):
        """u range along a slope's eave free at depth v1 (clear of the hips)."""
        L = self.edge(self.slope_edges()[0])[3]
        return (v1 + 0.3, L - v1 - 0.3) if self.roof == "hip" else (0.4, L - 0.4)


def _place_overhang(rng, site):
    if site.roof == "flat":
        return None
    return [{"kind": "overhang", "depth": round(_u(rng, 0.3, 0.8), 2)}]


def _place_chimney(rng, site):
    if site.shell.get("chimney"):
        return None
    size = round(_u(rng, 0.4, 0.7), 2)
    at = site.free_rect(rng, size, size, margin=1.0)
    if at is None:
        return None
    return [{"kind": "chimney", "x": at[0], "y": at[1], "size": size, "height": round(_u(rng, 0.8, 1.5), 2)}]


def _slope_spot(rng, site, w, v0, v1):
    """An eave edge and a centre t for something w wide reaching from v0 to v1 up the slope."""
    edges = site.slope_edges()
    if not edges or v1 > site.depth - 0.2:
        return None
    lo, hi = site.slope_range(v1)
    if hi - lo < w + 1e-6:
        return None
    for _ in range(20):
        i = edges[int(rng.integers(0, len(edges)))]
        t = _u(rng, lo + w / 2, hi - w / 2)
        if site.claim_slope(i, t - w / 2, t + w / 2, v0, v1):
            return i, round(t, 2)
    return None


def _place_dormer(rng, site):
    if site.roof == "flat":
        return None
    out = []
    for _ in range(int(rng.integers(1, 3))):
        w, h, vf = _u(rng, 1.2, 2.2), _u(rng, 1.0, 1.5), _u(rng, 0.6, 1.2)
        gable = rng.uniform() < 0.6
        r = 0.5 * w * math.tan(math.radians(35.0)) if gable else 0.0
        # as high as the slope allows: the dormer's ridge stays 0.3 m below the main ridge
        h = min(h, (site.depth - 0.3 - vf) * site.tan - r)
        if h < 0.8:
            continue
        v1 = vf + (h + r) / site.tan
        spot = _slope_spot(rng, site, w, vf, v1)
        if spot:
            out.append({"kind": "dormer", "edge": spot[0], "t": spot[1], "width": round(w, 2), "height": round(h, 2),
                        "setback": round(vf, 2), "roof": "gable" if gable else "flat", "pitch": 35.0})
    return out or None


def _place_skylight(rng, site):
    out = []
    for _ in range(int(rng.integers(1, 4))):
        w, ln = round(_u(rng, 0.6, 1.2), 2), round(_u(rng, 0.8, 1.4), 2)
        if site.roof == "flat":
            at = site.free_rect(rng, w, ln)
            if at:
                out.append({"kind": "skylight", "x": at[0], "y": at[1], "width": w, "length": ln})
            continue
        if site.depth - 0.6 < ln + 0.5:
            continue
        v = _u(rng, 0.5 + ln / 2, site.depth - 0.3 - ln / 2)
        spot = _slope_spot(rng, site, w, v - ln / 2, v + ln / 2)
        if spot:
            out.append({"kind": "skylight", "edge": spot[0], "t": spot[1], "v": round(v, 2), "width": w, "length": ln})
    return out or None


def _place_solar(rng, site):
    if site.roof != "flat":
        v0 = round(_u(rng, 0.5, 1.0), 2)
        v1 = round(min(v0 + _u(rng, 2.0, 4.0), site.depth - 0.3), 2)
        if v1 - v0 < 1.5:
            return None
        lo, hi = site.slope_range(v1)
        w = min(_u(rng, 3.0, 8.0), hi - lo - 0.01)
        if w < 2.0:
            return None
        spot = _slope_spot(rng, site, w, v0, v1)
        if spot is None:
            return None
        i, t = spot
        return [{"kind": "solar_panels", "mode": "flush", "edge": i, "u0": round(t - w / 2, 2),
                 "u1": round(t + w / 2, 2), "v0": v0, "v1": v1}]
    for scale in (1.0, 0.6, 0.35):
        sx = min(_u(rng, 4.0, 10.0) * scale, site.x1 - site.x0 - 2.0)
        sy = min(_u(rng, 3.0, 8.0) * scale, site.y1 - site.y0 - 2.0)
        if sx < 1.5 or sy < 1.2:
            continue
        at = site.free_rect(rng, sx, sy, margin=0.8)
        if at:
            return [{"kind": "solar_panels", "mode": "rows", **_rect_keys(at, sx, sy),
                     "tilt": round(_u(rng, 15, 30), 1), "depth": round(_u(rng, 1.0, 1.7), 2), "pitch": round(_u(rng, 1.8, 2.6), 2)}]
    return None


def _rect_keys(at, sx, sy):
    return {"x0": round(at[0] - sx / 2, 2), "y0": round(at[1] - sy / 2, 2), "x1": round(at[0] + sx / 2, 2),
            "y1": round(at[1] + sy / 2, 2)}


def _place_box(rng, site, typ, count, sx_range, sy_range, h_range):
    if site.roof != "flat":
        return None
    out = []
    for _ in range(count):
        sx, sy = round(_u(rng, *sx_range), 2), round(_u(rng, *sy_range), 2)
        at = site.free_rect(rng, sx, sy)
        if at:
            out.append({"kind": "rooftop_structure", "type": typ, "x": at[0], "y": at[1], "sx": sx, "sy": sy,
                        "height": round(_u(rng, *h_range), 2)})
    return out or None


def _place_stair(rng, site):
    return _place_box(rng, site, "stair", 1, (2.5, 4.0), (2.5, 3.5), (2.4, 3.0))


def _place_hvac(rng, site):
    return _place_box(rng, site, "hvac", int(rng.integers(1, 4)), (1.0, 3.0), (1.0, 2.0), (1.0, 1.8))


def _place_terrace(rng, site):
    if site.roof != "flat":
        sx, sy = round(_u(rng, 2.5, 4.0), 2), round(_u(rng, 2.5, 3.5), 2)
        cy = (site.y0 + site.y1) / 2  # astride the ridge (gable) or the middle (hip)
        at = site.free_rect(rng, sx, sy, margin=0.8, region=(site.x0, cy - sy / 2 - 0.9, site.x1, cy + sy / 2 + 0.9))
        if at is None:
            return None
        return [{"kind": "terrace", "mode": "altana", "x": at[0], "y": at[1], "sx": sx, "sy": sy,
                 "deck": round(_u(rng, 0.3, 0.6), 2)}]
    if site.ns < 3:
        return None
    fx, fy = _u(rng, 0.4, 0.6), _u(rng, 0.5, 0.7)
    for scale in (1.0, 0.7, 0.5):  # smaller on an L-shaped roof, whose arms are narrower than its box
        sx, sy = scale * fx * (site.x1 - site.x0), scale * fy * (site.y1 - site.y0)
        at = site.free_rect(rng, sx, sy, margin=1.5)
        if at:
            return [{"kind": "terrace", "mode": "penthouse", **_rect_keys(at, sx, sy),
                     "height": round(site.hs, 2), "railing": site.parapet <= 0}]
    return None


def _place_antenna(rng, site):
    at = site.free_rect(rng, 1.0, 1.0, margin=0.8)
    if at is None:
        return None
    dish = rng.uniform() < 0.5
    h = (0.6 if site.roof == "flat" else 1.0) if dish else round(_u(rng, 1.5, 4.0), 2)
    return [{"kind": "antenna", "x": at[0], "y": at[1], "type": "dish" if dish else "mast", "height": h,
             "size": round(_u(rng, 0.6, 1.0), 2), "azimuth": round(_u(rng, 0, 2 * math.pi), 3)}]


def _place_balcony(rng, site):
    if site.ns < 2:
        return None
    edges = [i for i in site.exposed() if site.edge(i)[3] >= 6.0]
    if not edges:
        return None
    chosen = sorted(int(i) for i in rng.permutation(edges)[:int(rng.integers(1, 3))])
    width, depth = round(_u(rng, 2.0, 3.5), 2), round(_u(rng, 1.0, 1.5), 2)
    out = []
    for i in chosen:
        L = site.edge(i)[3]
        n = max(1, int(L // _u(rng, 5.0, 8.0)))
        step = L / n
        pos = [round(step * (k + 0.5), 2) for k in range(n)]
        out.append({"kind": "balcony", "edge": i, "positions": pos, "storeys": list(range(1, site.ns)),
                    "width": round(min(width, step - 0.6), 2), "depth": depth, "railing": 1.0})
    return [d for d in out if d["width"] >= 1.2] or None


def _place_annex(rng, site):
    if site.world is None:
        return None
    loc, rot = site.world
    c, s = math.cos(rot), math.sin(rot)
    R = np.array([[c, s], [-s, c]])
    h = round(min(_u(rng, 2.3, 3.0), 0.9 * site.hs), 2)
    for _ in range(6):
        edges = [i for i in site.exposed() if site.edge(i)[3] >= 3.5]
        if not edges:
            return None
        i = edges[int(rng.integers(0, len(edges)))]
        a, d, n, L = site.edge(i)
        w, dep = min(_u(rng, 3.0, 6.0), L - 0.4), _u(rng, 2.5, 5.0)
        if L - w < 1.0:
            continue
        t = _u(rng, w / 2 + 0.5, L - w / 2 - 0.5)
        local = np.array([a + d * (t - w / 2), a + d * (t - w / 2) + n * dep, a + d * (t + w / 2) + n * dep,
                          a + d * (t + w / 2)])
        world = local @ R + np.asarray(loc)
        if not all(_clear(world, ob, ANNEX_CLEARANCE) for ob in site.obstacles):
            continue
        site.obstacles.append(world)
        return [{"kind": "annex", "edge": i, "t": round(t, 2), "width": round(w, 2), "depth": round(dep, 2),
                 "height": h, "roof": "shed" if rng.uniform() < 0.5 else "flat"}]
    return None


ANNEX_CLEARANCE = 0.5  # m between an annex and any other building (or annex)


def _clear(a, b, clearance) -> bool:
    """Convex polygons a and b do not overlap and are at least `clearance` apart."""
    if poly2d.convex_overlap(a, b, 0.0):
        return False
    return min(poly2d.boundary_distance(a, b).min(), poly2d.boundary_distance(b, a).min()) >= clearance


def _place_parapet(rng, site):
    if site.roof != "flat" or site.parapet > 0:
        return None
    return [{"kind": "parapet", "height": round(_u(rng, 0.3, 0.8), 2)}]


_PLACERS = {"overhang": _place_overhang, "chimney": _place_chimney, "dormer": _place_dormer,
            "skylight": _place_skylight, "solar_panels": _place_solar, "rooftop_structure": _place_stair,
            "hvac": _place_hvac, "terrace": _place_terrace, "antenna": _place_antenna, "balcony": _place_balcony,
            "annex": _place_annex, "parapet": _place_parapet}


def draw_details(shell: dict, typology: str, seed: int, world=None, obstacles=()) -> list:
    """Details for one shell (dicts for ShellSpec.details) drawn with DETAIL_FREQUENCIES from the
    building's own stream (seed, DETAIL_SALT): the city plan's streams are not touched. `world`:
    (location, rotation) and `obstacles` (world polygons of other buildings) allow annexes."""
    freqs = DETAIL_FREQUENCIES.get(typology, DETAIL_FREQUENCIES["small_apartment"])
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, DETAIL_SALT])
    site = _Site(shell, world, obstacles)
    out = []
    for entry in DETAIL_ENTRIES:
        u = rng.uniform()  # one draw per entry whatever the building: entries do not shift each other
        if u < freqs.get(entry, 0.0):
            out += _PLACERS[entry](rng, site) or []
    return out


def add_details(plan: CityPlan, level: str = "typical") -> CityPlan:
    """Give every building of `plan` its details (in place); `level` "none" leaves it as it is."""
    if level not in DETAIL_LEVELS:
        raise ValueError(f"details must be one of {DETAIL_LEVELS}, got {level!r}")
    if level == "none":
        return plan
    worlds = [world_polygon(b) for b in plan.buildings]
    owner = list(range(len(worlds)))
    boxes = np.array([np.concatenate([w.min(axis=0), w.max(axis=0)]) for w in worlds])
    reach = 6.0  # an annex reaches at most 5 m out; only buildings this close can be in its way
    for k, b in enumerate(plan.buildings):
        lo, hi = boxes[k, :2] - reach, boxes[k, 2:] + reach
        near = np.flatnonzero((boxes[:, 2] >= lo[0]) & (boxes[:, 0] <= hi[0]) & (boxes[:, 3] >= lo[1])
                              & (boxes[:, 1] <= hi[1]))
        others = [worlds[j] for j in near if owner[j] != k]
        b.shell["details"] = draw_details(b.shell, b.typology, b.seed, (b.location, b.rotation), others)
        # later buildings keep clear of this one's annex (earlier ones were checked by it)
        for d in b.shell["details"]:
            if d["kind"] == "annex":
                w = _annex_world(b, d)
                worlds.append(w)
                owner.append(k)
                boxes = np.vstack([boxes, np.concatenate([w.min(axis=0), w.max(axis=0)])])
    return plan


def _annex_world(b, d):
    site = _Site(b.shell)
    a, dd, n, _ = site.edge(int(d["edge"]))
    t, w, dep = d["t"], d["width"], d["depth"]
    local = np.array([a + dd * (t - w / 2), a + dd * (t - w / 2) + n * dep, a + dd * (t + w / 2) + n * dep,
                      a + dd * (t + w / 2)])
    c, s = math.cos(b.rotation), math.sin(b.rotation)
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(b.location)


def typology_for(material: str, storeys: int) -> str:
    """The city typology whose detail frequencies suit a single building (the Add Building operator)."""
    if material == ems98.MASONRY and storeys <= 2:
        return "detached_house"
    if storeys >= 6:
        return "apartment_block"
    return "small_apartment"
