"""Compiled inner loop of `core.features` (numba, GIL released, parallel over grid cells).

Points and queries are sorted by a grid key (cell size = radius, key = (ix*ny + iy)*nz + iz),
so the 27 cells around a query cell form 9 contiguous key ranges, found once per cell by
binary search. Each neighbourhood is gathered into a buffer (pass 1: distance test), then
centred on its own mean (pass 2: covariance), so no large coordinate enters a product.
Same definitions as `core.features._reference_features` (tests compare the two).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_JIT = dict(nogil=True, cache=True, error_model="numpy")


@njit(inline="always", **_JIT)
def _jacobi3(A, V, w):
    """Eigen-decomposition of the symmetric 3×3 `A` (destroyed): w descending, V[:, k] vectors."""
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        diag = A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]
        if off == 0.0 or off <= 1e-40 * diag:
            break
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):
                akp = A[k, p]
                akq = A[k, q]
                A[k, p] = c * akp - s * akq
                A[k, q] = s * akp + c * akq
            for k in range(3):
                apk = A[p, k]
                aqk = A[q, k]
                A[p, k] = c * apk - s * aqk
                A[q, k] = s * apk + c * aqk
            for k in range(3):
                vkp = V[k, p]
                vkq = V[k, q]
                V[k, p] = c * vkp - s * vkq
                V[k, q] = s * vkp + c * vkq
    # sort descending (3 elements, swap columns along)
    for i in range(3):
        w[i] = A[i, i]
    for a in range(2):
        for b in range(2 - a):
            if w[b] < w[b + 1]:
                tmp = w[b]
                w[b] = w[b + 1]
                w[b + 1] = tmp
                for k in range(3):
                    tmp = V[k, b]
                    V[k, b] = V[k, b + 1]
                    V[k, b + 1] = tmp


@njit(inline="always", **_JIT)
def _solve6(M, b, x):
    """Gaussian elimination with partial pivoting; False if singular (relative pivot 1e-12)."""
    n = 6
    scale = 0.0
    for i in range(n):
        scale = max(scale, abs(M[i, i]))
    if scale == 0.0:
        return False
    for col in range(n):
        piv = col
        for r in range(col + 1, n):
            if abs(M[r, col]) > abs(M[piv, col]):
                piv = r
        if abs(M[piv, col]) <= 1e-12 * scale:
            return False
        if piv != col:
            for k in range(n):
                tmp = M[col, k]
                M[col, k] = M[piv, k]
                M[piv, k] = tmp
            tmp = b[col]
            b[col] = b[piv]
            b[piv] = tmp
        for r in range(col + 1, n):
            f = M[r, col] / M[col, col]
            for k in range(col, n):
                M[r, k] -= f * M[col, k]
            b[r] -= f * b[col]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= M[i, k] * x[k]
        x[i] = s / M[i, i]
    return True


@njit(**_JIT)
def _cov_from_buffer(buf, n, px, py, pz, qx, qy, qz, self_j, C):
    """Mean (relative to the query) and scatter (centred on the mean) excluding self_j.

    Returns (mx, my, mz); C holds the scatter of the neighbours other than self_j,
    centred on the mean of all n."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for t in range(n):
        j = buf[t]
        sx += px[j] - qx
        sy += py[j] - qy
        sz += pz[j] - qz
    mx = sx / n
    my = sy / n
    mz = sz / n
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for t in range(n):
        j = buf[t]
        if j == self_j:
            continue
        dx = px[j] - qx - mx
        dy = py[j] - qy - my
        dz = pz[j] - qz - mz
        c00 += dx * dx
        c01 += dx * dy
        c02 += dx * dz
        c11 += dy * dy
        c12 += dy * dz
        c22 += dz * dz
    C[0, 0] = c00
    C[0, 1] = c01
    C[0, 2] = c02
    C[1, 1] = c11
    C[1, 2] = c12
    C[2, 2] = c22
    C[1, 0] = c01
    C[2, 0] = c02
    C[2, 1] = c12
    return mx, my, mz


