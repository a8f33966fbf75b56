"""Trees, hedges, parked cars and street furniture around a city's buildings (pure Python +
numpy, no bpy).

Real scenes have them and ours had not: a classifier trained without them reads a crown
over a roof or a car that left as damage. `plan_streetscape` places them around building
footprints (world polygons) inside the terrain rectangle, seeded; `post_event_cars` gives a
post-event scene its own parked cars (responders rescan days later: some cars stayed, some
moved, some left, others arrived); trees, hedges and furniture stay where they were.

Free space: no trunk, hedge, car or furniture piece stands inside a footprint or closer than
`CLEARANCE_M` to one, nor on another object; crowns may overhang roofs (that is the point
of the trees planted 1-4 m from a facade).

Densities per set (`DENSITY`; numbers per building, each a mean of seeded draws):

| set | trees near facades | free trees | hedges | parked cars | furniture |
|---|---|---|---|---|---|
| generic (town with gardens) | 0.8 | 0.6 | 0.4 | 0.8 | 0.6 |
| region (L'Aquila-like centre: narrow streets, few trees) | 0.08 | 0.05 | 0.02 | 1.2 | 0.5 |
| small (sheds, garages, row houses: Dutch terrace streets) | 0.3 | 0.3 | 0.4 | 0.5 | 0.3 |
| bundle (imported buildings) | as generic | | | | |

Tree sizes: small street trees (4-7 m tall, crown radius 1.5-2.5 m), medium (7-12 m,
2.5-4 m) and large (15-20 m, 4-6.5 m, two or three merged crown blobs).
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

CLEARANCE_M = 0.3  # objects keep this far from walls
STYLES = ("none", "typical")


@dataclass(frozen=True)
class Density:
    trees_near: float  # trees 1-4 m from a facade (crowns over roofs), per building
    trees_free: float  # garden and street trees elsewhere, per building
    hedges: float  # hedges along plot edges, per building
    cars: float  # parked cars, per building
    furniture: float  # lamp posts, benches, bins, bollards, per building
    car_offset_m: tuple  # distance of a parked car's side from the facade
    tree_kinds: tuple  # (kind, weight)


DENSITY = {
    "generic": Density(0.8, 0.6, 0.4, 0.8, 0.6, (2.0, 5.0), (("small", 0.35), ("medium", 0.4), ("large", 0.25))),
    "region": Density(0.08, 0.05, 0.02, 1.2, 0.5, (0.4, 1.2), (("small", 0.6), ("medium", 0.3), ("large", 0.1))),
    # per building, and half the buildings are sheds and garages: gardens of a Dutch terrace street
    "small": Density(0.3, 0.3, 0.4, 0.5, 0.3, (1.5, 4.0), (("small", 0.5), ("medium", 0.4), ("large", 0.1))),
}
DENSITY["bundle"] = DENSITY["generic"]

# kind: (total height range m, crown radius range m, crown blobs)
TREE_KINDS = {"small": ((4.0, 7.0), (1.5, 2.5), 1), "medium": ((7.0, 12.0), (2.5, 4.0), 1),
              "large": ((15.0, 20.0), (4.0, 6.5), 3)}
CAR_SIZE = {"small": (3.7, 1.65, 1.45), "medium": (4.4, 1.8, 1.5), "large": (4.9, 1.9, 1.7)}  # L, W, H
FURNITURE = {"lamp": 0.25, "bench": 0.25, "bin": 0.2, "bollard": 0.3}  # kind: share
FURNITURE_RADIUS = {"lamp": 0.3, "bench": 1.0, "bin": 0.35, "bollard": 0.15}


@dataclass
class Tree:
    x: float
    y: float
    trunk_radius: float
    # crown blobs: (cx, cy, cz, rx, ry, rz), cz above the ground at the trunk
    blobs: list
    height: float  # top of the crown above the ground
    kind: str
    z: float = 0.0  # ground height at the trunk

    @property
    def trunk_top(self) -> float:
        """Trunks reach into the lowest blob's centre (so no gap shows)."""
        return min(b[2] for b in self.blobs)


@dataclass
class Hedge:
    x0: float
    y0: float
    x1: float
    y1: float
    width: float
    height: float
    z: float = 0.0


@dataclass
class Car:
    id: int
    x: float
    y: float
    heading: float  # radians, long axis
    length: float
    width: float
    height: float
    z: float = 0.0


@dataclass
class Furniture:
    kind: str
    x: float
    y: float
    heading: float
    height: float
    z: float = 0.0


