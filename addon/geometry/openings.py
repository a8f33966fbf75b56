"""Openings: roof-covering holes, wall holes, RC infill blow-out (grade 3, 4)."""
from __future__ import annotations

import math

import numpy as np

from . import debris as dbr
from . import poly2d
from .common import PatternNotApplicable, edge, interval_planes, z_above, z_below
from .mesh import (P_ROOF, P_WALL, Labels, carve, cut_holes, delete_faces, face_frame, faces_area, faces_where,
                   to_2d)
from ..ems98 import WALL_ZONE_DEPTH

HOLE_MARGIN = 0.15  # m between a hole and a face edge or another hole


def _hole_areas(rng, total, n, a_min, a_max):
    """n hole areas summing to `total` (when the size bounds allow), each within bounds."""
    n = max(1, int(n))
    w = rng.uniform(0.6, 1.4, n)
    a = total * w / w.sum()
    for _ in range(20):
        a = np.clip(a, a_min, a_max)
        miss = total - a.sum()
        if abs(miss) < 1e-9 * max(total, 1):
            break
        free = (a < a_max - 1e-12) if miss > 0 else (a > a_min + 1e-12)
        if not free.any():
            break
        a[free] += miss / free.sum()
    return np.clip(a, a_min, a_max)


def _fits(poly2d_face, hole, placed, margin):
    if not poly2d.contains(poly2d_face, hole).all():
        return False
    if poly2d.boundary_distance(poly2d_face, hole).min() < margin:
        return False
    c = hole.mean(axis=0)
    r = np.linalg.norm(hole - c, axis=1).max()
    for h2 in placed:
        c2 = h2.mean(axis=0)
        r2 = np.linalg.norm(h2 - c2, axis=1).max()
        if np.linalg.norm(c - c2) < r + r2 + margin:
            return False
    return True


def place_holes(rng, faces, areas, margin=HOLE_MARGIN, tries=40):
    """Place irregular holes of the given areas into faces (chosen by area).
    Returns {face: [2D polygons]} in face order, and the frames used."""
    frames = {f: face_frame(f) for f in faces}
    polys = {f: to_2d([v.co for v in f.verts], frames[f]) for f in faces}
    weights = np.array([f.calc_area() for f in faces]) + 1e-9
    placed = {f: [] for f in faces}
    for a in sorted(areas, reverse=True):
        scale = 1.0
        done = False
        for attempt in range(3):
            shape = poly2d.irregular_polygon(rng, a * scale)
            order = list(rng.choice(len(faces), size=len(faces), replace=False, p=weights / weights.sum()))
            for fi in order:
                f = faces[fi]
                P = polys[f]
                lo, hi = P.min(axis=0), P.max(axis=0)
                for _ in range(tries):
                    c = rng.uniform(lo, hi)
                    ang = rng.uniform(0, 2 * math.pi)
                    R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
                    hole = shape @ R.T + c
                    if _fits(P, hole, placed[f], margin):
                        placed[f].append(hole)
                        done = True
                        break
                if done:
                    break
            if done:
                break
            scale *= 0.6
    return {f: hs for f, hs in placed.items() if hs}, frames


def _cut(bm, lab, placed, frames):
    area = 0.0
    n = 0
    for f, holes in placed.items():
        area += sum(abs(poly2d.area(h)) for h in holes)
        n += len(holes)
        cut_holes(bm, lab, f, holes, frames[f])
    return n, area


def roof_holes(bm, spec, rng, building_id, n_holes=8, area_fraction=0.15, hole_min=0.5, hole_max=3.0):
    """Irregular holes through the roof covering (3-15 holes of 0.5-3 m, 5-30 % of the roof)."""
    lab = Labels(bm)
    faces = faces_where(bm, lab, parts={P_ROOF})
    if not faces:
        raise PatternNotApplicable("building has no roof faces (label 'roof')")
    roof_area = faces_area(faces)
    a_min = math.pi / 4 * hole_min ** 2
    a_max = math.pi / 4 * hole_max ** 2
    target = area_fraction * roof_area
    n = int(np.clip(n_holes, math.ceil(target / a_max), max(1, math.floor(target / a_min))))
    areas = _hole_areas(rng, target, n, a_min, a_max)
    placed, frames = place_holes(rng, faces, areas)
    n_made, hole_area = _cut(bm, lab, placed, frames)
    return {"n_holes": n_made, "area_fraction": hole_area / roof_area, "hole_area": hole_area,
            "roof_area": roof_area, "hole_min": hole_min, "hole_max": hole_max}


