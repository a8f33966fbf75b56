"""Collapses: partial roof, top storey, storey (soft/mid/top), pancake, corner, wing, heap."""
from __future__ import annotations

import math

import numpy as np
from mathutils import Vector

from . import debris as dbr
from . import poly2d
from .common import PatternNotApplicable, edge, exposed_hull_edges, half_space_x, region_polygon, split_for_fraction
from .mesh import (P_BASE, P_CHIMNEY, P_DEBRIS, P_GABLE, P_INNER, P_PARAPET, P_ROOF, P_SLAB, P_STUB, P_WALL, WALL,
                   Labels, add_polygon, bisect, carve, delete_faces, detach, faces_area, faces_where, remove_loose,
                   rotation_matrix, transform_verts, verts_of)

BUILDING_PARTS = {P_WALL, P_ROOF, P_SLAB, P_INNER, P_GABLE, P_PARAPET, P_CHIMNEY, P_BASE, P_STUB}


def _building_faces(bm, lab):
    return faces_where(bm, lab, exclude_parts={P_DEBRIS})


def _group_centroid(faces):
    tot = 0.0
    c = Vector((0, 0, 0))
    for f in faces:
        a = f.calc_area()
        c += f.calc_center_median() * a
        tot += a
    return c / tot if tot > 0 else faces[0].calc_center_median()


def partial_roof_collapse(bm, spec, rng, building_id, area_fraction=0.4, drop=2.0, tilt=25.0):
    """A section of the roof (`area_fraction`, cut across the ridge) breaks off; each of its
    planes drops by `drop` (at its centroid) and ends up inclined `tilt` degrees, resting
    at the latest on the floor below."""
    lab = Labels(bm)
    if not faces_where(bm, lab, parts={P_ROOF}):
        raise PatternNotApplicable("building has no roof faces")
    x0, y0, x1, y1 = spec.bbox
    L = x1 - x0
    seg = float(np.clip(area_fraction, 0.05, 1.0)) * L
    s = float(rng.uniform(x0, x1 - seg)) if seg < L - 1e-6 else x0
    planes = [half_space_x(s - (1e-4 if s <= x0 else 0), True), half_space_x(s + seg + (1e-4 if s + seg >= x1 else 0), False)]
    roof_all = faces_where(bm, lab, parts={P_ROOF})
    roof_area = faces_area(roof_all)
    inside = carve(bm, lambda b: faces_where(b, lab, parts={P_ROOF}), planes)
    # the chimney cannot stay in the air over a collapsed section
    chim = [f for f in faces_where(bm, lab, parts={P_CHIMNEY}) if s <= f.calc_center_median().x <= s + seg]
    if chim and len(chim) == len(faces_where(bm, lab, parts={P_CHIMNEY})):
        delete_faces(bm, chim)
    coll_area = faces_area(inside)
    attic = spec.roof_type != "flat"
    floor_z = spec.eave_height if attic else spec.z_level(spec.storeys - 1)
    tan_t = math.tan(math.radians(tilt))
    groups = {}
    for f in inside:
        groups.setdefault(f[lab.elem], []).append(f)
    plans = []
    for key in sorted(groups):
        faces = detach(bm, groups[key])
        if not faces:
            continue
        c = _group_centroid(faces)
        n0 = faces[0].normal
        dh = np.array([n0.x, n0.y])
        if np.linalg.norm(dh) < 1e-3:
            # flat roof: the section breaks along a line through its centre and sags into a V
            # (both halves inclined `tilt`), which keeps the plates inside the top storey
            dh = np.array([1.0, 0.0]) if rng.uniform() < 0.5 else np.array([0.0, 1.0])
            bisect(bm, faces, (c.x, c.y, c.z), (float(dh[0]), float(dh[1]), 0.0))
            faces = [f for f in bm.faces if f[lab.part] == P_ROOF and f.is_valid
                     and s - 1e-4 <= f.calc_center_median().x <= s + seg + 1e-4 and f.calc_center_median().z > c.z - 1e-3]
            vs = verts_of(faces)
            sd = [abs(float(np.dot(dh, (v.co.x - c.x, v.co.y - c.y)))) for v in vs]
            mean_abs = _mean_abs_offset(faces, c, dh)
            newz = [c.z - drop + tan_t * (x - mean_abs) for x in sd]
            plans.append((faces, vs, newz))
            continue
        dh = dh / np.linalg.norm(dh)
        vs = verts_of(faces)
        newz = [c.z - drop + tan_t * float(np.dot(dh, (v.co.x - c.x, v.co.y - c.y))) for v in vs]
        plans.append((faces, vs, newz))
    # Under a pitched roof the attic floor gives way too when the plates would go through it
    # (EMS-98 grade 4: partial collapse of roofs and floors).
    floor_broken = False
    if attic and plans and min(min(z) for _, _, z in plans) < floor_z + 0.1:
        slab = carve(bm, lambda b: faces_where(b, lab, parts={P_SLAB}, storeys={spec.storeys}), planes)
        delete_faces(bm, slab)
        floor_z = spec.z_level(spec.storeys - 1)
        floor_broken = True
    drops, weights = [], []
    for faces, vs, newz in plans:
        lift = max(0.0, floor_z + 0.1 - min(newz))
        for v, z in zip(vs, newz):
            v.co.z = z + lift
        drops.append(drop - lift)
        weights.append(faces_area(faces))
    bm.normal_update()
    w = np.array(weights) if weights else np.array([1.0])
    return {"area_fraction": coll_area / roof_area if roof_area else 0.0, "drop": float(np.dot(drops, w) / w.sum()) if drops else 0.0,
            "tilt": tilt, "collapsed_area": coll_area, "section": [s, s + seg], "floor_collapsed": floor_broken}