@dataclass
class Streetscape:
    trees: list = field(default_factory=list)
    hedges: list = field(default_factory=list)
    cars: list = field(default_factory=list)
    furniture: list = field(default_factory=list)


# --- geometry helpers ------------------------------------------------------------------------

class FreeSpace:
    """Footprints (world polygons), the terrain rectangle and the discs already taken."""

    def __init__(self, footprints, bounds, margin=1.0):
        self.polys = [np.asarray(p, np.float64).reshape(-1, 2) for p in footprints]
        self.boxes = np.array([[p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()] for p in self.polys]) \
            if self.polys else np.zeros((0, 4))
        self.bounds = tuple(float(b) for b in bounds)
        self.margin = margin
        self.discs = []  # (x, y, r)

    def wall_distance(self, pts) -> np.ndarray:
        """Distance of points (n, 2) to the nearest footprint; negative inside one."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        best = np.full(len(pts), np.inf)
        for k, poly in enumerate(self.polys):
            box = self.boxes[k]
            near = ((pts[:, 0] > box[0] - 20) & (pts[:, 0] < box[2] + 20) & (pts[:, 1] > box[1] - 20)
                    & (pts[:, 1] < box[3] + 20))
            if not near.any():
                continue
            d = _polygon_distance(pts[near], poly)
            best[near] = np.minimum(best[near], d)
        return best

    def inside_bounds(self, pts, pad=0.0) -> bool:
        x0, y0, x1, y1 = self.bounds
        pts = np.asarray(pts).reshape(-1, 2)
        m = self.margin + pad
        return bool(((pts[:, 0] > x0 + m) & (pts[:, 0] < x1 - m) & (pts[:, 1] > y0 + m) & (pts[:, 1] < y1 - m)).all())

    def free(self, pts, radius) -> bool:
        """Every point (sampling an object) at least `radius` + CLEARANCE_M from walls and
        `radius` from every taken disc, and inside the terrain."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        if not self.inside_bounds(pts, radius):
            return False
        if (self.wall_distance(pts) < radius + CLEARANCE_M).any():
            return False
        if self.discs:
            d = np.asarray(self.discs)
            gap = np.hypot(pts[:, None, 0] - d[None, :, 0], pts[:, None, 1] - d[None, :, 1]) - d[None, :, 2]
            if (gap < radius).any():
                return False
        return True

    def take(self, pts, radius):
        for p in np.asarray(pts, np.float64).reshape(-1, 2):
            self.discs.append((float(p[0]), float(p[1]), float(radius)))