def _corner_breakout(bm, lab, spec, rng, corner):
    """Masonry breaks out at a building corner: a notch 0.5-1.5 m into both walls, 0.8-2 m
    high, within one storey. Returns the area removed."""
    p = spec.poly
    n = len(p)
    c = p[corner]
    d_next = p[(corner + 1) % n] - c
    d_prev = p[(corner - 1) % n] - c
    d_next /= np.linalg.norm(d_next)
    d_prev /= np.linalg.norm(d_prev)
    k = int(rng.integers(0, spec.storeys))
    zk, zk1 = spec.z_level(k), spec.z_level(k + 1)
    h = float(rng.uniform(0.8, min(2.0, zk1 - zk - 0.3)))
    z0 = float(rng.uniform(zk + 0.1, zk1 - 0.1 - h))
    w1, w2 = float(rng.uniform(0.5, 1.5)), float(rng.uniform(0.5, 1.5))
    planes = [((float(c[0] + d_next[0] * w1), float(c[1] + d_next[1] * w1), 0.0), (float(d_next[0]), float(d_next[1]), 0.0)),
              ((float(c[0] + d_prev[0] * w2), float(c[1] + d_prev[1] * w2), 0.0), (float(d_prev[0]), float(d_prev[1]), 0.0)),
              z_above(z0), z_below(z0 + h)]
    walls = {corner, (corner - 1) % n}
    inside = carve(bm, lambda b: faces_where(b, lab, parts={P_WALL}, elems=walls, storeys={k}), planes)
    a = faces_area(inside)
    delete_faces(bm, inside)
    return a


def wall_holes(bm, spec, rng, building_id, n_facades=2, holes_per_facade=2, area_fraction=0.05,
               hole_min=0.5, hole_max=2.0, corner_breakouts=0):
    """Irregular holes in 1-4 facades (1-4 each, 0.5-2 m, 2-10 % of the facade area) and
    `corner_breakouts` notches at building corners."""
    lab = Labels(bm)
    n_edges = len(spec.poly)
    edges = [i for i in spec.exposed_edges() if faces_where(bm, lab, parts={P_WALL}, elems={i})]
    if not edges:
        raise PatternNotApplicable("building has no wall faces (label 'wall')")
    order = list(rng.permutation(edges))
    chosen = sorted(int(i) for i in order[:max(1, min(int(n_facades), len(edges)))])
    a_min = math.pi / 4 * hole_min ** 2
    a_max = math.pi / 4 * hole_max ** 2
    total_hole, total_facade, n_made = 0.0, 0.0, 0
    per_facade = []
    for i in chosen:
        faces = faces_where(bm, lab, parts={P_WALL}, elems={i})
        fa = faces_area(faces)
        target = area_fraction * fa
        n = int(np.clip(holes_per_facade, math.ceil(target / a_max), max(1, math.floor(target / a_min))))
        areas = _hole_areas(rng, target, n, a_min, a_max)
        placed, frames = place_holes(rng, faces, areas)
        k, ha = _cut(bm, lab, placed, frames)
        n_made += k
        total_hole += ha
        total_facade += fa
        per_facade.append({"facade": i, "holes": k, "area_fraction": ha / fa})
    # corners between two exposed, convex-cornered facades
    p = spec.poly
    ne = len(p)
    exposed = set(spec.exposed_edges())
    corners = []
    for i in range(ne):
        a, b = p[(i - 1) % ne], p[(i + 1) % ne]
        turn = (p[i][0] - a[0]) * (b[1] - p[i][1]) - (p[i][1] - a[1]) * (b[0] - p[i][0])
        if turn > 0 and i in exposed and (i - 1) % ne in exposed:
            corners.append(i)
    n_corner = min(int(corner_breakouts), len(corners))
    corner_area = 0.0
    picked = sorted(int(x) for x in rng.choice(len(corners), size=n_corner, replace=False)) if n_corner else []
    for ci in picked:
        corner_area += _corner_breakout(bm, lab, spec, rng, corners[ci])
    return {"n_facades": len(chosen), "holes_per_facade": n_made / len(chosen),
            "area_fraction": total_hole / total_facade, "hole_area": total_hole + corner_area, "facades": per_facade,
            "hole_min": hole_min, "hole_max": hole_max, "corner_breakouts": n_corner, "corner_area": corner_area,
            "corners": [corners[ci] for ci in picked]}