def _mean_abs_offset(faces, c, dh):
    """Area-weighted mean of |dh . (x - c)| over planar faces (exact per triangle fan: the
    faces are split at dh . (x - c) = 0, so |.| is linear on each)."""
    tot, acc = 0.0, 0.0
    for f in faces:
        cos = [v.co for v in f.verts]
        for i in range(1, len(cos) - 1):
            tri = (cos[0], cos[i], cos[i + 1])
            a = (tri[1] - tri[0]).cross(tri[2] - tri[0]).length * 0.5
            m = sum(abs(float(dh[0] * (p.x - c.x) + dh[1] * (p.y - c.y))) for p in tri) / 3.0
            tot += a
            acc += a * m
    return acc / tot if tot > 0 else 0.0


def top_storey_collapse(bm, spec, rng, building_id, footprint_fraction=0.4, solid_fraction=0.2, bulking=1.5):
    """The top storey (and the roof over it) collapses over `footprint_fraction` of the
    footprint, at one end; its debris lies on the floor below."""
    lab = Labels(bm)
    ns = spec.storeys
    if ns < 2:
        raise PatternNotApplicable("top storey collapse needs at least 2 storeys")
    from_high = bool(rng.integers(0, 2))
    xc = split_for_fraction(spec, footprint_fraction, from_high)
    top = ns - 1

    def sel(b):
        return [f for f in _building_faces(b, lab)
                if (f[lab.part] in (P_WALL, P_INNER) and f[lab.storey] == top)
                or (f[lab.part] == P_SLAB and f[lab.storey] == ns)
                or f[lab.part] in (P_ROOF, P_GABLE, P_PARAPET, P_CHIMNEY)]
    inside = carve(bm, sel, [half_space_x(xc, from_high)])
    delete_faces(bm, inside)
    region = region_polygon(spec, xc, from_high)
    a_reg = abs(poly2d.area(region))
    frac = a_reg / spec.footprint_area
    roof_vol = (spec.gross_volume - spec.footprint_area * spec.eave_height) * frac
    vol = dbr.debris_volume(solid_fraction, bulking, a_reg * spec.storey_height + roof_vol)
    field = dbr.heap_field(rng, region, 0.0, plateau=0.3)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, vol, spec.z_level(top))
    return {"footprint_fraction": frac, "end": "+x" if from_high else "-x", "debris_volume": dv,
            "debris_height": pk, "solid_fraction": solid_fraction, "bulking": bulking}