def _polygon_distance(pts, poly) -> np.ndarray:
    """Signed distance of points to a polygon's boundary: negative inside (even-odd rule)."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    e = b - a
    rel = pts[:, None, :] - a[None, :, :]
    t = np.clip((rel * e[None]).sum(-1) / np.maximum((e * e).sum(-1), 1e-12)[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * e[None]
    dist = np.sqrt(((pts[:, None, :] - closest) ** 2).sum(-1)).min(axis=1)
    y = pts[:, 1][:, None]
    crosses = ((a[None, :, 1] > y) != (b[None, :, 1] > y))
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[None, :, 0] + (y - a[None, :, 1]) * e[None, :, 0] / e[None, :, 1]
    inside = (crosses & (pts[:, 0][:, None] < x_at)).sum(axis=1) % 2 == 1
    return np.where(inside, -dist, dist)


def _edges(footprints):
    """Every facade edge: (start (2,), unit direction (2,), outward normal (2,), length, building index)."""
    out = []
    for k, p in enumerate(footprints):
        p = np.asarray(p, np.float64).reshape(-1, 2)
        area2 = float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
        for i in range(len(p)):
            a, b = p[i], p[(i + 1) % len(p)]
            L = float(np.hypot(*(b - a)))
            if L < 1.0:
                continue
            u = (b - a) / L
            n = np.array([u[1], -u[0]]) if area2 > 0 else np.array([-u[1], u[0]])  # outward
            out.append((a, u, n, L, k))
    return out


def _rect_samples(x, y, heading, length, width):
    """Centre, corners and side midpoints of a rotated rectangle (for the free-space test)."""
    c, s = math.cos(heading), math.sin(heading)
    pts = [(0, 0)] + [(sx * length / 2, sy * width / 2) for sx in (-1, 0, 1) for sy in (-1, 0, 1) if (sx, sy) != (0, 0)]
    return np.array([(x + c * px - s * py, y + s * px + c * py) for px, py in pts])


def _count(rng, per_building, n_buildings) -> int:
    return int(rng.poisson(per_building * n_buildings))


# --- placement -------------------------------------------------------------------------------

def _tree(rng, kind, x, y):
    (h0, h1), (r0, r1), blobs = TREE_KINDS[kind]
    height = float(rng.uniform(h0, h1))
    r = float(rng.uniform(r0, r1))
    rz = min(r * float(rng.uniform(0.8, 1.15)), 0.45 * height)
    cz = height - rz
    out = [(x, y, cz, r, r * float(rng.uniform(0.85, 1.15)), rz)]
    for _ in range(blobs - 1):  # large trees: lower side blobs merged with the main crown
        a = float(rng.uniform(0, 2 * math.pi))
        rb = r * float(rng.uniform(0.55, 0.75))
        off = r * float(rng.uniform(0.45, 0.65))
        out.append((x + off * math.cos(a), y + off * math.sin(a), cz - rz * float(rng.uniform(0.2, 0.45)),
                    rb, rb, rb * 0.85))
    trunk_r = {"small": 0.1, "medium": 0.18, "large": 0.3}[kind] * float(rng.uniform(0.8, 1.2))
    return Tree(x, y, trunk_r, out, height, kind)


def _place_trees(rng, space, edges, n_near, n_free, kinds):
    names = [k for k, _ in kinds]
    w = np.array([wt for _, wt in kinds], np.float64)
    trees = []
    for want, near in ((n_near, True), (n_free, False)):
        placed, tries = 0, 0
        while placed < want and tries < 40 * max(want, 1):
            tries += 1
            kind = names[int(rng.choice(len(names), p=w / w.sum()))]
            if near and edges:
                a, u, n, L, _ = edges[int(rng.integers(len(edges)))]
                p = a + u * float(rng.uniform(0.1, 0.9)) * L + n * float(rng.uniform(1.0, 4.0))
            else:
                x0, y0, x1, y1 = space.bounds
                p = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            t = _tree(rng, kind, float(p[0]), float(p[1]))
            if not near and space.wall_distance(p)[0] < 2.0:  # free trees stand in gardens and streets
                continue
            if not space.free(p, t.trunk_radius + 0.3):
                continue
            space.take(p, t.trunk_radius + 0.3)
            trees.append(t)
            placed += 1
    return trees


def _place_hedges(rng, space, edges, n):
    hedges, tries = [], 0
    while len(hedges) < n and tries < 30 * max(n, 1) and edges:
        tries += 1
        a, u, nrm, L, _ = edges[int(rng.integers(len(edges)))]
        off = float(rng.uniform(2.5, 6.0))
        s0, s1 = sorted(rng.uniform(-0.3, 1.3, 2) * L)
        if s1 - s0 < 3.0:
            continue
        p0, p1 = a + u * s0 + nrm * off, a + u * s1 + nrm * off
        width, height = float(rng.uniform(0.6, 1.0)), float(rng.uniform(0.8, 1.8))
        k = max(2, int(math.ceil((s1 - s0) / 0.8)) + 1)
        samples = p0[None] + np.linspace(0, 1, k)[:, None] * (p1 - p0)[None]
        if not space.free(samples, width / 2):
            continue
        space.take(samples, width / 2)
        hedges.append(Hedge(float(p0[0]), float(p0[1]), float(p1[0]), float(p1[1]), width, height))
    return hedges


def _random_car(rng, space, edges, car_id, offset_range):
    for _ in range(60):
        a, u, nrm, L, _ = edges[int(rng.integers(len(edges)))]
        size = list(CAR_SIZE)[int(rng.integers(len(CAR_SIZE)))]
        length, width, height = CAR_SIZE[size]
        off = float(rng.uniform(*offset_range)) + width / 2
        p = a + u * float(rng.uniform(-0.2, 1.2)) * L + nrm * off
        heading = math.atan2(u[1], u[0]) + (math.pi if rng.uniform() < 0.5 else 0.0)
        car = Car(car_id, float(p[0]), float(p[1]), heading, length, width, height)
        if _car_fits(space, car):
            return car
    return None


def _car_samples(car):
    return _rect_samples(car.x, car.y, car.heading, car.length - car.width, 0.0)[[0, 2, 7]]


def _car_fits(space, car) -> bool:
    # three discs of the car's half width along its axis cover it; walls also against corners
    if not space.free(_car_samples(car), car.width / 2):
        return False
    corners = _rect_samples(car.x, car.y, car.heading, car.length, car.width)
    return bool((space.wall_distance(corners) >= CLEARANCE_M).all())


def _place_cars(rng, space, edges, n, offset_range, first_id=1):
    cars, tries = [], 0
    while len(cars) < n and tries < 5 * max(n, 1) and edges:
        tries += 1
        car = _random_car(rng, space, edges, first_id + len(cars), offset_range)
        if car is None:
            continue
        space.take(_car_samples(car), car.width / 2)
        cars.append(car)
    return cars


def _place_furniture(rng, space, edges, n):
    kinds = list(FURNITURE)
    w = np.array([FURNITURE[k] for k in kinds])
    out, tries = [], 0
    while len(out) < n and tries < 30 * max(n, 1) and edges:
        tries += 1
        kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
        a, u, nrm, L, _ = edges[int(rng.integers(len(edges)))]
        p = a + u * float(rng.uniform(0, 1)) * L + nrm * float(rng.uniform(0.8, 4.0))
        r = FURNITURE_RADIUS[kind]
        if not space.free(p, r):
            continue
        space.take(p, r)
        height = {"lamp": float(rng.uniform(5.0, 8.0)), "bench": 0.85, "bin": 0.9, "bollard": 0.9}[kind]
        out.append(Furniture(kind, float(p[0]), float(p[1]), math.atan2(u[1], u[0]), height))
    return out


def plan_streetscape(footprints, bounds, set_name: str, seed: int, ground_z=None) -> Streetscape:
    """Seeded trees, hedges, parked cars and furniture around `footprints` (world polygons,
    (k, 2) each) inside the terrain rectangle `bounds` (x0, y0, x1, y1), at the density of
    `set_name` (`DENSITY`). `ground_z(xy (n, 2)) -> (n,)` gives the terrain height (flat 0
    by default)."""
    if set_name not in DENSITY:
        raise ValueError(f"set must be one of {sorted(DENSITY)}, got {set_name!r}")
    d = DENSITY[set_name]
    rng = np.random.default_rng([seed, 606])
    n_b = len(footprints)
    space = FreeSpace(footprints, bounds)
    edges = _edges(footprints)
    trees = _place_trees(rng, space, edges, _count(rng, d.trees_near, n_b), _count(rng, d.trees_free, n_b),
                         d.tree_kinds)
    hedges = _place_hedges(rng, space, edges, _count(rng, d.hedges, n_b))
    furniture = _place_furniture(rng, space, edges, _count(rng, d.furniture, n_b))
    cars = _place_cars(rng, space, edges, _count(rng, d.cars, n_b), d.car_offset_m)
    scape = Streetscape(trees, hedges, cars, furniture)
    return on_ground(scape, ground_z)


# Post-event fate of a pre-event car: stays, moves along the street, leaves.
CAR_FATE = (("kept", 0.5), ("moved", 0.2), ("gone", 0.3))
NEW_CARS_SHARE = 0.3  # new cars arriving, as a share of the pre-event cars


def post_event_cars(scape: Streetscape, footprints, bounds, set_name: str, seed: int, scene_name: str,
                    ground_z=None) -> list:
    """The parked cars of one post-event scene: each pre-event car kept, moved (2-8 m along
    its street) or gone (`CAR_FATE`), plus new ones (`NEW_CARS_SHARE`), seeded by (seed,
    scene name). Trees, hedges and furniture keep their places and block as before."""
    d = DENSITY[set_name]
    rng = np.random.default_rng([seed, 707, zlib.crc32(scene_name.encode())])
    space = FreeSpace(footprints, bounds)
    for t in scape.trees:
        space.take([(t.x, t.y)], t.trunk_radius + 0.3)
    for h in scape.hedges:
        k = max(2, int(math.ceil(math.hypot(h.x1 - h.x0, h.y1 - h.y0) / 0.8)) + 1)
        space.take(np.linspace((h.x0, h.y0), (h.x1, h.y1), k), h.width / 2)
    for f in scape.furniture:
        space.take([(f.x, f.y)], FURNITURE_RADIUS[f.kind])
    fates = [f for f, _ in CAR_FATE]
    w = np.array([p for _, p in CAR_FATE])
    cars, moved = [], []
    for car in scape.cars:
        fate = fates[int(rng.choice(len(fates), p=w / w.sum()))]
        if fate == "kept":
            space.take(_car_samples(car), car.width / 2)
            cars.append(car)
        elif fate == "moved":
            moved.append(car)
    for car in moved:
        for _ in range(10):
            step = float(rng.uniform(2.0, 8.0)) * (1 if rng.uniform() < 0.5 else -1)
            new = replace(car, x=car.x + step * math.cos(car.heading), y=car.y + step * math.sin(car.heading))
            if _car_fits(space, new):
                space.take(_car_samples(new), new.width / 2)
                cars.append(new)
                break
    edges = _edges(footprints)
    first = max([c.id for c in scape.cars], default=0) + 1
    cars += _place_cars(rng, space, edges, int(rng.poisson(NEW_CARS_SHARE * len(scape.cars))), d.car_offset_m,
                        first_id=first)
    return on_ground(Streetscape(cars=cars), ground_z).cars


def on_ground(scape: Streetscape, ground_z=None) -> Streetscape:
    """Set every object's base height from `ground_z` (None: flat terrain at 0)."""
    if ground_z is None:
        return scape
    for items, xy in ((scape.trees, lambda o: (o.x, o.y)), (scape.cars, lambda o: (o.x, o.y)),
                      (scape.furniture, lambda o: (o.x, o.y)),
                      (scape.hedges, lambda o: ((o.x0 + o.x1) / 2, (o.y0 + o.y1) / 2))):
        if items:
            z = ground_z(np.array([xy(o) for o in items], np.float64))
            for o, zi in zip(items, z):
                o.z = float(zi)
    return scape


