"""Compiled inner loops of the scanner (numba, GIL released).

Each loop is one pass over a batch that numpy would do in ten: building rays, refining
Embree's hits in float64 and packing LAS records. They are plain loops with the same
arithmetic as their numpy references of the same names in `_scan_reference` (tests compare
each pair, and whole scans of both byte for byte).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(**_JIT)
def pulse_rays(t, theta, t_start, start, velocity, down, right):
    """Origins and unit directions of pulses, in float64 and float32 (Embree's input)."""
    n = t.shape[0]
    o64 = np.empty((n, 3))
    d64 = np.empty((n, 3))
    o32 = np.empty((n, 3), np.float32)
    d32 = np.empty((n, 3), np.float32)
    for i in range(n):
        dt = t[i] - t_start
        c = math.cos(theta[i])
        s = math.sin(theta[i])
        for k in range(3):
            o = start[k] + dt * velocity[k]
            d = c * down[k] + s * right[k]
            o64[i, k] = o
            d64[i, k] = d
            o32[i, k] = o
            d32[i, k] = d
    return o64, d64, o32, d32


@njit(**_JIT)
def refine_hits(origins, directions, face, normals, plane_d, max_range):
    """Distance to the hit face's plane in float64; face = -1 where the ray is parallel to
    it (grazing) or the hit falls outside [0, max_range]. Modifies `face` in place."""
    n = face.shape[0]
    t = np.full(n, np.inf)
    for i in range(n):
        f = face[i]
        if f < 0:
            continue
        num = plane_d[f]
        den = 0.0
        for k in range(3):
            num -= normals[f, k] * origins[i, k]
            den += normals[f, k] * directions[i, k]
        if den == 0.0:
            face[i] = -1
            continue
        ti = num / den
        if not (ti >= 0.0 and ti <= max_range):
            face[i] = -1
            continue
        t[i] = ti
    return t


@njit(inline="always", **_JIT)
def _write_point(cols, m, xyz_int, gps, theta, forward, edge, ret, nret, line_id, building, grade_, surface_,
                 cls, intensity_):
    """Fill row m of the LAS columns (X, Y, Z, intensity, gps_time, scan_angle, bit_fields,
    classification_flags, classification, user_data, point_source_id, building_id, grade, surface)."""
    cols[0][m] = np.int32(xyz_int[0])
    cols[1][m] = np.int32(xyz_int[1])
    cols[2][m] = np.int32(xyz_int[2])
    cols[3][m] = intensity_
    cols[4][m] = gps
    # LAS 1.4 scan angle: int16 in units of 0.006°
    cols[5][m] = np.int16(np.rint((theta * (180.0 / math.pi)) / 0.006))
    cols[6][m] = (ret & 15) | ((nret & 15) << 4)
    cols[7][m] = (np.uint8(forward) << 6) | (np.uint8(edge) << 7)
    cols[8][m] = cls
    cols[9][m] = 0
    cols[10][m] = line_id
    cols[11][m] = building
    cols[12][m] = grade_
    cols[13][m] = surface_


@njit(inline="always", **_JIT)
def _intensity(reflect, normals, f, d, rng, ref2):
    """ρ · |cos θ_inc| · R_ref² / R² scaled to uint16 (see quakescan.acquisition.reflectance; its numpy
    reference `intensity` does the same arithmetic in the same order)."""
    cos = abs(normals[f, 0] * d[0] + normals[f, 1] * d[1] + normals[f, 2] * d[2])
    v = 65535.0 * reflect * cos * ref2 / (rng * rng)
    if v >= 65535.0:
        return np.uint16(65535)
    return np.uint16(np.rint(v))


@njit(**_JIT)
def _to_ints(o, d, dist, shift, scale, xyz_int, mins, maxs):
    """Scaled integer coordinates of o + d·dist + shift; False when one leaves int32."""
    for a in range(3):
        v = np.rint((o[a] + d[a] * dist + shift[a]) / scale)
        if v < -2147483648.0 or v > 2147483647.0:
            return False
        iv = np.int64(v)
        xyz_int[a] = iv
        mins[a] = min(mins[a], iv)
        maxs[a] = max(maxs[a], iv)
    return True


@njit(**_JIT)
def pack_points(ray, pulse, face, rng, noise, noise_sigma, ret, nret, origins, directions, shift, scale,
                gps, theta, forward, edge, line_id, f_building, f_grade, f_surface, f_class, normals, f_reflect,
                ref2, cols):
    """Write point k (ray[k] of the batch's rays, pulse[k] of its pulses) into the LAS columns
    `cols` (see `_write_point`); the range is rng[k] + noise_sigma * noise[k]; the intensity
    comes from rng[k] (without noise), the face's reflectance and normal (`_intensity`).

    Returns (ok, int mins (3,), int maxs (3,), points by return number (16,), points by face):
    ok is False when a coordinate does not fit int32 at `scale` (the caller raises)."""
    mins = np.full(3, np.iinfo(np.int64).max, np.int64)
    maxs = np.full(3, np.iinfo(np.int64).min, np.int64)
    by_return = np.zeros(16, np.int64)
    by_face = np.zeros(f_class.shape[0], np.int64)
    xyz_int = np.empty(3, np.int64)
    for k in range(ray.shape[0]):
        r, p, f = ray[k], pulse[k], face[k]
        if not _to_ints(origins[r], directions[r], rng[k] + noise_sigma * np.float64(noise[k]), shift, scale,
                        xyz_int, mins, maxs):
            return False, mins, maxs, by_return, by_face
        _write_point(cols, k, xyz_int, gps[p], theta[p], forward[p], edge[p], ret[k], nret[k], line_id,
                     f_building[f], f_grade[f], f_surface[f], f_class[f],
                     _intensity(f_reflect[f], normals, f, directions[r], rng[k], ref2))
        by_return[ret[k] & 15] += 1
        by_face[f] += 1
    return True, mins, maxs, by_return, by_face


@njit(**_JIT)
def _deflect(t, g0, rate, half_sweep, oscillating):
    phase = (t - g0) * rate
    line = math.floor(phase)
    frac = phase - line
    forward = True
    if oscillating:
        forward = (np.int64(line) % 2) == 0
    if forward:
        return -half_sweep + 2 * half_sweep * frac, line, forward
    return half_sweep - 2 * half_sweep * frac, line, forward


@njit(**_JIT)
def fov_pulses(lo, hi, t_start, prr, rate, g0, half_sweep, half_fov, oscillating, aim_lo, aim_hi):
    """Pulses j in the runs lo[i]..hi[i] whose scan angle lies inside the FOV and inside the
    aimed window [aim_lo, aim_hi]: index, time, angle, sweep direction, edge-of-line flag
    (the next pulse starts a new scan line or leaves the FOV) and the pulse's rank among
    all pulses inside the FOV. Also returns that count. Same arithmetic as
    `_scan_reference.deflect`."""
    n_max = 0
    for i in range(lo.shape[0]):
        n_max += max(hi[i] - lo[i] + 1, 0)
    j_out = np.empty(n_max, np.int64)
    t_out = np.empty(n_max)
    th_out = np.empty(n_max)
    fw_out = np.empty(n_max, np.bool_)
    edge_out = np.empty(n_max, np.bool_)
    rank_out = np.empty(n_max, np.int64)
    n = 0
    n_fov = 0
    for i in range(lo.shape[0]):
        prev_kept = False  # was pulse j-1 kept (its edge flag waits for pulse j)?
        prev_line = 0.0
        for j in range(lo[i], hi[i] + 2):
            t = t_start + j / prr
            th, line, fw = _deflect(t, g0, rate, half_sweep, oscillating)
            inside = abs(th) <= half_fov
            if prev_kept:
                edge_out[n - 1] = line != prev_line or not inside
            prev_kept = False
            if j > hi[i] or not inside:
                continue
            n_fov += 1
            if th < aim_lo or th > aim_hi:
                continue
            j_out[n] = j
            t_out[n] = t
            th_out[n] = th
            fw_out[n] = fw
            rank_out[n] = n_fov - 1
            prev_kept = True
            prev_line = line
            n += 1
    return j_out[:n], t_out[:n], th_out[:n], fw_out[:n], edge_out[:n], rank_out[:n], n_fov


@njit(**_JIT)
def flag_discontinuities_rows(n_ext, segments, offsets, normals, tau):
    """Pulses whose footprint may straddle a depth discontinuity: for every pair (i, i+s) of
    n_ext consecutive pulses, s in `offsets`, flag both when exactly one of them hits, or
    when either hit point lies farther than `tau` from the plane of the other's hit face.

    `segments` is a tuple of (pos, origins, directions, t, face) for the pulses that were
    cast, pos being each row's index among all n_ext consecutive pulses; a pulse that was
    not cast counts as a miss (it cannot reach the scene's box). Returns one flag array
    per segment."""
    seg_of = np.full(n_ext, -1, np.int64)
    row_of = np.full(n_ext, -1, np.int64)
    flags = []
    for k in range(len(segments)):
        pos = segments[k][0]
        for r in range(pos.shape[0]):
            seg_of[pos[r]] = k
            row_of[pos[r]] = r
        flags.append(np.zeros(pos.shape[0], np.bool_))
    pi = np.empty(3)
    pj = np.empty(3)
    for q in range(n_ext):
        ki = seg_of[q]
        fi = -1
        if ki >= 0:
            fi = segments[ki][4][row_of[q]]
        for s in offsets:
            q2 = q + s
            if q2 >= n_ext:
                continue
            kj = seg_of[q2]
            fj = -1
            if kj >= 0:
                fj = segments[kj][4][row_of[q2]]
            if fi < 0 and fj < 0:
                continue
            edge = (fi < 0) != (fj < 0)
            if not edge:
                ri, rj = row_of[q], row_of[q2]
                si, sj = segments[ki], segments[kj]
                for a in range(3):
                    pi[a] = si[1][ri, a] + si[2][ri, a] * si[3][ri]
                    pj[a] = sj[1][rj, a] + sj[2][rj, a] * sj[3][rj]
                off_i = 0.0
                off_j = 0.0
                for a in range(3):
                    diff = pj[a] - pi[a]
                    off_i += normals[fi, a] * diff
                    off_j += normals[fj, a] * diff
                edge = abs(off_i) > tau or abs(off_j) > tau
            if edge:
                if ki >= 0:
                    flags[ki][row_of[q]] = True
                if kj >= 0:
                    flags[kj][row_of[q2]] = True
    return flags


@njit(**_JIT)
def sub_rays(directions, plane_normal, offsets):
    """Unit sub-ray directions (n*k, 3) for n central rays and k footprint offsets
    (tangent-plane coordinates along plane_normal and directions × plane_normal)."""
    n, k = directions.shape[0], offsets.shape[0]
    out = np.empty((n * k, 3))
    e2 = np.empty(3)
    for i in range(n):
        d0, d1, d2 = directions[i, 0], directions[i, 1], directions[i, 2]
        e2[0] = d1 * plane_normal[2] - d2 * plane_normal[1]
        e2[1] = d2 * plane_normal[0] - d0 * plane_normal[2]
        e2[2] = d0 * plane_normal[1] - d1 * plane_normal[0]
        for j in range(k):
            x = d0 + offsets[j, 0] * plane_normal[0] + offsets[j, 1] * e2[0]
            y = d1 + offsets[j, 0] * plane_normal[1] + offsets[j, 1] * e2[1]
            z = d2 + offsets[j, 0] * plane_normal[2] + offsets[j, 1] * e2[2]
            norm = math.sqrt(x * x + y * y + z * z)
            out[i * k + j, 0] = x / norm
            out[i * k + j, 1] = y / norm
            out[i * k + j, 2] = z / norm
    return out


@njit(**_JIT)
def form_returns(t, face, weights, separation, min_energy, max_returns):
    """Returns of n pulses from their k sub-rays' ranges t (n, k) and faces (n, k).

    Sub-rays sorted by range; a gap > `separation` starts a new return; a return's range
    is the weighted mean of its sub-rays, its face the strongest sub-ray's (first on ties),
    and it is detected when its weight share reaches `min_energy`; at most `max_returns`,
    nearest first. Output rows are pulse-major, return-minor:
    (pulse, face, range, return_number, number_of_returns)."""
    n, k = t.shape
    out_p = np.empty(n * max_returns, np.int64)
    out_f = np.empty(n * max_returns, np.int64)
    out_r = np.empty(n * max_returns)
    out_ret = np.empty(n * max_returns, np.uint8)
    out_nret = np.empty(n * max_returns, np.uint8)
    m = 0
    for i in range(n):
        order = np.argsort(t[i], kind="mergesort")  # stable, misses (inf) last
        first = m
        cnt = 0
        e_w = 0.0
        e_wt = 0.0
        best_w = -1.0
        best_f = -1
        prev = 0.0
        for jj in range(k + 1):
            j = order[jj] if jj < k else 0
            end = jj == k or not math.isfinite(t[i, j])
            if end or (jj > 0 and t[i, j] - prev > separation):
                # close the return collected so far
                if e_w > 0 and e_w >= min_energy and cnt < max_returns:
                    out_p[m] = i
                    out_f[m] = best_f
                    out_r[m] = e_wt / e_w
                    cnt += 1
                    out_ret[m] = cnt
                    m += 1
                e_w = 0.0
                e_wt = 0.0
                best_w = -1.0
                best_f = -1
                if end:
                    break
            w = weights[j]
            e_w += w
            e_wt += w * t[i, j]
            if w > best_w:
                best_w = w
                best_f = face[i, j]
            prev = t[i, j]
        for q in range(first, m):
            out_nret[q] = cnt
    return out_p[:m], out_f[:m], out_r[:m], out_ret[:m], out_nret[:m]


@njit(**_JIT)
def pulse_rays32(t, theta, t_start, start, velocity, down, right):
    """Float32 rays for Embree plus each ray's (cos θ, sin θ) in float64, so that the float64
    ray can be rebuilt later without another sin/cos and without storing it."""
    n = t.shape[0]
    o32 = np.empty((n, 3), np.float32)
    d32 = np.empty((n, 3), np.float32)
    cs = np.empty((n, 2))
    for i in range(n):
        dt = t[i] - t_start
        c = math.cos(theta[i])
        s = math.sin(theta[i])
        cs[i, 0] = c
        cs[i, 1] = s
        for k in range(3):
            o32[i, k] = start[k] + dt * velocity[k]
            d32[i, k] = c * down[k] + s * right[k]
    return o32, d32, cs


@njit(**_JIT)
def refine_and_pack(face, t, cs, t_start, start, velocity, down, right, normals, plane_d, max_range,
                    noise, noise_sigma, shift, scale, theta, forward, edge, line_id,
                    f_building, f_grade, f_surface, f_class, f_reflect, ref2, cols):
    """Single-ray beam in one pass: for every ray Embree saw hit a face, rebuild the float64
    ray, intersect it with the face's plane (dropping grazing or out-of-range hits, as
    `refine_hits`), add noise and write the LAS point. Returns (points written, ok, int mins,
    int maxs, points by return, points by face)."""
    mins = np.full(3, np.iinfo(np.int64).max, np.int64)
    maxs = np.full(3, np.iinfo(np.int64).min, np.int64)
    by_return = np.zeros(16, np.int64)
    by_face = np.zeros(f_class.shape[0], np.int64)
    xyz_int = np.empty(3, np.int64)
    o = np.empty(3)
    d = np.empty(3)
    m = 0
    for i in range(face.shape[0]):
        f = face[i]
        if f < 0:
            continue
        dt = t[i] - t_start
        num = plane_d[f]
        den = 0.0
        for k in range(3):
            o[k] = start[k] + dt * velocity[k]
            d[k] = cs[i, 0] * down[k] + cs[i, 1] * right[k]
            num -= normals[f, k] * o[k]
            den += normals[f, k] * d[k]
        if den == 0.0:
            continue
        ti = num / den
        if not (ti >= 0.0 and ti <= max_range):
            continue
        if not _to_ints(o, d, ti + noise_sigma * np.float64(noise[m]), shift, scale, xyz_int, mins, maxs):
            return m, False, mins, maxs, by_return, by_face
        _write_point(cols, m, xyz_int, t[i], theta[i], forward[i], edge[i], np.uint8(1), np.uint8(1), line_id,
                     f_building[f], f_grade[f], f_surface[f], f_class[f],
                     _intensity(f_reflect[f], normals, f, d, ti, ref2))
        by_return[1] += 1
        by_face[f] += 1
        m += 1
    return m, True, mins, maxs, by_return, by_face