def _upper_verts(bm, lab, z_hi):
    faces = [f for f in bm.faces if min(v.co.z for v in f.verts) >= z_hi - 1e-4]
    return verts_of(faces)


def storey_collapse(bm, spec, rng, building_id, storey, drop, tilt=0.0, offset=0.0, solid_fraction=0.15,
                    bulking=1.5):
    """Storey `storey` is crushed: everything above drops by `drop` (at the hinge side),
    tilts `tilt` degrees about a footprint edge and slides `offset` metres towards it.
    Debris not fitting into the crushed storey forms a skirt around the footprint."""
    lab = Labels(bm)
    ns = spec.storeys
    if not 0 <= storey < ns:
        raise PatternNotApplicable(f"storey {storey} does not exist (building has {ns})")
    hs = spec.storey_height
    z_lo, z_hi = spec.z_level(storey), spec.z_level(storey + 1)
    drop = float(np.clip(drop, 0.0, hs - 0.15))
    crushed = [f for f in _building_faces(bm, lab)
               if f[lab.part] in (P_WALL, P_INNER) and f[lab.storey] == storey]
    delete_faces(bm, crushed)
    remove_loose(bm)
    vs = _upper_verts(bm, lab, z_hi)
    # hinge: a random footprint edge; the block rotates about it so that the rest rises
    hinges = exposed_hull_edges(spec)
    i = hinges[int(rng.integers(0, len(hinges)))]
    a, b, d, n, L = edge(spec, i)
    span = float(np.max((spec.poly - a) @ (-n)))  # footprint depth behind the hinge edge
    max_tilt = math.degrees(math.asin(min(1.0, 0.8 * drop / span))) if span > 0 else 0.0
    tilt = float(min(tilt, max_tilt))
    transform_verts(vs, translate=(0, 0, -drop))
    if tilt > 0:
        axis = np.array([d[0], d[1], 0.0])
        pivot = np.array([a[0], a[1], z_hi - drop])
        R = rotation_matrix(axis, math.radians(tilt))
        probe = np.array([a[0] - n[0], a[1] - n[1], z_hi - drop])
        if (R @ (probe - pivot) + pivot)[2] < probe[2]:
            R = rotation_matrix(axis, -math.radians(tilt))
        transform_verts(vs, rot=R, pivot=pivot)
    if offset > 0:
        transform_verts(vs, translate=(n[0] * offset, n[1] * offset, 0.0))
    bm.normal_update()
    A = spec.footprint_area
    total = dbr.debris_volume(solid_fraction, bulking, A * hs)
    residual = (hs - drop) + 0.5 * span * math.sin(math.radians(tilt))
    visible = max(total - A * residual, 0.3 * total)
    if storey == 0:
        field = dbr.apron_field(rng, spec.poly, 1.2 + offset, inner=1.0)
    else:  # what does not stay in the crushed storey falls to the ground around the building
        field = dbr.apron_field(rng, spec.poly, 1.0 + 0.15 * z_lo + offset, inner=0.05)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, visible, z_lo if storey == 0 else 0.0)
    return {"storey": storey, "drop": drop, "tilt": tilt, "offset": offset, "hinge_edge": i,
            "debris_volume": dv, "debris_volume_total": total, "debris_height": pk,
            "solid_fraction": solid_fraction, "bulking": bulking}


def soft_storey_collapse(bm, spec, rng, building_id, drop=3.0, tilt=5.0, offset=1.0, solid_fraction=0.15,
                         bulking=1.5):
    """Ground storey collapses; the intact upper part drops, tilts and shifts (grade 5)."""
    if spec.storeys < 2:
        raise PatternNotApplicable("soft-storey collapse needs at least 2 storeys")
    return storey_collapse(bm, spec, rng, building_id, 0, drop, tilt, offset, solid_fraction, bulking)