COLUMN = 0.35  # RC column width (m) left standing between blown-out infill panels
BEAM = 0.5  # beam depth under the slab
SILL = 0.1


def rc_panels(spec):
    """All infill panels: (facade, storey, bay, t0, t1) with t along the facade edge."""
    bay = spec.bay_width if spec.bay_width > 0 else 4.5
    out = []
    for i in spec.exposed_edges():
        _, _, _, _, L = edge(spec, i)
        nb = max(1, int(round(L / bay)))
        w = L / nb
        for k in range(spec.storeys):
            for j in range(nb):
                t0, t1 = j * w + COLUMN / 2, (j + 1) * w - COLUMN / 2
                if t1 - t0 > 1.0:
                    out.append((i, k, j, t0, t1))
    return out


def infill_blowout(bm, spec, rng, building_id, panels=2, storey_share=0.0, debris_height=0.6,
                   solid_fraction=0.15, bulking=1.5):
    """RC infill panels fall out of their frame (whole bays; the frame stays); debris in front.
    `panels` > 0: that many panels anywhere (grade 3); otherwise `storey_share` of one
    storey's panels (grade 4)."""
    lab = Labels(bm)
    allp = [p for p in rc_panels(spec) if faces_where(bm, lab, parts={P_WALL}, elems={p[0]}, storeys={p[1]})]
    if not allp:
        raise PatternNotApplicable("building has no wall faces to blow out")
    if panels and panels > 0:
        idx = rng.choice(len(allp), size=min(int(panels), len(allp)), replace=False)
        chosen = [allp[i] for i in sorted(idx)]
        mode = "panels"
    else:
        k = int(rng.integers(0, spec.storeys))
        row = [p for p in allp if p[1] == k]
        m = max(1, int(round(storey_share * len(row))))
        idx = rng.choice(len(row), size=m, replace=False)
        chosen = [row[i] for i in sorted(idx)]
        mode = "storey"
    hs = spec.storey_height
    removed_area = 0.0
    debris_vol = 0.0
    peak = 0.0
    reach_cache = {}
    for (i, k, j, t0, t1) in chosen:
        a, b, d, n, L = edge(spec, i)
        z0 = spec.z_level(k) + SILL
        z1 = spec.z_level(k + 1) - BEAM
        planes = interval_planes(a, d, t0, t1) + [z_above(z0), z_below(z1)]
        sel = lambda bm_, i=i, k=k: faces_where(bm_, lab, parts={P_WALL}, elems={i}, storeys={k})
        inside = carve(bm, sel, planes)
        area = faces_area(inside)
        delete_faces(bm, inside)
        removed_area += area
        vol = dbr.debris_volume(solid_fraction, bulking, area * WALL_ZONE_DEPTH)
        width = t1 - t0
        key = (round(width, 3), round(vol, 3))
        if key not in reach_cache:
            reach_cache[key] = dbr.fan_reach_for_height(vol, width, debris_height, 0.5, 3.0)
        reach = reach_cache[key]
        pa = a + d * t0
        pb = a + d * t1
        field = dbr.fan_field(rng, pa, pb, n, reach)
        _, v, pk = dbr.emit(bm, lab, building_id, field, vol, 0.0)
        debris_vol += v
        peak = max(peak, pk)
    return {"panels": len(chosen), "mode": mode, "storey_share": storey_share if mode == "storey" else None,
            "opened_area": removed_area, "debris_volume": debris_vol, "debris_height": peak,
            "debris_height_target": debris_height, "solid_fraction": solid_fraction, "bulking": bulking,
            "panel_list": [[i, k, j] for i, k, j, _, _ in chosen]}
