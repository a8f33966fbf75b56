"""Falling elements: chimney loss, parapet loss, gable wall fall, facade topple."""
from __future__ import annotations

import math

import numpy as np

from . import debris as dbr
from . import poly2d
from .common import PatternNotApplicable, edge, interval_planes, z_above
from .mesh import (P_CHIMNEY, P_GABLE, P_PARAPET, P_ROOF, P_SLAB, P_WALL, ROOF, Labels, add_polygon, carve,
                   delete_faces, detach, faces_area, faces_where, verts_of)
from ..ems98 import WALL_ZONE_DEPTH


def chimney_loss(bm, spec, rng, building_id, removed_height=1.0, fragment_distance=2.0, n_fragments=5):
    """The chimney stack breaks: its top `removed_height` falls, fragments land on the roof or
    the ground within `fragment_distance`."""
    lab = Labels(bm)
    faces = faces_where(bm, lab, parts={P_CHIMNEY})
    if not spec.chimney or not faces:
        raise PatternNotApplicable("building has no chimney")
    cx, cy, size, above = spec.chimney
    top = max(v.co.z for f in faces for v in f.verts)
    h = size / 2
    xs = np.array([cx - h, cx + h, cx + h, cx - h])
    ys = np.array([cy - h, cy - h, cy + h, cy + h])
    roof_hi = float(np.max(spec.roof_z(xs, ys)))
    removed = float(min(removed_height, top - roof_hi - 0.1))
    if removed <= 0.05:
        raise PatternNotApplicable("chimney too short to lose its top")
    zc = top - removed
    inside = carve(bm, lambda b: faces_where(b, lab, parts={P_CHIMNEY}), [z_above(zc)])
    delete_faces(bm, inside)
    add_polygon(bm, lab, [(float(x), float(y), zc) for x, y in zip(xs, ys)], ROOF, building_id, P_CHIMNEY,
                spec.storeys, 4)
    # Fragments: the stack is ~half solid (flue); bulked debris split over n pieces.
    vol = 0.5 * size * size * removed * 1.4
    n = max(1, int(n_fragments))
    w = rng.uniform(0.5, 1.5, n)
    vols = vol * w / w.sum()
    p = spec.poly
    placed = 0.0
    for v in vols:
        s = float(v) ** (1 / 3)
        ang = rng.uniform(0, 2 * math.pi)
        r = rng.uniform(0.4, fragment_distance)
        x, y = cx + r * math.cos(ang), cy + r * math.sin(ang)
        on_roof = bool(poly2d.contains(p, [(x, y)])[0])
        z = float(spec.roof_z(x, y)) if on_roof else 0.0
        dbr.add_box(bm, lab, building_id, (x, y, z + 0.35 * s), (s, s * 0.8, s * 0.6),
                    yaw=rng.uniform(0, math.pi), pitch=rng.uniform(-0.4, 0.4))
        placed += s * s * 0.8 * s * 0.6
    return {"removed_height": removed, "fragment_distance": fragment_distance, "n_fragments": n,
            "debris_volume": placed}


def _fan(bm, lab, rng, building_id, a, b, n, volume, height, reach_lo, reach_hi):
    width = float(np.linalg.norm(np.asarray(b) - np.asarray(a)))
    reach = dbr.fan_reach_for_height(volume, width, height, reach_lo, reach_hi)
    field = dbr.fan_field(rng, a, b, n, reach)
    _, v, pk = dbr.emit(bm, lab, building_id, field, volume, 0.0)
    return v, pk, reach


