"""Where a collapse by physics starts: the support an EMS-98 grade removes (no bpy).

A trigger is a convex zone of the building (half-spaces in its local frame, dot(x - co, no)
<= 0 inside) and the storeys whose walls inside it lose their bearing capacity. Inside the
zone the structural elements are fractured and handed to the rigid-body solver: the walls
of the failing storeys are crushed in place (their shards flattened to ``CRUSH`` of their
height, so the load above them drops), everything else in the zone is free to fall. Outside
the zone the building stands as it was (documented assumption: connections to the intact
part are strong enough to hold it; the zone's shards are not glued to each other).

Modes (catalogue: docs/DAMAGE_CATALOGUE.md, EMS-98 grades):

- grade 4 ``corner``: a corner of the footprint (30–60 % of each side) from storey k up —
  a corner column or pier fails, the bays above it come down;
- grade 4 ``wall``: a strip 1.5–3 m deep behind one street facade from storey k up — a
  bearing wall fails, the facade and the floor strips it carried fall;
- grade 4 ``storey_part``: 20–50 % of the footprint at one end loses its top storey (or an
  upper storey);
- grade 5 ``ground_storey``: the whole ground storey fails (soft storey; RC preferred), the
  building above drops onto it;
- grade 5 ``everything``: every storey's walls and the gables fail (pancake and heap): total
  collapse.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import common, poly2d

CRUSH = 0.2  # height share a failing wall keeps (crushed in place)
GRADE_MODES = {
    4: {"masonry": (("corner", 0.3), ("wall", 0.35), ("storey_part", 0.35)),
        "reinforced_concrete": (("corner", 0.5), ("wall", 0.2), ("storey_part", 0.3))},
    5: {"masonry": (("ground_storey", 0.25), ("everything", 0.75)),
        "reinforced_concrete": (("ground_storey", 0.6), ("everything", 0.4))},
}
MODES = ("corner", "wall", "storey_part", "ground_storey", "everything")


@dataclass
class Trigger:
    mode: str
    zone: list  # [(co, no)] half-spaces, inside where dot(x - co, no) <= 0 for all
    support_storeys: list  # storeys whose walls inside the zone fail
    origin: tuple  # where the damage starts (cells are smallest there)
    params: dict = field(default_factory=dict)

    def contains(self, pts, tol=0.0) -> np.ndarray:
        q = np.atleast_2d(np.asarray(pts, dtype=np.float64))
        ok = np.ones(len(q), bool)
        for co, no in self.zone:
            ok &= (q - np.asarray(co)) @ np.asarray(no) <= tol
        return ok


def _pl(co, no):
    return (tuple(float(c) for c in co), tuple(float(c) for c in no))


def choose_mode(grade: int, material: str, storeys: int, rng) -> str:
    if grade not in GRADE_MODES:
        raise ValueError(f"physics makes EMS-98 grades 4 and 5, not {grade}: lower grades are local damage "
                         "(use the patterns)")
    table = GRADE_MODES[grade][material]
    names = [n for n, _ in table]
    w = np.array([p for _, p in table], dtype=np.float64)
    mode = names[int(rng.choice(len(names), p=w / w.sum()))]
    if mode == "ground_storey" and storeys < 2:
        mode = "everything"
    return mode


def make_trigger(spec, grade: int, rng, mode: str | None = None) -> Trigger:
    """The trigger of a grade-4 or grade-5 collapse of the shell `spec` (seeded by `rng`)."""
    ns = spec.storeys
    mode = mode or choose_mode(grade, spec.material, ns, rng)
    if mode not in MODES:
        raise ValueError(f"unknown collapse mode {mode!r}; known: {', '.join(MODES)}")
    x0, y0, x1, y1 = spec.bbox
    cen = poly2d.centroid(spec.poly)
    if mode in ("corner", "wall"):
        k = int(rng.integers(0, ns))
    elif mode == "storey_part":
        k = ns - 1 if ns < 3 or rng.random() < 0.7 else int(rng.integers(1, ns))
    else:
        k = 0
    zk = spec.z_level(k)
    above = [_pl((0, 0, zk), (0, 0, -1))]
    if mode == "corner":
        hx, hy = bool(rng.random() < 0.5), bool(rng.random() < 0.5)
        fx, fy = rng.uniform(0.3, 0.6, 2)
        xc = x1 - fx * (x1 - x0) if hx else x0 + fx * (x1 - x0)
        yc = y1 - fy * (y1 - y0) if hy else y0 + fy * (y1 - y0)
        zone = [_pl((xc, 0, 0), (-1, 0, 0) if hx else (1, 0, 0)),
                _pl((0, yc, 0), (0, -1, 0) if hy else (0, 1, 0))] + above
        origin = (x1 if hx else x0, y1 if hy else y0, zk)
        params = {"corner": [int(hx), int(hy)], "fraction_x": float(fx), "fraction_y": float(fy)}
    elif mode == "wall":
        edges = spec.exposed_edges()
        i = int(edges[int(rng.integers(0, len(edges)))])
        a, b, d, n, L = common.edge(spec, i)
        depth = float(rng.uniform(1.5, 3.0))
        co = a - depth * n
        zone = [_pl((co[0], co[1], 0), (n[0], n[1], 0))] + above  # within `depth` of the facade line
        m = (a + b) / 2
        origin = (float(m[0]), float(m[1]), zk)
        params = {"facade": i, "depth": depth}
    elif mode == "storey_part":
        f = float(rng.uniform(0.2, 0.5))
        high = bool(rng.random() < 0.5)
        xc = common.split_for_fraction(spec, f, from_high=high)
        zone = [_pl((xc, 0, 0), (-1, 0, 0) if high else (1, 0, 0))] + above
        origin = (x1 if high else x0, float(cen[1]), zk)
        params = {"footprint_fraction": f, "end": "high_x" if high else "low_x"}
    elif mode == "ground_storey":
        zone = []
        origin = (float(cen[0]), float(cen[1]), 0.0)
        params = {}
    else:
        zone = []
        origin = (float(cen[0]), float(cen[1]), 0.0)
        params = {}
    support = list(range(ns)) if mode == "everything" else [k]
    return Trigger(mode, zone, support, tuple(float(c) for c in origin), {"storey": k, **params})


@dataclass
class Shard:
    """One Voronoi cell of one element inside the trigger's zone."""
    element: int  # index into the elements list
    seed: int  # the cell's seed index within its element
    solid: object  # fracture.Polyhedron (building local frame)
    support: bool  # a failing wall: crushed in place before the simulation


