"""Compiled cylinder statistics for `quakescan.change.m3c2` (numba).

The points are bucketed in square x/y columns (the counting sort of `quakescan.change._nn_kernels`),
each column sorted by z. A cylinder (centre c, unit axis n, radius r, half length L) visits
only the columns that its x/y bounding box touches and, in each, only the z run that its
height range can reach (binary search), so a roof cylinder reads little more than its
own points and a wall cylinder a thin slab. `quakescan.change._m3c2_reference` is the numpy version
(tests compare the two).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._feature_kernels import _lower_bound

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(**_JIT)
def _median_sorted(a, n):
    if n % 2 == 1:
        return a[n // 2]
    return 0.5 * (a[n // 2 - 1] + a[n // 2])


@njit(**_JIT)
def _reach(c, a, behind, ahead, r):
    """Range of one coordinate over the cylinder from `behind` before its centre c to `ahead`
    after it along the axis (component a), grown by the radius across the axis. One-sided:
    a post-event cylinder looks 30 m behind the surface and 2 m ahead, and a box symmetric
    about the centre read twice the columns it needs."""
    grow = r * math.sqrt(max(0.0, 1.0 - a * a))
    back, front = -behind * a, ahead * a
    return c + min(back, front) - grow, c + max(back, front) + grow


@njit(parallel=True, **_JIT)
def cylinder_robust(cx, cy, cz, nx_, ny_, nz_, radius, half_length, behind_length, near_length, px, py, pz, starts,
                    lo_x, lo_y, cell, ncx, ncy, sample, count, median, spread, behind, near, mean, var):
    """Per cylinder: number of points with |distance along the axis| <= half_length, the median
    of their distances and their robust spread (1.4826 x median absolute deviation), from a
    uniform sample of at most `sample.shape[1]` of them (reservoir sampling with a generator
    seeded by the cylinder's index: deterministic whatever the threads); and the number of
    points behind the surface, at distances in [-behind_length, -half_length), and the number
    within near_length of the core (|distance| <= near_length: on the core's own surface);
    and the mean and population variance of all the distances (not only the sample's)."""
    m = cx.shape[0]
    cap = sample.shape[1]
    for k in prange(m):
        x, y, z = cx[k], cy[k], cz[k]
        ax, ay, az = nx_[k], ny_[k], nz_[k]
        r = radius[k]
        h = half_length[k]
        hb = max(behind_length[k], h)
        r2 = r * r
        x0, x1 = _reach(x, ax, hb, h, r)
        y0, y1 = _reach(y, ay, hb, h, r)
        z0, z1 = _reach(z, az, hb, h, r)
        i0 = max(int(math.floor((x0 - lo_x) / cell)), 0)
        i1 = min(int(math.floor((x1 - lo_x) / cell)), ncx - 1)
        j0 = max(int(math.floor((y0 - lo_y) / cell)), 0)
        j1 = min(int(math.floor((y1 - lo_y) / cell)), ncy - 1)
        n = 0
        nb = 0
        nn = 0
        acc = 0.0
        acc2 = 0.0
        hn = near_length[k]
        state = np.uint64(k) * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                c = i * ncy + j
                a = starts[c]
                b = starts[c + 1]
                if a == b:
                    continue
                t = _lower_bound(pz, a, b, z0)
                while t < b and pz[t] <= z1:
                    dx = px[t] - x
                    dy = py[t] - y
                    dz = pz[t] - z
                    along = dx * ax + dy * ay + dz * az
                    if -hb <= along <= h:
                        perp2 = dx * dx + dy * dy + dz * dz - along * along
                        if perp2 <= r2:
                            if along >= -h:
                                if abs(along) <= hn:
                                    nn += 1
                                acc += along
                                acc2 += along * along
                                if n < cap:
                                    sample[k, n] = along
                                else:
                                    state = state * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
                                    slot = (state >> np.uint64(33)) % np.uint64(n + 1)
                                    if slot < cap:
                                        sample[k, slot] = along
                                n += 1
                            else:
                                nb += 1
                    t += 1
        count[k] = n
        behind[k] = nb
        near[k] = nn
        if n > 0:
            mu = acc / n
            mean[k] = mu
            var[k] = max(acc2 / n - mu * mu, 0.0)
            s = min(n, cap)
            vals = np.sort(sample[k, :s])
            med = _median_sorted(vals, s)
            dev = np.sort(np.abs(vals - med))
            median[k] = med
            spread[k] = 1.4826 * _median_sorted(dev, s)
        else:
            median[k] = np.nan
            spread[k] = np.nan
            mean[k] = np.nan
            var[k] = np.nan