def parapet_loss(bm, spec, rng, building_id, length_fraction=0.3, solid_fraction=0.2, bulking=1.5):
    """Parapet (or cornice) segments totalling `length_fraction` of the roof edge fall."""
    lab = Labels(bm)
    if not faces_where(bm, lab, parts={P_PARAPET}):
        raise PatternNotApplicable("building has no parapet")
    p = spec.poly
    ne = len(p)
    lens = [edge(spec, i)[4] for i in range(ne)]
    per = float(sum(lens))
    starts = np.concatenate([[0.0], np.cumsum(lens)])
    total = length_fraction * per
    k = int(rng.integers(1, 4))
    w = rng.uniform(0.5, 1.5, k)
    seg = total * w / w.sum()
    # non-overlapping intervals along the perimeter
    gaps = rng.uniform(0.5, 1.5, k)
    free = max(per - total, 0.0)
    gaps = free * gaps / gaps.sum()
    s = rng.uniform(0, per)
    intervals = []
    for L, g in zip(seg, gaps):
        intervals.append((s, s + L))
        s += L + g
    removed_len, removed_area, dvol, peak = 0.0, 0.0, 0.0, 0.0
    ph = spec.effective_parapet_height
    H = spec.eave_height
    for s0, s1 in intervals:
        for rep in (0.0, per):  # wrap around the start of the perimeter
            for i in range(ne):
                if i in spec.party_walls:
                    continue
                e0, e1 = starts[i] + rep, starts[i + 1] + rep
                lo, hi = max(s0, e0), min(s1, e1)
                if hi - lo < 0.05:
                    continue
                a, b, d, n, L = edge(spec, i)
                t0, t1 = lo - e0, hi - e0
                inside = carve(bm, lambda b_, i=i: faces_where(b_, lab, parts={P_PARAPET}, elems={i}),
                               interval_planes(a, d, t0, t1))
                area = faces_area(inside)
                if area <= 0:
                    continue
                delete_faces(bm, inside)
                removed_len += t1 - t0
                removed_area += area
                vol = dbr.debris_volume(solid_fraction, bulking, area * WALL_ZONE_DEPTH)
                reach = float(np.clip(0.25 * H, 1.0, 3.0))
                field = dbr.fan_field(rng, a + d * t0, a + d * t1, n, reach)
                _, v, pk = dbr.emit(bm, lab, building_id, field, vol, 0.0)
                dvol += v
                peak = max(peak, pk)
    return {"length_fraction": removed_len / per, "removed_length": removed_len, "parapet_height": ph,
            "removed_area": removed_area, "debris_volume": dvol, "debris_height": peak,
            "solid_fraction": solid_fraction, "bulking": bulking}


def gable_fall(bm, spec, rng, building_id, gable_fraction=0.6, fan_height=0.5, solid_fraction=0.2,
               bulking=1.5):
    """The top `gable_fraction` (by area) of one gable triangle falls outward; debris fan
    reaching 0.5-1.0 × gable height."""
    lab = Labels(bm)
    exposed = set(spec.exposed_edges())
    sides = [i for i in spec.gable_edges() if i in exposed and faces_where(bm, lab, parts={P_GABLE}, elems={i})]
    if not sides:
        raise PatternNotApplicable("building has no gable wall")
    i = sides[int(rng.integers(0, len(sides)))]
    H = spec.eave_height
    hg = spec.ridge_rise
    f = float(np.clip(gable_fraction, 0.0, 1.0))
    zc = H + hg * (1.0 - math.sqrt(f)) if f < 0.999 else H - 1e-3
    inside = carve(bm, lambda b: faces_where(b, lab, parts={P_GABLE}, elems={i}), [z_above(zc)])
    area = faces_area(inside)
    delete_faces(bm, inside)
    a, b, d, n, L = edge(spec, i)
    w = L * math.sqrt(f)
    mid = a + d * (L / 2)
    pa, pb = mid - d * (w / 2), mid + d * (w / 2)
    vol = dbr.debris_volume(solid_fraction, bulking, area * WALL_ZONE_DEPTH)
    dv, pk, reach = _fan(bm, lab, rng, building_id, pa, pb, n, vol, fan_height, max(0.5 * hg, 0.5), max(hg, 1.0))
    total_gable = 0.5 * L * hg
    return {"gable_fraction": area / total_gable if total_gable else 0.0, "gable": i, "removed_area": area,
            "debris_volume": dv, "fan_height": pk, "fan_height_target": fan_height,
            "fan_reach": reach / hg if hg else None, "solid_fraction": solid_fraction, "bulking": bulking}