def mid_storey_collapse(bm, spec, rng, building_id, residual_height=0.5, tilt=2.0, offset=0.5,
                        solid_fraction=0.15, bulking=1.5):
    """A middle storey collapses; the upper block drops one storey (grade 5)."""
    ns = spec.storeys
    if ns < 3:
        raise PatternNotApplicable("mid-storey collapse needs at least 3 storeys")
    s = int(rng.integers(1, ns - 1))
    r = storey_collapse(bm, spec, rng, building_id, s, spec.storey_height - residual_height, tilt, offset,
                        solid_fraction, bulking)
    r["residual_height"] = spec.storey_height - r["drop"]
    return r


def top_floor_pancake(bm, spec, rng, building_id, residual_height=0.5, solid_fraction=0.15, bulking=1.5):
    """The top storey is compressed to `residual_height` (grade 4, RC)."""
    if spec.storeys < 2:
        raise PatternNotApplicable("top floor pancake needs at least 2 storeys")
    r = storey_collapse(bm, spec, rng, building_id, spec.storeys - 1, spec.storey_height - residual_height,
                        0.0, 0.0, solid_fraction, bulking)
    r["residual_height"] = spec.storey_height - r["drop"]
    return r


def pancake_collapse(bm, spec, rng, building_id, final_height_fraction=0.15, max_slab_tilt=15.0,
                     spread_fraction=0.2, solid_fraction=0.15, bulking=1.5):
    """All storeys collapse onto each other: the slabs (and the roof) lie stacked within
    `final_height_fraction` of the height, inclined up to `max_slab_tilt`; debris skirt."""
    lab = Labels(bm)
    ns = spec.storeys
    H = spec.height
    groups = []
    for k in range(1, ns + 1):
        g = faces_where(bm, lab, parts={P_SLAB}, storeys={k})
        if g:
            groups.append(g)
    roof = faces_where(bm, lab, parts={P_ROOF, P_PARAPET})
    if roof:
        groups.append(roof)
    if not groups:
        raise PatternNotApplicable("building has no slabs or roof to pancake")
    kill = [f for f in _building_faces(bm, lab) if f[lab.part] in (P_WALL, P_INNER, P_GABLE, P_CHIMNEY, P_STUB)]
    delete_faces(bm, kill)
    remove_loose(bm)
    Hf = float(final_height_fraction) * H
    m = len(groups)
    tilts = []
    centre_z = []
    for idx, g in enumerate(groups):
        g = [f for f in g if f.is_valid]
        vs = verts_of(g)
        zt = Hf * (idx + 1) / m
        zs = np.array([v.co.z for v in vs])
        zmin = zs.min()
        compress = 0.25 if (g is not None and idx == m - 1 and spec.roof_type != "flat") else 0.0
        for v in vs:
            v.co.z = zt + (v.co.z - zmin) * compress
        c = _group_centroid(g)
        R_h = max(math.hypot(v.co.x - c.x, v.co.y - c.y) for v in vs)
        limit = math.degrees(math.asin(min(1.0, max(zt - 0.05, 0.0) / R_h))) if R_h > 0 else 0.0
        ang = min(float(rng.uniform(0.3, 1.0)) * max_slab_tilt, limit)
        az = rng.uniform(0, 2 * math.pi)
        R = rotation_matrix((math.cos(az), math.sin(az), 0.0), math.radians(ang))
        sh = rng.uniform(-1, 1, 2) * min(0.03 * H, 0.6)
        transform_verts(vs, rot=R, pivot=(c.x, c.y, c.z), translate=(sh[0], sh[1], 0.0))
        tilts.append(ang)
        centre_z.append(_group_centroid(g).z)
    bm.normal_update()
    A = spec.footprint_area
    total = dbr.debris_volume(solid_fraction, bulking, spec.gross_volume)
    visible = max(total - A * Hf, 0.3 * total)
    spread = max(float(spread_fraction) * H, 0.5)
    field = dbr.apron_field(rng, spec.poly, spread, inner=1.5)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, visible, 0.0)
    return {"final_height_fraction": max(centre_z) / H, "final_height": max(centre_z),
            "max_slab_tilt": max(tilts), "slab_tilt_limit": max_slab_tilt, "spread_fraction": spread / H,
            "debris_volume": dv, "debris_volume_total": total, "debris_height": pk,
            "solid_fraction": solid_fraction, "bulking": bulking}


