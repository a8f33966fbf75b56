"""Building shells: outer walls per storey and facade, floor slabs, coarse inner walls and a
flat (optionally with parapet), gable or hip roof, optionally a chimney, and procedural
roof and facade details (``details``: dormers, overhangs, balconies, ...; see details.py).

Slabs and inner walls are labelled ``interior`` (4) so that a hole shows something behind
it. The shell is built in the object's local frame: z = 0 is the ground, the footprint is a
counter-clockwise polygon; pitched roofs need a rectangular footprint (ridge along local x).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from . import details as dtl
from . import poly2d
from .mesh import (INTERIOR, P_CHIMNEY, P_GABLE, P_INNER, P_ROOF, P_SLAB, P_WALL, ROOF, WALL,
                   Labels, add_polygon)

ROOF_TYPES = ("flat", "gable", "hip")


@dataclass
class ShellSpec:
    footprint: list  # [[x, y], ...] counter-clockwise, local frame
    storeys: int = 2
    storey_height: float = 3.0
    roof: str = "flat"  # flat | gable | hip
    roof_pitch: float = 30.0  # degrees
    parapet_height: float = 0.0  # flat roofs only; 0 = none
    chimney: list | None = None  # [x, y, size, height above the roof]
    inner_wall_spacing: float = 5.0  # cross walls every ~this many metres; 0 = none
    spine_wall: bool = True  # longitudinal inner wall when the footprint is deep enough
    bay_width: float = 0.0  # RC frame bay width along facades (0 = masonry, no frame)
    party_walls: list = field(default_factory=list)  # footprint edges abutting a neighbour
    material: str = "masonry"
    typology: str = "generic"
    extra: dict = field(default_factory=dict)
    details: list = field(default_factory=list)  # [{"kind": ..., params}], see geometry/details.py

    def __post_init__(self):
        # counter-clockwise footprint: edge i runs from vertex i to i+1 with the outside on
        # its right; party_walls and facade indices refer to this order
        if poly2d.area(np.asarray(self.footprint, dtype=np.float64)) < 0:
            self.footprint = [list(p) for p in self.footprint[::-1]]

    # --- derived -------------------------------------------------------------------------
    @property
    def poly(self) -> np.ndarray:
        return poly2d.ccw(np.asarray(self.footprint, dtype=np.float64))

    @property
    def eave_height(self) -> float:
        return self.storeys * self.storey_height

    def z_level(self, k: int) -> float:
        return k * self.storey_height

    @property
    def is_rect(self) -> bool:
        p = self.poly
        if len(p) != 4:
            return False
        x0, y0 = p.min(axis=0)
        x1, y1 = p.max(axis=0)
        return all((abs(x - x0) < 1e-6 or abs(x - x1) < 1e-6) and (abs(y - y0) < 1e-6 or abs(y - y1) < 1e-6)
                   for x, y in p)

    @property
    def bbox(self):
        p = self.poly
        (x0, y0), (x1, y1) = p.min(axis=0), p.max(axis=0)
        return float(x0), float(y0), float(x1), float(y1)

    @property
    def roof_type(self) -> str:
        return self.roof if (self.roof in ("gable", "hip") and self.is_rect) else "flat"

    @property
    def ridge_rise(self) -> float:
        if self.roof_type == "flat":
            return 0.0
        x0, y0, x1, y1 = self.bbox
        span = (y1 - y0) if self.roof_type == "gable" else min(x1 - x0, y1 - y0)
        return 0.5 * span * math.tan(math.radians(self.roof_pitch))

    @property
    def height(self) -> float:
        """Top of the walls plus roof rise (parapet and chimney excluded)."""
        return self.eave_height + self.ridge_rise

    @property
    def footprint_area(self) -> float:
        return abs(poly2d.area(self.poly))

    @property
    def gross_volume(self) -> float:
        """Enclosed volume (storeys plus the roof space)."""
        x0, y0, x1, y1 = self.bbox
        L, W = x1 - x0, y1 - y0
        roof = 0.0
        if self.roof_type == "gable":
            roof = 0.5 * W * self.ridge_rise * L
        elif self.roof_type == "hip":
            r = self.ridge_rise
            roof = W * r * (L / 2 - W / 6) if L >= W else L * r * (W / 2 - L / 6)
        return self.footprint_area * self.eave_height + roof

    def roof_z(self, x, y):
        """Height of the roof surface above (x, y) (inside the footprint)."""
        H = self.eave_height
        t = self.roof_type
        if t == "flat":
            return np.full(np.shape(x), H) if np.ndim(x) else H
        x0, y0, x1, y1 = self.bbox
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        tp = math.tan(math.radians(self.roof_pitch))
        dy = (y1 - y0) / 2 - np.abs(np.asarray(y) - cy)
        if t == "gable":
            return H + tp * np.maximum(dy, 0)
        dx = (x1 - x0) / 2 - np.abs(np.asarray(x) - cx)
        return H + tp * np.maximum(np.minimum(dx, dy), 0)

    def features(self) -> set:
        f = set()
        t = self.roof_type
        if t != "flat":
            f.add("pitched")
        if t == "gable":
            f.add("gable")
        if t == "flat" and self.effective_parapet_height > 0:
            f.add("parapet")
        if self.chimney:
            f.add("chimney")
        if self.storeys >= 2:
            f.add("storeys>=2")
        if self.storeys >= 3:
            f.add("storeys>=3")
        return f

    @property
    def effective_parapet_height(self) -> float:
        """Parapet of a flat roof: the shell's own, else that of a parapet detail."""
        return dtl.parapet_height(self)

    def exposed_edges(self) -> list[int]:
        """Footprint edges that face a street or yard (not a neighbour's party wall);
        all edges when every one is marked as a party wall."""
        n = len(self.footprint)
        out = [i for i in range(n) if i not in set(self.party_walls)]
        return out or list(range(n))

    def gable_edges(self) -> list[int]:
        """Footprint edge indices carrying a gable (the ends across the ridge)."""
        if self.roof_type != "gable":
            return []
        p = self.poly
        out = []
        for i in range(len(p)):
            a, b = p[i], p[(i + 1) % len(p)]
            if abs(a[0] - b[0]) < 1e-6:  # edge along y: an end of a ridge along x
                out.append(i)
        return out

    # --- persistence ----------------------------------------------------------------------
    def to_json(self) -> str:
        d = asdict(self)
        d["footprint"] = [[float(x), float(y)] for x, y in self.footprint]
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "ShellSpec":
        d = json.loads(text)
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