def facade_topple(bm, spec, rng, building_id, facade_fraction=0.5, height_fraction=0.5, fan_height=1.0,
                  solid_fraction=0.2, bulking=1.5, roof_drop=0.0, sag_depth=3.0):
    """Part of one facade (`facade_fraction` of its length, the top `height_fraction` of its
    storeys, at least one) topples outward; debris fan 0.5-1.0 × wall height long. The roof
    and floors that rested on the fallen wall lose their support (`_sag_over_fallen_wall`): a
    strip `sag_depth` deep hinges down, its edge `roof_drop` lower (0: the roof stays)."""
    lab = Labels(bm)
    cands = []
    for i in spec.exposed_edges():
        if edge(spec, i)[4] >= 3.0 and faces_where(bm, lab, parts={P_WALL}, elems={i}):
            cands.append(i)
    if not cands:
        raise PatternNotApplicable("building has no facade of at least 3 m")
    i = cands[int(rng.integers(0, len(cands)))]
    a, b, d, n, L = edge(spec, i)
    ns = spec.storeys
    m = int(np.clip(round(height_fraction * ns), 1, ns))
    k0 = ns - m
    z0 = spec.z_level(k0)
    seg = float(np.clip(facade_fraction, 0.05, 1.0)) * L
    t0 = float(rng.uniform(0.0, L - seg)) if seg < L else 0.0
    t1 = t0 + seg
    eps = 1e-4
    planes = interval_planes(a, d, t0 - (eps if t0 <= 0 else 0), t1 + (eps if t1 >= L else 0)) + [z_above(z0 - eps)]
    parts = {P_WALL, P_PARAPET} | ({P_GABLE} if m == ns else set())
    inside = carve(bm, lambda b_: faces_where(b_, lab, parts=parts, elems={i}), planes)
    area = faces_area(inside)
    top = max((v.co.z for f in inside for v in f.verts), default=spec.eave_height)
    delete_faces(bm, inside)
    hw = top - z0
    vol = dbr.debris_volume(solid_fraction, bulking, area * WALL_ZONE_DEPTH)
    dv, pk, reach = _fan(bm, lab, rng, building_id, a + d * t0, a + d * t1, n, vol, fan_height,
                         0.5 * hw, 1.0 * hw)
    sag = _sag_over_fallen_wall(bm, lab, spec, a, d, n, t0, t1, z0, roof_drop, sag_depth)
    return {"facade": i, "facade_fraction": seg / L, "height_fraction": m / ns, "collapsed_storeys": m,
            "removed_area": area, "wall_height": hw, "debris_volume": dv, "fan_height": pk,
            "fan_height_target": fan_height, "fan_reach": reach / hw, "solid_fraction": solid_fraction,
            "bulking": bulking, **sag}


# The sagging roof ends this far above the wall left standing (or the ground): it rests on it.
SAG_REST_M = 0.1


def _sag_over_fallen_wall(bm, lab, spec, a, d, n, t0, t1, z_rest, drop, depth):
    """The roof over the fallen part of a facade loses the wall it bore on (rafters, a flat
    roof's slab): the roof strip behind segment [t0, t1] of the facade, `depth` deep, breaks
    off its neighbours and hinges down about the line `depth` behind the facade, so that its
    edge at the facade is `drop` lower, never below `z_rest` + SAG_REST_M (the wall left
    standing). Floors above `z_rest` in the strip spanned onto the same wall and fall (they
    would otherwise stand above the sagged roof). Returns the record: the drop reached, the
    depth, the roof area that sagged and the floor area that fell."""
    out = {"roof_drop": 0.0, "sag_depth": float(depth), "sagged_roof_area": 0.0, "fallen_floor_area": 0.0}
    if drop <= 0.0:
        return out
    span = float(np.max((spec.poly - a) @ (-n)))  # footprint depth behind the facade
    depth = float(np.clip(depth, 0.5, max(span, 0.5)))
    out["sag_depth"] = depth
    eps = 1e-4
    hinge = a - n * depth
    planes = interval_planes(a, d, t0 - eps, t1 + eps) + [((float(hinge[0]), float(hinge[1]), 0.0),
                                                          (float(-n[0]), float(-n[1]), 0.0))]
    strip = carve(bm, lambda b_: faces_where(b_, lab, parts={P_ROOF}), planes)
    if not strip:
        return out
    strip = detach(bm, strip)
    vs = verts_of(strip)
    # 1 at the facade line, 0 at the hinge; an eave overhang (behind < 0) drops further, as a
    # rigid plate turning about the hinge does
    weight = [1.0 - float((v.co.x - a[0]) * -n[0] + (v.co.y - a[1]) * -n[1]) / depth for v in vs]
    room = [(v.co.z - z_rest - SAG_REST_M) / w for v, w in zip(vs, weight) if w > 1e-6]
    drop = float(np.clip(drop, 0.0, max(0.0, min(room, default=0.0))))
    for v, w in zip(vs, weight):
        v.co.z -= drop * max(w, 0.0)
    bm.normal_update()
    out["roof_drop"] = drop
    out["sagged_roof_area"] = faces_area(strip)
    if drop > 0.0:
        floors = carve(bm, lambda b_: [f for f in faces_where(b_, lab, parts={P_SLAB})
                                       if f.calc_center_median().z > z_rest + eps], planes)
        out["fallen_floor_area"] = faces_area(floors)
        delete_faces(bm, floors)
    return out