def terrain_height_function(vertices, triangles):
    """ground_z(xy) of a terrain mesh (world vertices (n, 3), triangles (m, 3)): the height of
    the triangle under each point (barycentric), the nearest vertex's outside the mesh."""
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(triangles, np.int64)
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    lo = np.minimum(np.minimum(a, b), c)[:, :2]
    hi = np.maximum(np.maximum(a, b), c)[:, :2]

    def ground_z(xy):
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        out = np.empty(len(xy))
        for i, p in enumerate(xy):
            cand = np.flatnonzero((lo[:, 0] <= p[0]) & (hi[:, 0] >= p[0]) & (lo[:, 1] <= p[1]) & (hi[:, 1] >= p[1]))
            z = None
            for k in cand:
                (x1, y1), (x2, y2), (x3, y3) = a[k, :2], b[k, :2], c[k, :2]
                det = (y2 - y3) * (x1 - x3) + (x3 - x2) * (y1 - y3)
                if abs(det) < 1e-12:
                    continue
                l1 = ((y2 - y3) * (p[0] - x3) + (x3 - x2) * (p[1] - y3)) / det
                l2 = ((y3 - y1) * (p[0] - x3) + (x1 - x3) * (p[1] - y3)) / det
                l3 = 1 - l1 - l2
                if min(l1, l2, l3) >= -1e-9:
                    z = l1 * a[k, 2] + l2 * b[k, 2] + l3 * c[k, 2]
                    break
            if z is None:
                z = v[np.argmin(((v[:, :2] - p) ** 2).sum(1)), 2]
            out[i] = z
        return out
    return ground_z