def rect_footprint(length: float, width: float) -> list:
    """Centred rectangle, long side along local x."""
    return poly2d.rect(-length / 2, -width / 2, length / 2, width / 2).tolist()


def build_shell(bm, spec: ShellSpec, building_id: int) -> Labels:
    """Add the building's faces to `bm` (local frame) labelled with `building_id`."""
    lab = Labels(bm)
    p = spec.poly
    n = len(p)
    ns = spec.storeys
    if ns < 1:
        raise ValueError(f"storeys must be >= 1, got {ns}")
    if n < 3 or abs(poly2d.area(p)) < 1.0:
        raise ValueError("footprint must be a polygon of at least 1 m²")
    levels = [spec.z_level(k) for k in range(ns + 1)]
    H = levels[-1]
    bid = building_id
    # Outer walls: a grid of vertices shared between facades and storeys.
    grid = [[bm.verts.new((float(x), float(y), z)) for z in levels] for x, y in p]
    for i in range(n):
        j = (i + 1) % n
        for k in range(ns):
            add_polygon(bm, lab, None, WALL, bid, P_WALL, k, i,
                        verts=[grid[i][k], grid[j][k], grid[j][k + 1], grid[i][k + 1]])
    roof_type = spec.roof_type
    # Floor slabs (not the ground floor: the terrain is there); under a pitched roof also the
    # attic floor.
    top_slab = ns if roof_type != "flat" else ns - 1
    for k in range(1, top_slab + 1):
        add_polygon(bm, lab, [(x, y, levels[k]) for x, y in p], INTERIOR, bid, P_SLAB, k, 0)
    # Coarse inner walls.
    _inner_walls(bm, lab, spec, p, levels, bid)
    # Roof.
    x0, y0, x1, y1 = spec.bbox
    if roof_type == "flat":
        add_polygon(bm, lab, [(x, y, H) for x, y in p], ROOF, bid, P_ROOF, ns, 0)
        ph = spec.effective_parapet_height
        if ph > 0:
            dtl.parapet(bm, lab, spec, bid, ph)
    else:
        r = spec.ridge_rise
        cy = (y0 + y1) / 2
        zr = H + r
        if roof_type == "gable":
            south = [(x0, y0, H), (x1, y0, H), (x1, cy, zr), (x0, cy, zr)]
            north = [(x1, y1, H), (x0, y1, H), (x0, cy, zr), (x1, cy, zr)]
            rv = {}

            def V(c):
                if c not in rv:
                    rv[c] = bm.verts.new(c)
                return rv[c]
            add_polygon(bm, lab, None, ROOF, bid, P_ROOF, ns, 0, verts=[V(c) for c in south])
            add_polygon(bm, lab, None, ROOF, bid, P_ROOF, ns, 1, verts=[V(c) for c in north])
            # gable triangles, outward normals -x (west) and +x (east), sharing wall-top vertices
            corner = {(round(float(x), 6), round(float(y), 6)): i for i, (x, y) in enumerate(p)}
            gw = [grid[corner[(round(x0, 6), round(y1, 6))]][ns], grid[corner[(round(x0, 6), round(y0, 6))]][ns]]
            ge = [grid[corner[(round(x1, 6), round(y0, 6))]][ns], grid[corner[(round(x1, 6), round(y1, 6))]][ns]]
            west_edge = [i for i in spec.gable_edges() if abs(p[i][0] - x0) < 1e-6][0]
            east_edge = [i for i in spec.gable_edges() if abs(p[i][0] - x1) < 1e-6][0]
            add_polygon(bm, lab, None, WALL, bid, P_GABLE, ns, west_edge,
                        verts=gw + [bm.verts.new((x0, cy, zr))])
            add_polygon(bm, lab, None, WALL, bid, P_GABLE, ns, east_edge,
                        verts=ge + [bm.verts.new((x1, cy, zr))])
        else:  # hip
            L, W = x1 - x0, y1 - y0
            cx = (x0 + x1) / 2
            if L >= W:
                half = (L - W) / 2
                ra, rb = (cx - half, cy, zr), (cx + half, cy, zr)
            else:
                half = (W - L) / 2
                ra, rb = (cx, cy - half, zr), (cx, cy + half, zr)
            rv = {}

            def V(c):
                key = tuple(round(float(t), 9) for t in c)
                if key not in rv:
                    rv[key] = bm.verts.new(key)
                return rv[key]
            c00, c10, c11, c01 = (x0, y0, H), (x1, y0, H), (x1, y1, H), (x0, y1, H)
            if L >= W:
                planes = [[c00, c10, rb, ra], [c11, c01, ra, rb], [c10, c11, rb], [c01, c00, ra]]
            else:
                planes = [[c00, c10, ra], [c10, c11, rb, ra], [c11, c01, rb], [c01, c00, ra, rb]]
            for e, pl in enumerate(planes):
                vs = []
                for c in pl:
                    vv = V(c)
                    if vv not in vs:
                        vs.append(vv)
                add_polygon(bm, lab, None, ROOF, bid, P_ROOF, ns, e, verts=vs)
    if spec.chimney:
        _chimney(bm, lab, spec, bid)
    dtl.build_details(bm, lab, spec, bid)
    bm.normal_update()
    return lab


