"""Plain numpy references of `quakescan.acquisition._scan_kernels`, one per compiled function of
the general path, with the kernel's name and signature. The scanner runs them only with
`fast=False` (`quakescan.acquisition.scan.scan`), the numpy path that the tests compare with
the compiled one byte for byte; tests/test_scan_kernels.py also compares each pair directly.

The fused single-ray loops (`pulse_rays32`, `refine_and_pack`, `pack_points`) have no
reference of their own: the numpy path forms the same points from the functions below and
packs them with `quakescan.formats.pointcloud.pack_points`, which is what the whole-scan
comparison checks.
"""
from __future__ import annotations

import numpy as np


def loops(fast: bool):
    """The module whose functions the scanner calls: the compiled loops, or (fast=False) these
    references, which have the same names and signatures."""
    if fast:
        from . import _scan_kernels

        return _scan_kernels
    import sys

    return sys.modules[__name__]


def pulse_rays(t, theta, t_start, start, velocity, down, right):
    """`_scan_kernels.pulse_rays`: origins and unit directions of pulses at times `t` and scan
    angles `theta`, in float64 and float32."""
    dt = t - t_start
    c, s = np.cos(theta), np.sin(theta)
    o = np.empty((len(dt), 3))
    d = np.empty((len(dt), 3))
    for k in range(3):
        o[:, k] = start[k] + dt * velocity[k]
        d[:, k] = c * down[k] + s * right[k]
    return o, d, o.astype(np.float32), d.astype(np.float32)


def refine_hits(origins, directions, face, normals, plane_d, max_range):
    """`_scan_kernels.refine_hits`: distance to the hit face's plane in float64 (inf: no hit);
    sets face = -1 in place where the ray is parallel to that plane or the hit lies outside
    [0, max_range]."""
    t = np.full(len(face), np.inf)
    hit = face >= 0
    if hit.any():
        fh = face[hit]
        nrm = normals[fh]
        num = plane_d[fh] - np.einsum("ij,ij->i", nrm, origins[hit])
        den = np.einsum("ij,ij->i", nrm, directions[hit])
        with np.errstate(divide="ignore", invalid="ignore"):
            th = num / den
        # A ray that Embree reports on a face but that is exactly parallel to its plane in
        # float64 (grazing) has no defined hit point: drop it instead of inventing one.
        bad = ~np.isfinite(th) | (th < 0) | (th > max_range)
        if bad.any():
            face[np.flatnonzero(hit)[bad]] = -1
            th[bad] = np.inf
        t[hit] = th
    return t


def deflect(t, g0, rate, half_sweep, oscillating):
    """`_scan_kernels._deflect` over an array of GPS times: scan angle, scan-line number and
    sweep direction of a rotating polygon (oscillating=False) or an oscillating mirror."""
    phase = (t - g0) * rate
    line = np.floor(phase)
    frac = phase - line
    if not oscillating:
        return -half_sweep + 2 * half_sweep * frac, line, np.ones(len(t), bool)
    forward = (line.astype(np.int64) % 2) == 0
    return np.where(forward, -half_sweep + 2 * half_sweep * frac, half_sweep - 2 * half_sweep * frac), line, forward


def fov_pulses(lo, hi, t_start, prr, rate, g0, half_sweep, half_fov, oscillating, aim_lo, aim_hi):
    """`_scan_kernels.fov_pulses`: the pulses of the runs lo[i]..hi[i] inside the FOV and the
    aimed window — index, time, angle, sweep direction, edge-of-line flag, rank among the
    pulses inside the FOV — and the count of pulses inside the FOV."""
    counts = np.maximum(hi - lo + 1, 0)
    j = np.repeat(lo, counts) + np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    t = t_start + j / prr
    theta, scan_line, forward = deflect(t, g0, rate, half_sweep, oscillating)
    inside = np.abs(theta) <= half_fov
    next_theta, next_line, _ = deflect(t + 1.0 / prr, g0, rate, half_sweep, oscillating)
    edge = (next_line != scan_line) | (np.abs(next_theta) > half_fov)
    rank = np.cumsum(inside) - 1
    keep = inside & (theta >= aim_lo) & (theta <= aim_hi)
    return j[keep], t[keep], theta[keep], forward[keep], edge[keep], rank[keep], int(inside.sum())