def corner_failure(bm, spec, rng, building_id, drop=2.0, tilt=20.0, solid_fraction=0.15, bulking=1.5):
    """A corner column fails: the bays at one corner drop `drop` metres at the corner, the
    slabs above them inclined ~`tilt` degrees (grade 4, RC)."""
    lab = Labels(bm)
    x0, y0, x1, y1 = spec.bbox
    corners = [(x0, y0, 1, 1), (x1, y0, -1, 1), (x1, y1, -1, -1), (x0, y1, 1, -1)]
    inside_fp = [c for c in corners if poly2d.boundary_distance(spec.poly, [(c[0], c[1])])[0] < 1e-6]
    if not inside_fp:
        raise PatternNotApplicable("footprint has no bounding-box corner")
    xc, yc, sx, sy = inside_fp[int(rng.integers(0, len(inside_fp)))]
    ext = 0.8 * min(x1 - x0, y1 - y0)
    Lb = drop / math.tan(math.radians(tilt))
    Lb = float(np.clip(Lb, 3.0, 12.0))
    Lb = min(Lb, ext)
    drop = float(min(Lb * math.tan(math.radians(tilt)), 3.0, spec.storey_height - 0.3))
    tilt_real = math.degrees(math.atan2(drop, Lb))
    faces = _building_faces(bm, lab)
    bisect(bm, faces, (xc + sx * Lb, 0, 0), (1, 0, 0))
    faces = _building_faces(bm, lab)
    bisect(bm, faces, (0, yc + sy * Lb, 0), (0, 1, 0))
    z1 = spec.z_level(1)
    moved = 0
    for v in verts_of(_building_faces(bm, lab)):
        wx = max(0.0, 1.0 - abs(v.co.x - xc) / Lb)
        wy = max(0.0, 1.0 - abs(v.co.y - yc) / Lb)
        w = wx * wy
        if w <= 0:
            continue
        wz = min(1.0, max(0.0, v.co.z / z1))
        v.co.z -= drop * w * wz
        moved += 1
    bm.normal_update()
    # crushed ground-storey corner: debris pile at the corner
    sq = poly2d.rect(min(xc, xc + sx * Lb / 2), min(yc, yc + sy * Lb / 2), max(xc, xc + sx * Lb / 2),
                     max(yc, yc + sy * Lb / 2))
    vol = dbr.debris_volume(solid_fraction, bulking, 0.25 * Lb * Lb * spec.storey_height)
    field = dbr.heap_field(rng, sq, 1.5, plateau=0.2)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, vol, 0.0)
    return {"drop": drop, "tilt": tilt_real, "extent": Lb, "bays": int(math.ceil(Lb / 6.0)),
            "corner": [xc, yc], "debris_volume": dv, "debris_height": pk,
            "solid_fraction": solid_fraction, "bulking": bulking}


def wing_collapse(bm, spec, rng, building_id, footprint_fraction=0.4, spread_fraction=0.2, solid_fraction=0.2,
                  bulking=1.5):
    """One end of the building (`footprint_fraction` of the footprint) collapses into a heap
    (grade 5); the rest stands with its interior exposed at the break."""
    lab = Labels(bm)
    from_high = bool(rng.integers(0, 2))
    xc = split_for_fraction(spec, footprint_fraction, from_high)
    inside = carve(bm, lambda b: _building_faces(b, lab), [half_space_x(xc, from_high)])
    delete_faces(bm, inside)
    region = region_polygon(spec, xc, from_high)
    rest = region_polygon(spec, xc, not from_high)
    a_reg = abs(poly2d.area(region))
    frac = a_reg / spec.footprint_area
    vol = dbr.debris_volume(solid_fraction, bulking, spec.gross_volume * frac)
    spread = float(spread_fraction) * spec.height
    field = dbr.heap_field(rng, region, spread, plateau=0.4, exclude=rest if len(rest) else None)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, vol, 0.0)
    return {"footprint_fraction": frac, "end": "+x" if from_high else "-x", "spread_fraction": spread_fraction,
            "debris_volume": dv, "debris_height": pk, "solid_fraction": solid_fraction, "bulking": bulking}