def _inner_walls(bm, lab, spec, p, levels, bid):
    s = spec.inner_wall_spacing
    x0, y0, x1, y1 = spec.bbox
    segs = []  # (ax, ay, bx, by)
    if s > 0:
        L = x1 - x0
        k = int(L // s)
        for j in range(1, k + 1):
            x = x0 + L * j / (k + 1)
            for t0, t1 in poly2d.line_segments_inside(p, (x, y0 - 1.0), (0.0, 1.0)):
                segs.append((x, y0 - 1.0 + t0, x, y0 - 1.0 + t1))
    if spec.spine_wall and (y1 - y0) >= 8.0:
        y = (y0 + y1) / 2
        for t0, t1 in poly2d.line_segments_inside(p, (x0 - 1.0, y), (1.0, 0.0)):
            segs.append((x0 - 1.0 + t0, y, x0 - 1.0 + t1, y))
    for ax, ay, bx, by in segs:
        if math.hypot(bx - ax, by - ay) < 0.5:
            continue
        for k in range(len(levels) - 1):
            za, zb = levels[k], levels[k + 1]
            add_polygon(bm, lab, [(ax, ay, za), (bx, by, za), (bx, by, zb), (ax, ay, zb)],
                        INTERIOR, bid, P_INNER, k, 0)


def _chimney(bm, lab, spec, bid):
    cx, cy, size, above = spec.chimney
    dtl.roof_box(bm, lab, spec.roof_z, cx, cy, size, size, above, bid, P_CHIMNEY, spec.storeys, 0,
                 side_elems=[0, 1, 2, 3], top_elem=4)


def chimney_top(spec: ShellSpec) -> float:
    cx, cy, size, above = spec.chimney
    h = size / 2
    xs = np.array([cx - h, cx + h, cx + h, cx - h])
    ys = np.array([cy - h, cy - h, cy + h, cy + h])
    return float(np.max(spec.roof_z(xs, ys))) + above