def zone_shards(spec, trigger: Trigger, rng, max_shards: int = 600, max_cells: int = 40, elements=None):
    """Elements of `spec` (or the given ones: a mesh's own, geometry/mesh_elements.py) and the
    shards of their parts inside the trigger's zone: (elements, shards, (near, far) cell sizes
    used). Cells follow the material's sizes, scaled up when the building would need more
    than `max_shards` (the simulation's cost)."""
    from . import fracture as fr
    m = fr.MATERIAL[spec.material]
    if elements is None:
        elements = fr.building_elements(spec)
    clipped = []
    for ei, el in enumerate(elements):
        solid = fr.clip_to_zone(el, trigger.zone) if trigger.zone else el.solid
        if solid is None or solid.volume() < 1e-6:
            continue
        bearing = (fr.P_WALL, fr.P_INNER, fr.P_GABLE) if trigger.mode == "everything" else (fr.P_WALL, fr.P_INNER)
        support = el.part in bearing and (el.storey in trigger.support_storeys or el.part == fr.P_GABLE)
        clipped.append((ei, solid, support))
    near, far = m["cell_near"], m["cell_far"]
    state = rng.bit_generator.state
    for _ in range(6):
        rng.bit_generator.state = state  # the same draws at every scale: same seed, same shards
        seeds = [fr.seed_points(s, rng, trigger.origin, near, far, max_cells=max_cells) for _, s, _ in clipped]
        n = sum(len(s) for s in seeds)
        if n <= max_shards:
            break
        f = (n / max_shards) ** 0.5
        near, far = near * f, far * f
    shards = []
    for (ei, solid, support), s in zip(clipped, seeds):
        for j, cell in fr.voronoi_cells(solid, s):
            shards.append(Shard(ei, j, cell, support))
    return elements, shards, (float(near), float(far))