@njit(parallel=True, **_JIT)
def neighbourhoods(px, py, pz, pkeys, qx, qy, qz, qself, cell_start, cell_key, ny, nz, radius,
                   min_points, do_eig, do_rough, do_z, do_curv,
                   count, lam, normal, rough, zrank, zrange, curv):
    """Per query: neighbour count and, as asked, eigenvalues/normal, roughness, z rank/range, curvature.

    px.. sorted cloud (local frame), pkeys its sorted grid keys; qx.. queries sorted by key,
    grouped in cells: queries cell_start[c]:cell_start[c+1] share the key cell_key[c].
    qself[i] = index of the query in the sorted cloud, or -1. Outputs are pre-filled with NaN
    by the caller and written only where defined (see `core.features` for the rule)."""
    r2 = radius * radius
    ncell = cell_key.shape[0]
    tiny_extent = (1e-9 * radius) ** 2
    for c in prange(ncell):
        key = cell_key[c]
        iz = key % nz
        ixy = key // nz
        iy = ixy % ny
        ix = ixy // ny
        lo = np.empty(9, np.int64)
        hi = np.empty(9, np.int64)
        total = 0
        k = 0
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                kx = ix + dx
                ky = iy + dy
                if kx < 0 or ky < 0 or ky >= ny:
                    lo[k] = 0
                    hi[k] = 0
                else:
                    base = (kx * ny + ky) * nz
                    lo[k] = np.searchsorted(pkeys, base + max(iz - 1, 0))
                    hi[k] = np.searchsorted(pkeys, base + min(iz + 1, nz - 1), side="right")
                total += hi[k] - lo[k]
                k += 1
        buf = np.empty(max(total, 1), np.int64)
        A = np.empty((3, 3))
        C = np.empty((3, 3))
        V = np.empty((3, 3))
        w = np.empty(3)
        M = np.empty((6, 6))
        bb = np.empty(6)
        xx = np.empty(6)
        for i in range(cell_start[c], cell_start[c + 1]):
            x = qx[i]
            y = qy[i]
            z = qz[i]
            n = 0
            for k in range(9):
                for j in range(lo[k], hi[k]):
                    ddx = px[j] - x
                    ddy = py[j] - y
                    ddz = pz[j] - z
                    if ddx * ddx + ddy * ddy + ddz * ddz <= r2:
                        buf[n] = j
                        n += 1
            count[i] = n
            if n < min_points:
                continue
            if do_z:
                zmin = np.inf
                zmax = -np.inf
                below = 0
                for t in range(n):
                    zj = pz[buf[t]]
                    zmin = min(zmin, zj)
                    zmax = max(zmax, zj)
                    if zj < z:
                        below += 1
                zrange[i] = zmax - zmin
                zrank[i] = below / (n - 1.0) if qself[i] >= 0 else below / float(n)
            if not (do_eig or do_rough or do_curv):
                continue
            sj = qself[i]
            mx, my, mz = _cov_from_buffer(buf, n, px, py, pz, x, y, z, sj, C)
            # scatter of all n = scatter without self + d d^T (d = self - mean)
            for a in range(3):
                for b in range(3):
                    A[a, b] = C[a, b]
            if sj >= 0:
                d0 = -mx
                d1 = -my
                d2 = -mz
                A[0, 0] += d0 * d0
                A[0, 1] += d0 * d1
                A[0, 2] += d0 * d2
                A[1, 1] += d1 * d1
                A[1, 2] += d1 * d2
                A[2, 2] += d2 * d2
                A[1, 0] = A[0, 1]
                A[2, 0] = A[0, 2]
                A[2, 1] = A[1, 2]
            for a in range(3):
                for b in range(3):
                    A[a, b] /= n
            _jacobi3(A, V, w)
            l1 = max(w[0], 0.0)
            l2 = max(w[1], 0.0)
            l3 = max(w[2], 0.0)
            if l1 <= tiny_extent:
                continue  # all duplicates: nothing defined beyond counts and z
            lam[i, 0] = l1
            lam[i, 1] = l2
            lam[i, 2] = l3
            planar_ok = l2 > 1e-10 * l1
            if not planar_ok:
                continue  # collinear: no plane, no normal
            n0 = V[0, 2]
            n1 = V[1, 2]
            n2 = V[2, 2]
            if n2 < 0.0 or (n2 == 0.0 and (n1 < 0.0 or (n1 == 0.0 and n0 < 0.0))):
                n0 = -n0
                n1 = -n1
                n2 = -n2
            normal[i, 0] = n0
            normal[i, 1] = n1
            normal[i, 2] = n2
            if do_rough:
                if sj >= 0:
                    # plane of the other n-1 points: mean m' = n m/(n-1), scatter C - m m^T/(n-1)
                    f = 1.0 / (n - 1.0)
                    ms = n * f
                    A[0, 0] = C[0, 0] - mx * mx * f
                    A[0, 1] = C[0, 1] - mx * my * f
                    A[0, 2] = C[0, 2] - mx * mz * f
                    A[1, 1] = C[1, 1] - my * my * f
                    A[1, 2] = C[1, 2] - my * mz * f
                    A[2, 2] = C[2, 2] - mz * mz * f
                    A[1, 0] = A[0, 1]
                    A[2, 0] = A[0, 2]
                    A[2, 1] = A[1, 2]
                    _jacobi3(A, M[:3, :3], w)
                    if max(w[1], 0.0) > 1e-10 * max(w[0], 0.0) and w[0] > tiny_extent * (n - 1):
                        rough[i] = abs(M[0, 2] * mx * ms + M[1, 2] * my * ms + M[2, 2] * mz * ms)
                else:
                    rough[i] = abs(n0 * mx + n1 * my + n2 * mz)
            if do_curv and n >= 6:
                for a in range(6):
                    bb[a] = 0.0
                    for b in range(6):
                        M[a, b] = 0.0
                inv = 1.0 / radius
                for t in range(n):
                    j = buf[t]
                    ex = px[j] - x - mx
                    ey = py[j] - y - my
                    ez = pz[j] - z - mz
                    u = (V[0, 0] * ex + V[1, 0] * ey + V[2, 0] * ez) * inv
                    v = (V[0, 1] * ex + V[1, 1] * ey + V[2, 1] * ez) * inv
                    h = (V[0, 2] * ex + V[1, 2] * ey + V[2, 2] * ez) * inv
                    xx[0] = 1.0
                    xx[1] = u
                    xx[2] = v
                    xx[3] = u * u
                    xx[4] = u * v
                    xx[5] = v * v
                    for a in range(6):
                        bb[a] += xx[a] * h
                        for b in range(a, 6):
                            M[a, b] += xx[a] * xx[b]
                for a in range(6):
                    for b in range(a):
                        M[a, b] = M[b, a]
                if _solve6(M, bb, xx):
                    uq = -(V[0, 0] * mx + V[1, 0] * my + V[2, 0] * mz) * inv
                    vq = -(V[0, 1] * mx + V[1, 1] * my + V[2, 1] * mz) * inv
                    fx = xx[1] + 2.0 * xx[3] * uq + xx[4] * vq
                    fy = xx[2] + xx[4] * uq + 2.0 * xx[5] * vq
                    fxx = 2.0 * xx[3]
                    fxy = xx[4]
                    fyy = 2.0 * xx[5]
                    g = 1.0 + fx * fx + fy * fy
                    H = ((1.0 + fy * fy) * fxx - 2.0 * fx * fy * fxy + (1.0 + fx * fx) * fyy) / (2.0 * g ** 1.5)
                    curv[i] = abs(H) * inv