def plan_footprints(plan) -> list:
    """World footprint polygons of a city_plan.CityPlan's buildings (in plan order), then those
    of their annexes (``details="typical"``: one-storey extensions outside the footprint)."""
    from .geometry import poly2d

    out, annexes = [], []
    for b in plan.buildings:
        c, s = math.cos(b.rotation), math.sin(b.rotation)
        R, loc = np.array([[c, s], [-s, c]]), np.asarray(b.location, np.float64)
        p = np.asarray(b.shell["footprint"], np.float64)
        out.append(p @ R + loc)
        ccw = poly2d.ccw(p)
        for d in b.shell.get("details") or []:
            if d.get("kind") != "annex":
                continue
            # as building_details._place_annex: along edge `edge` of the counter-clockwise footprint, outward
            a, e = ccw[d["edge"]], ccw[(d["edge"] + 1) % len(ccw)]
            u = (e - a) / np.linalg.norm(e - a)
            n = np.array([u[1], -u[0]])
            t, w, dep = d["t"], d["width"], d["depth"]
            local = np.array([a + u * (t - w / 2), a + u * (t - w / 2) + n * dep, a + u * (t + w / 2) + n * dep,
                              a + u * (t + w / 2)])
            annexes.append(local @ R + loc)
    return out + annexes  # the buildings' own first, in plan order