def flag_discontinuities_rows(n_ext, segments, offsets, normals, tau):
    """`_scan_kernels.flag_discontinuities_rows`: per segment (pos, origins, directions, t, face),
    the pulses whose footprint may straddle a depth discontinuity: for every pair (i, i+s) of
    the n_ext consecutive pulses, s in `offsets`, both are flagged when exactly one of them
    hits, or when either hit point lies farther than `tau` from the plane of the other's hit
    face. A pulse in no segment counts as a miss."""
    face = np.full(n_ext, -1, np.int64)
    p = np.zeros((n_ext, 3))
    for pos, o, d, t, f in segments:
        face[pos] = f
        p[pos] = o + d * t[:, None]
    hit = face >= 0
    nrm = normals[np.where(hit, face, 0)]
    flag = np.zeros(n_ext, bool)
    for step in offsets:
        a = np.arange(n_ext - step)
        b = a + step
        diff = p[b] - p[a]
        off_a = np.abs(np.einsum("ij,ij->i", nrm[a], diff))
        off_b = np.abs(np.einsum("ij,ij->i", nrm[b], diff))
        both = hit[a] & hit[b]
        edge = (hit[a] != hit[b]) | (both & ((off_a > tau) | (off_b > tau)))
        flag[a] |= edge
        flag[b] |= edge
    return [flag[pos] for pos, *_ in segments]


def sub_rays(directions, plane_normal, offsets):
    """`_scan_kernels.sub_rays`: unit sub-ray directions (n*k, 3) for n central rays and k
    footprint offsets (along plane_normal and directions × plane_normal)."""
    e1 = np.broadcast_to(plane_normal, directions.shape)
    e2 = np.cross(directions, e1)
    sub = (directions[:, None, :] + offsets[None, :, 0, None] * e1[:, None, :]
           + offsets[None, :, 1, None] * e2[:, None, :])
    sub /= np.sqrt((sub * sub).sum(axis=2, keepdims=True))
    return sub.reshape(-1, 3)


def form_returns(t, face, weights, separation, min_energy, max_returns):
    """`_scan_kernels.form_returns`: the returns of n pulses from their k sub-rays' ranges t
    (n, k) and faces (n, k): sub-rays closer than `separation` along the range form one echo,
    an echo with at least `min_energy` of the weights is a return (at most `max_returns` per
    pulse, nearest first), at the weighted mean range, on the face of its heaviest sub-ray.
    Returns (pulse, face, range, return_number, number_of_returns), pulse-major."""
    n = len(t)
    order = np.argsort(t, axis=1, kind="stable")
    t = np.take_along_axis(t, order, 1)
    face = np.take_along_axis(face, order, 1)
    w = weights[order]
    finite = np.isfinite(t)
    with np.errstate(invalid="ignore"):
        gap = np.diff(t, axis=1) > separation
    echo = np.concatenate([np.zeros((n, 1), np.int64), np.cumsum(gap, axis=1)], axis=1)
    rows_i, rows_ret, rows_face, rows_rng = [], [], [], []
    det_count = np.zeros(n, np.int64)
    kmax = int(echo[finite].max()) + 1 if finite.any() else 0
    for e in range(kmax):
        m = finite & (echo == e)
        energy = np.zeros(n)
        weighted = np.zeros(n)
        for j in range(m.shape[1]):  # sequential sums, in the kernel's order
            energy += np.where(m[:, j], w[:, j], 0.0)
            weighted += np.where(m[:, j], w[:, j] * np.where(m[:, j], t[:, j], 0.0), 0.0)
        ok = (energy >= min_energy) & (energy > 0) & (det_count < max_returns)
        if not ok.any():
            continue
        okr = np.flatnonzero(ok)
        rows_i.append(okr)
        rows_ret.append(det_count[okr] + 1)
        rows_face.append(face[okr, np.argmax(np.where(m, w, -1.0), axis=1)[ok]])
        rows_rng.append(weighted[ok] / energy[ok])
        det_count[okr] += 1
    if not rows_i:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.uint8),
                np.zeros(0, np.uint8))
    pi = np.concatenate(rows_i)
    ret = np.concatenate(rows_ret)
    order = np.lexsort((ret, pi))  # pulse-major, return-minor: scan order
    pi, ret = pi[order], ret[order]
    return (pi, np.concatenate(rows_face)[order], np.concatenate(rows_rng)[order],
            ret.astype(np.uint8), det_count[pi].astype(np.uint8))