def debris_heap(bm, spec, rng, building_id, heap_height_fraction=0.25, stub_fraction=0.15,
                stub_height_fraction=0.6, solid_fraction=0.2, bulking=1.5):
    """Total collapse into a heap of `heap_height_fraction` × H (spread 0.1-0.67 H beyond
    the footprint); wall stubs up to one storey on `stub_fraction` of the perimeter."""
    lab = Labels(bm)
    delete_faces(bm, _building_faces(bm, lab))
    remove_loose(bm)
    H = spec.height
    p = spec.poly
    # wall stubs
    per = poly2d.perimeter(p)
    stub_len = 0.0
    if stub_fraction > 0:
        k = int(rng.integers(1, 4))
        w = rng.uniform(0.5, 1.5, k)
        lens = stub_fraction * per * w / w.sum()
        hmax = stub_height_fraction * spec.storey_height
        for Ls in lens:
            i = int(rng.integers(0, len(p)))
            a, b, d, n, L = edge(spec, i)
            Ls = min(float(Ls), L)
            t0 = float(rng.uniform(0, L - Ls)) if Ls < L else 0.0
            m = max(1, int(math.ceil(Ls / 0.7)))
            ts = np.linspace(t0, t0 + Ls, m + 1)
            hs_ = hmax * rng.uniform(0.4, 1.0, m + 1)
            bottom = [Vector((float(a[0] + d[0] * t), float(a[1] + d[1] * t), 0.0)) for t in ts]
            topv = [Vector((float(a[0] + d[0] * t), float(a[1] + d[1] * t), float(h))) for t, h in zip(ts, hs_)]
            bv = [bm.verts.new(c) for c in bottom]
            tv = [bm.verts.new(c) for c in topv]
            for j in range(m):
                add_polygon(bm, lab, None, WALL, building_id, P_STUB, 0, i, verts=[bv[j], bv[j + 1], tv[j + 1], tv[j]])
            stub_len += Ls
    vol = dbr.debris_volume(solid_fraction, bulking, spec.gross_volume)
    target = heap_height_fraction * H
    lo, hi = 0.1 * H, 0.67 * H
    seed = int(rng.integers(0, 2 ** 31))

    def peak(spread, cell=None):
        return dbr.heap_field(np.random.default_rng(seed), p, spread, cell=cell).peak(vol)
    coarse = dbr.cell_size(max(spec.bbox[2] - spec.bbox[0], spec.bbox[3] - spec.bbox[1]) + H, 24)
    if peak(lo, coarse) <= target:
        spread = lo
    elif peak(hi, coarse) >= target:
        spread = hi
    else:
        a_, b_ = lo, hi
        for _ in range(10):
            mid = 0.5 * (a_ + b_)
            if peak(mid, coarse) > target:
                a_ = mid
            else:
                b_ = mid
        spread = 0.5 * (a_ + b_)
    field = dbr.heap_field(np.random.default_rng(seed), p, spread)
    _, dv, pk = dbr.emit(bm, lab, building_id, field, vol, 0.0)
    return {"heap_height_fraction": pk / H, "heap_height_target": heap_height_fraction,
            "spread_fraction": spread / H, "stub_fraction": stub_len / per, "stub_height_fraction": stub_height_fraction,
            "debris_volume": dv, "solid_fraction": solid_fraction, "bulking": bulking}
