"""Plain numpy reference of `quakescan.change._m3c2_kernels`, for the tests that compare the two;
nothing in production calls it.

The kernel visits only the grid columns and z runs a cylinder can reach, in the order of
the column-sorted points; here every point is tested, in the same order, so the points
kept, the reservoir sample drawn from them and the sums over them are the kernel's.
"""
from __future__ import annotations

import numpy as np

_LCG_MUL = 6364136223846793005
_LCG_ADD = 1442695040888963407
_MASK64 = (1 << 64) - 1


def _median_sorted(a):
    n = len(a)
    return a[n // 2] if n % 2 == 1 else 0.5 * (a[n // 2 - 1] + a[n // 2])


def cylinder_robust(cx, cy, cz, nx_, ny_, nz_, radius, half_length, behind_length, near_length, px, py, pz,
                    sample, count, median, spread, behind, near, mean, var):
    """`_m3c2_kernels.cylinder_robust` without the grid: the same outputs (see there) from
    the points px, py, pz in the grid's order (`ColumnGrid.px` ...)."""
    cap = sample.shape[1]
    for k in range(len(cx)):
        dx, dy, dz = px - cx[k], py - cy[k], pz - cz[k]
        along = dx * nx_[k] + dy * ny_[k] + dz * nz_[k]
        perp2 = dx * dx + dy * dy + dz * dz - along * along
        h = half_length[k]
        hb = max(behind_length[k], h)
        inside = (-hb <= along) & (along <= h) & (perp2 <= radius[k] * radius[k])
        vals = along[inside & (along >= -h)]
        n = len(vals)
        count[k] = n
        behind[k] = int(np.count_nonzero(inside & (along < -h)))
        near[k] = int(np.count_nonzero(np.abs(vals) <= near_length[k]))
        if n == 0:
            median[k] = spread[k] = mean[k] = var[k] = np.nan
            continue
        # the kernel's running sums: np.cumsum adds in order, as its loop does
        mu = np.cumsum(vals)[-1] / n
        mean[k] = mu
        var[k] = max(np.cumsum(vals * vals)[-1] / n - mu * mu, 0.0)
        # reservoir sampling with the kernel's generator, seeded by the cylinder's index
        kept = vals[:cap].copy()
        state = (k * _LCG_MUL + _LCG_ADD) & _MASK64
        for i in range(cap, n):
            state = (state * _LCG_MUL + _LCG_ADD) & _MASK64
            slot = (state >> 33) % (i + 1)
            if slot < cap:
                kept[slot] = vals[i]
        kept = np.sort(kept)
        med = _median_sorted(kept)
        median[k] = med
        spread[k] = 1.4826 * _median_sorted(np.sort(np.abs(kept - med)))
