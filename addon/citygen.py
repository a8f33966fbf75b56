"""Procedural city layouts for the batch generator (pure Python + numpy, no bpy).

Two sets, after the seed paper's two virtual scenes:

- ``generic``: small to medium European town: detached houses, terraced rows, small and
  large apartment blocks, L-shaped blocks; masonry and RC; pitched and flat roofs; loose
  and dense rows along streets.
- ``region``: L'Aquila-like historic centre: 2-4 storey stone masonry (some RC) in
  courtyard blocks of attached buildings, narrow streets, low-pitch tiled roofs.

A plan is a list of BuildingPlan (shell parameters as plain dicts, placement, labels);
the same seed gives the same plan.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import ems98

SETS = ("generic", "region")


@dataclass
class BuildingPlan:
    id: int
    shell: dict  # keyword arguments of geometry.shell.ShellSpec
    location: tuple  # (x, y) of the local origin
    rotation: float  # radians about z
    vulnerability_class: str
    seed: int
    typology: str
    extent: tuple = field(default=(0.0, 0.0, 0.0, 0.0))  # world bbox x0, y0, x1, y1


@dataclass
class CityPlan:
    buildings: list
    bounds: tuple  # terrain rectangle x0, y0, x1, y1
    set_name: str
    seed: int


def _u(rng, a, b):
    return float(rng.uniform(a, b))


def _pick(rng, items):
    """items: [(value, weight)]"""
    w = np.array([x[1] for x in items], dtype=float)
    return items[int(rng.choice(len(items), p=w / w.sum()))][0]


def _rect(L, W):
    return [[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]]


def _vclass(rng, material, region=False):
    if material == ems98.MASONRY:
        return _pick(rng, [("A", 0.3), ("B", 0.6), ("C", 0.1)] if region else [("A", 0.15), ("B", 0.5), ("C", 0.35)])
    return _pick(rng, [("C", 0.7), ("D", 0.3)] if region else [("C", 0.45), ("D", 0.4), ("E", 0.15)])


def _storey_h(rng, material):
    lo, hi = ems98.STOREY_HEIGHT[material]
    return round(_u(rng, lo, hi), 2)


def _chimney(rng, L, W, p):
    if rng.uniform() >= p:
        return None
    return [round(_u(rng, -L / 2 + 1.5, L / 2 - 1.5), 2), round(_u(rng, -W / 4, W / 4), 2),
            round(_u(rng, 0.5, 0.8), 2), round(_u(rng, 0.8, 1.5), 2)]


# --- generic ------------------------------------------------------------------------------

GENERIC_TYPES = [("detached_house", 0.30), ("terraced_house", 0.20), ("small_apartment", 0.25),
                 ("apartment_block", 0.15), ("l_block", 0.10)]


def _generic_shell(rng, typ):
    if typ == "detached_house":
        mat = ems98.MASONRY if rng.uniform() < 0.7 else ems98.RC
        L, W = _u(rng, 8, 12), _u(rng, 7, 10)
        roof = _pick(rng, [("gable", 0.5), ("hip", 0.4), ("flat", 0.1)])
        ns = int(rng.integers(1, 3))
        shell = dict(footprint=_rect(L, W), storeys=ns, roof=roof, roof_pitch=round(_u(rng, 25, 40), 1),
                     parapet_height=round(_u(rng, 0.3, 0.6), 2) if roof == "flat" else 0.0,
                     chimney=_chimney(rng, L, W, 0.6) if (roof != "flat" and mat == ems98.MASONRY) else None)
    elif typ == "terraced_house":
        mat = ems98.MASONRY
        L, W = _u(rng, 6, 9), _u(rng, 9, 12)
        shell = dict(footprint=_rect(L, W), storeys=int(rng.integers(2, 4)), roof="gable",
                     roof_pitch=round(_u(rng, 30, 45), 1), chimney=_chimney(rng, L, W, 0.5))
    elif typ == "small_apartment":
        mat = ems98.RC if rng.uniform() < 0.7 else ems98.MASONRY
        L, W = _u(rng, 14, 24), _u(rng, 10, 14)
        roof = "flat" if mat == ems98.RC and rng.uniform() < 0.7 else "hip"
        shell = dict(footprint=_rect(L, W), storeys=int(rng.integers(3, 6)), roof=roof,
                     roof_pitch=round(_u(rng, 20, 30), 1),
                     parapet_height=round(_u(rng, 0.6, 1.0), 2) if roof == "flat" else 0.0)
    elif typ == "apartment_block":
        mat = ems98.RC
        L, W = _u(rng, 25, 45), _u(rng, 11, 15)
        shell = dict(footprint=_rect(L, W), storeys=int(rng.integers(5, 9)), roof="flat",
                     parapet_height=round(_u(rng, 0.6, 1.0), 2))
    else:  # l_block
        mat = ems98.RC
        A, B, w = _u(rng, 18, 30), _u(rng, 18, 26), _u(rng, 10, 13)
        pts = np.array([[0, 0], [A, 0], [A, w], [w, w], [w, B], [0, B]], dtype=float)
        pts -= (pts.min(axis=0) + pts.max(axis=0)) / 2
        shell = dict(footprint=pts.tolist(), storeys=int(rng.integers(3, 7)), roof="flat",
                     parapet_height=round(_u(rng, 0.6, 1.0), 2))
    shell["footprint"] = [[round(x, 3), round(y, 3)] for x, y in shell["footprint"]]
    shell.update(storey_height=_storey_h(rng, mat), material=mat, typology=typ,
                 bay_width=round(_u(rng, 3.5, 5.5), 2) if mat == ems98.RC else 0.0,
                 inner_wall_spacing=round(_u(rng, 4.0, 6.0), 2))
    return shell


def _extent(shell, rot):
    p = np.asarray(shell["footprint"], dtype=float)
    c, s = math.cos(rot), math.sin(rot)
    q = p @ np.array([[c, s], [-s, c]])
    return q.min(axis=0), q.max(axis=0)


def generic_plan(n: int, seed: int, row_length: float | None = None) -> CityPlan:
    rng = np.random.default_rng([seed, 101])
    row_length = row_length or max(100.0, 25.0 * math.sqrt(n))
    plans = []
    y = 0.0
    bid = 1
    while bid <= n:
        dense = rng.uniform() < 0.5
        street = _u(rng, 8, 14)
        x, depth, full = 0.0, 0.0, False
        while bid <= n and not full:
            if dense:
                typ = _pick(rng, [("terraced_house", 0.15), ("small_apartment", 0.35), ("apartment_block", 0.3),
                                  ("l_block", 0.2)])
            else:
                typ = _pick(rng, [("detached_house", 0.7), ("small_apartment", 0.25), ("l_block", 0.05)])
            count = int(rng.integers(2, 6)) if typ == "terraced_house" else 1
            prev = None
            for _ in range(count):
                if bid > n:
                    break
                shell = _generic_shell(rng, typ)
                rot = 0.0 if rng.uniform() < 0.5 else math.pi
                if typ == "detached_house" and not dense:
                    rot += _u(rng, -0.25, 0.25)
                lo, hi = _extent(shell, rot)
                gap = 0.05 if typ == "terraced_house" else (_u(rng, 2, 5) if dense else _u(rng, 6, 15))
                if x > 0 and x + (hi[0] - lo[0]) > row_length:
                    full = True
                    break
                cx, cy = x - lo[0], y - lo[1]
                plans.append(BuildingPlan(bid, shell, (round(cx, 3), round(cy, 3)), rot,
                                          _vclass(rng, shell["material"]), int(rng.integers(0, 2 ** 31 - 1)), typ,
                                          (cx + lo[0], cy + lo[1], cx + hi[0], cy + hi[1])))
                if typ == "terraced_house":
                    # attached row: the walls between neighbours are party walls (edge 1 is the
                    # local +x end, edge 3 the -x end; rotation pi swaps them in the world)
                    if prev is not None:
                        prev.shell.setdefault("party_walls", []).append(1 if prev.rotation == 0.0 else 3)
                        shell.setdefault("party_walls", []).append(3 if rot == 0.0 else 1)
                    prev = plans[-1]
                bid += 1
                x += (hi[0] - lo[0]) + gap
                depth = max(depth, hi[1] - lo[1])
        y += depth + street
    return CityPlan(plans, _bounds(plans), "generic", seed)


# --- region (L'Aquila-like) -----------------------------------------------------------------

def _region_shell(rng, L, W):
    mat = ems98.MASONRY if rng.uniform() < 0.85 else ems98.RC
    if mat == ems98.MASONRY:
        ns = int(rng.integers(2, 5))
        roof = _pick(rng, [("gable", 0.6), ("hip", 0.4)])
    else:
        ns = int(rng.integers(3, 6))
        roof = _pick(rng, [("hip", 0.5), ("flat", 0.5)])
    shell = dict(footprint=_rect(L, W), storeys=ns, roof=roof, roof_pitch=round(_u(rng, 18, 28), 1),
                 parapet_height=round(_u(rng, 0.4, 0.9), 2) if roof == "flat" else 0.0,
                 chimney=_chimney(rng, L, W, 0.35) if (roof != "flat" and mat == ems98.MASONRY and L > 4) else None,
                 storey_height=_storey_h(rng, mat), material=mat,
                 typology="courtyard_block_masonry" if mat == ems98.MASONRY else "courtyard_block_rc",
                 bay_width=round(_u(rng, 3.5, 5.0), 2) if mat == ems98.RC else 0.0,
                 inner_wall_spacing=round(_u(rng, 3.5, 5.5), 2))
    shell["footprint"] = [[round(x, 3), round(y, 3)] for x, y in shell["footprint"]]
    return shell


def _split(rng, length, lo=6.0, hi=14.0):
    segs = []
    left = length
    while left > hi:
        s = _u(rng, lo, hi)
        if left - s < 5.0:
            s = left - 5.0
        segs.append(s)
        left -= s
    segs.append(left)
    return segs


def region_plan(n: int, seed: int) -> CityPlan:
    rng = np.random.default_rng([seed, 202])
    plans = []
    bid = 1
    gap = 0.05
    cols = max(1, int(math.ceil(math.sqrt(n / 16.0))))
    bx0, by0 = 0.0, 0.0
    col = 0
    row_depth = 0.0
    while bid <= n:
        Bx, By = _u(rng, 35, 60), _u(rng, 30, 50)
        d = _u(rng, 8, 12)
        sides = [  # (start, direction, length, rotation, inward normal)
            ((bx0, by0), (1, 0), Bx, 0.0),
            ((bx0 + Bx, by0 + By), (-1, 0), Bx, math.pi),
            ((bx0 + Bx, by0 + d + gap), (0, 1), By - 2 * d - 2 * gap, math.pi / 2),
            ((bx0, by0 + By - d - gap), (0, -1), By - 2 * d - 2 * gap, -math.pi / 2),
        ]
        for side, ((sx, sy), (dx, dy), length, rot) in enumerate(sides):
            if length < 4.0:
                continue
            t = 0.0
            segs = _split(rng, length)
            for k, seg in enumerate(segs):
                if bid > n:
                    break
                L = seg - gap
                shell = _region_shell(rng, L, d)
                # attached in the block: ends are party walls except at the block's corners
                # (edge 3 = local -x end = start of the side, edge 1 = its end)
                party = [1, 3]
                if side < 2 and k == 0:
                    party.remove(3)
                if side < 2 and k == len(segs) - 1:
                    party.remove(1)
                shell["party_walls"] = party
                c = t + seg / 2
                # local +y (depth) points into the block: the rotation maps local y to the inward side
                nx, ny = -math.sin(rot), math.cos(rot)
                cx = sx + dx * c + nx * d / 2
                cy = sy + dy * c + ny * d / 2
                lo, hi = _extent(shell, rot)
                plans.append(BuildingPlan(bid, shell, (round(cx, 3), round(cy, 3)), rot,
                                          _vclass(rng, shell["material"], region=True),
                                          int(rng.integers(0, 2 ** 31 - 1)), shell["typology"],
                                          (cx + lo[0], cy + lo[1], cx + hi[0], cy + hi[1])))
                bid += 1
                t += seg
        street = _u(rng, 4, 8)
        row_depth = max(row_depth, By)
        col += 1
        if col >= cols:
            col = 0
            bx0 = 0.0
            by0 += row_depth + street
            row_depth = 0.0
        else:
            bx0 += Bx + street
    return CityPlan(plans, _bounds(plans), "region", seed)


def _bounds(plans, margin=15.0):
    ext = np.array([p.extent for p in plans], dtype=float)
    return (float(ext[:, 0].min() - margin), float(ext[:, 1].min() - margin),
            float(ext[:, 2].max() + margin), float(ext[:, 3].max() + margin))


def city_plan(set_name: str, n: int, seed: int) -> CityPlan:
    if set_name not in SETS:
        raise ValueError(f"set must be one of {SETS}, got {set_name!r}")
    if n < 1:
        raise ValueError(f"number of buildings must be >= 1, got {n}")
    return generic_plan(n, seed) if set_name == "generic" else region_plan(n, seed)


# --- grades ---------------------------------------------------------------------------------

PAPER_SCENES = (("post_heavy", 3), ("post_extreme", 4), ("post_destruction", 5))
MIXED_WEIGHTS = ((0, 0.3), (1, 0.05), (2, 0.05), (3, 0.2), (4, 0.2), (5, 0.2))


def mixed_grades(ids, seed: int) -> dict:
    rng = np.random.default_rng([seed, 303])
    g = [x for x, _ in MIXED_WEIGHTS]
    w = np.array([x for _, x in MIXED_WEIGHTS])
    draws = rng.choice(len(g), size=len(ids), p=w / w.sum())
    return {int(i): int(g[k]) for i, k in zip(ids, draws)}


def exact_grades(ids, mix: dict, seed: int) -> dict:
    """Grades with exact counts per grade (`mix`: grade -> count, summing to len(ids)),
    assigned to the buildings in a seeded random order."""
    grades = [g for g, n in sorted(mix.items()) for _ in range(n)]
    if len(grades) != len(ids):
        raise ValueError(f"grade mix sums to {len(grades)} but there are {len(ids)} buildings")
    rng = np.random.default_rng([seed, 304])
    order = rng.permutation(len(ids))
    return {int(ids[k]): int(grades[j]) for j, k in enumerate(order)}


def overlaps(plan: CityPlan, tol=0.01) -> list:
    """Pairs of buildings whose rotated footprints overlap by more than `tol` metres
    (separating-axis test on convex hulls); for tests."""
    polys = []
    for b in plan.buildings:
        p = np.asarray(b.shell["footprint"], dtype=float)
        c, s = math.cos(b.rotation), math.sin(b.rotation)
        polys.append(p @ np.array([[c, s], [-s, c]]) + np.asarray(b.location))
    out = []
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            if _sat_overlap(polys[i], polys[j], tol):
                out.append((plan.buildings[i].id, plan.buildings[j].id))
    return out


def _sat_overlap(a, b, tol):
    for poly in (a, b):
        for k in range(len(poly)):
            e = poly[(k + 1) % len(poly)] - poly[k]
            n = np.array([-e[1], e[0]]) / (np.linalg.norm(e) + 1e-12)
            pa, pb = a @ n, b @ n
            if pa.max() <= pb.min() + tol or pb.max() <= pa.min() + tol:
                return False
    return True
