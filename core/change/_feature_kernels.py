"""Compiled inner loop of `quakescan.change.features` (numba, GIL released, parallel over query groups).

Grid: vertical columns of side s = r / CELLS_PER_RADIUS (default 3), column key ix*ny + iy;
points sorted by one int64 key (column << zbits | floor(z / (s/64))), so a column is one
contiguous run ordered by z (to 1/64 of a cell). Queries are grouped by column and z slab of
height s. Per group: the columns whose box comes within r of the group's column (one binary
search per x row of columns), each cut by binary search on the key to the z run
[zmin - r, zmax + r] of the group, and copied into one contiguous buffer, row by row. Per
query and row, the columns whose x/y box comes within r form one run of that buffer. On the
2.8 M-point ULS city at r = 1.5 m this tests 1.45x the sphere's points (columns of side r:
2.5x; the former 27 cells of side r: ~3x).

One pass per query, fused with the distance test and branch-free (0/1 mask) so that LLVM
vectorises it: relative to the query point, d = p - q (|d| <= r), accumulate n, sum d,
sum d d^T (6 terms), z min/max and #below. Covariance C = S/n - m m^T, m = sum d / n.

Accuracy of the one pass: every entry of S/n and m m^T is at most r^2 and is a sum of n
terms, so |C_fast - C| <= ~(n + 3) eps r^2 per entry and (Weyl) every eigenvalue moves by
at most ~3 (n + 3) eps r^2 (eps = 2.2e-16: 4e-13 r^2 for n = 600, typically sqrt(n)
times less). That is exact to the tests' tolerance everywhere except where a decision or
an exact zero hangs on a small eigenvalue, so those neighbourhoods are redone with the
two-pass code (gather, centre on the own mean, then scatter), which gives the reference's
answers: l1 <= 1e-4 r^2 (compact: the l1 "no extent" test), l2 <= 1e-6 l1 (near
collinear: the "no plane" test), l3 <= 1e-6 l1 (near-exact planes: sphericity 0,
eigenentropy finite), and for roughness the same l1/l2 tests on the neighbours without
the point. Beyond those thresholds the bound is > 1e4 times smaller than the quantity.
The distance test itself (`_mask`, `_count_xy`) runs in the strict kernel, the same
expression as `_reference`, so neighbour sets are identical; only the sums, in fast-math
helpers that read its 0/1 mask, are reassociated and fused.

Roughness: the point contributes d = 0 to every sum, so the moments of the other n - 1
neighbours are the same sums with n - 1. Curvature (quadric in the PCA frame) needs a
second masked pass over the candidates, run only when curvature is asked for. The
cylinder count (point_density, echo_ratio) runs over whole columns with a 2-D test, in
the same kernel, only when asked for.
Same definitions as `quakescan.change._feature_reference`, the numpy reference of every function here
(tests compare the two).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}
# sums may be reassociated (vectorised) and fused (FMA); no NaN/inf assumptions. Numba compiles
# a callee with its caller's flags: the distance test must only be called from strict code
_FAST = {**_JIT, "fastmath": {"reassoc", "nsz", "contract"}}
_IMAX = np.int64(0x7FFFFFFFFFFFFFFF)


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


@njit(**_JIT)
def _rot(app, aqq, apq, arp, arq):
    """One Jacobi rotation zeroing a_pq of a symmetric 3x3 (r the third index): new a_pp,
    a_qq, a_rp, a_rq and (c, s)."""
    theta = (aqq - app) / (2.0 * apq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    return app - t * apq, aqq + t * apq, c * arp - s * arq, s * arp + c * arq, c, s


@njit(**_JIT)
def _eig3(a00, a01, a02, a11, a12, a22, V, w):
    """`_jacobi3` on scalars (kept in registers: ~4x faster): w descending, V[:, k] vectors."""
    v00 = v11 = v22 = 1.0
    v01 = v02 = v10 = v12 = v20 = v21 = 0.0
    for _sweep in range(30):
        off = a01 * a01 + a02 * a02 + a12 * a12
        diag = a00 * a00 + a11 * a11 + a22 * a22
        if off == 0.0 or off <= 1e-40 * diag:
            break
        if a01 != 0.0:  # p, q, r = 0, 1, 2
            a00, a11, a02, a12, c, s = _rot(a00, a11, a01, a02, a12)
            a01 = 0.0
            v00, v01 = c * v00 - s * v01, s * v00 + c * v01
            v10, v11 = c * v10 - s * v11, s * v10 + c * v11
            v20, v21 = c * v20 - s * v21, s * v20 + c * v21
        if a02 != 0.0:  # p, q, r = 0, 2, 1
            a00, a22, a01, a12, c, s = _rot(a00, a22, a02, a01, a12)
            a02 = 0.0
            v00, v02 = c * v00 - s * v02, s * v00 + c * v02
            v10, v12 = c * v10 - s * v12, s * v10 + c * v12
            v20, v22 = c * v20 - s * v22, s * v20 + c * v22
        if a12 != 0.0:  # p, q, r = 1, 2, 0
            a11, a22, a01, a02, c, s = _rot(a11, a22, a12, a01, a02)
            a12 = 0.0
            v01, v02 = c * v01 - s * v02, s * v01 + c * v02
            v11, v12 = c * v11 - s * v12, s * v11 + c * v12
            v21, v22 = c * v21 - s * v22, s * v21 + c * v22
    # sort descending, columns along
    if a00 < a11:
        a00, a11 = a11, a00
        v00, v01 = v01, v00
        v10, v11 = v11, v10
        v20, v21 = v21, v20
    if a11 < a22:
        a11, a22 = a22, a11
        v01, v02 = v02, v01
        v11, v12 = v12, v11
        v21, v22 = v22, v21
    if a00 < a11:
        a00, a11 = a11, a00
        v00, v01 = v01, v00
        v10, v11 = v11, v10
        v20, v21 = v21, v20
    w[0] = a00
    w[1] = a11
    w[2] = a22
    V[0, 0] = v00
    V[0, 1] = v01
    V[0, 2] = v02
    V[1, 0] = v10
    V[1, 1] = v11
    V[1, 2] = v12
    V[2, 0] = v20
    V[2, 1] = v21
    V[2, 2] = v22


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


@njit(**_JIT)
def _d2(dx, dy, dz):
    """Squared distance, the reference's expression (call it from strict code only)."""
    return dx * dx + dy * dy + dz * dz


@njit(**_JIT)
def _d2xy(dx, dy):
    return dx * dx + dy * dy


@njit(**_JIT)
def _lower_bound(a, lo, hi, v):
    """First j in [lo, hi) with a[j] >= v (a sorted there), else hi."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT)
def _upper_bound(a, lo, hi, v):
    """First j in [lo, hi) with a[j] > v, else hi."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] <= v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT)
def _mask(px, py, pz, mask, lo, hi, x, y, z, r2):
    """mask[lo:hi] = 1.0 where the point is within r of (x, y, z), else 0.0; their number.
    Strict IEEE: numba compiles a callee with its caller's fast-math flags, so the distance
    test lives here, called from the strict kernel, and the fast-math sums read the mask."""
    bx = px[lo:hi]
    by = py[lo:hi]
    bz = pz[lo:hi]
    bm = mask[lo:hi]
    k = 0
    for t in range(bx.shape[0]):
        inside = _d2(bx[t] - x, by[t] - y, bz[t] - z) <= r2
        bm[t] = 1.0 if inside else 0.0
        k += 1 if inside else 0
    return k


@njit(**_JIT)
def _count_xy(px, py, lo, hi, x, y, r2):
    bx = px[lo:hi]
    by = py[lo:hi]
    k = 0
    for t in range(bx.shape[0]):
        k += 1 if _d2xy(bx[t] - x, by[t] - y) <= r2 else 0
    return k


@njit(**_FAST)
def _scan_z(pz, pzi, mask, lo, hi, z, zmin, zmax, below):
    """zmin/zmax are taken over pzi, the int64 bits of z (z >= 0: same order as the floats),
    because integer min/max reductions vectorise and float ones do not."""
    bz = pz[lo:hi]
    bi = pzi[lo:hi]
    bm = mask[lo:hi]
    for t in range(bz.shape[0]):
        m = bm[t]
        below += m if bz[t] < z else 0.0  # no `and`: its branch stops the vectoriser
        zi = bi[t]
        inside = m != 0.0
        zmin = min(zmin, zi if inside else _IMAX)
        zmax = max(zmax, zi if inside else -1)
    return zmin, zmax, below


@njit(**_FAST)
def _scan_mom(px, py, pz, mask, lo, hi, x, y, z, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz):
    bx = px[lo:hi]
    by = py[lo:hi]
    bz = pz[lo:hi]
    bm = mask[lo:hi]
    for t in range(bx.shape[0]):
        dx = bx[t] - x
        dy = by[t] - y
        dz = bz[t] - z
        m = bm[t]
        ax = m * dx
        ay = m * dy
        az = m * dz
        sx += ax
        sy += ay
        sz += az
        sxx += ax * dx
        sxy += ax * dy
        sxz += ax * dz
        syy += ay * dy
        syz += ay * dz
        szz += az * dz
    return sx, sy, sz, sxx, sxy, sxz, syy, syz, szz


@njit(**_FAST)
def _scan_quad(px, py, pz, mask, lo, hi, x, y, z, ox, oy, oz, V, inv, acc):
    """Quadric moments in the PCA frame: (u, v, h) = V^T (d - mean) / r, masked (0/1) by the
    distance test. acc: 20 sums u, v, uu, uv, vv, uuu, uuv, uvv, vvv, u4, u3v, u2v2, uv3, v4,
    h, uh, vh, uuh, uvh, vvh."""
    e00 = V[0, 0] * inv
    e10 = V[1, 0] * inv
    e20 = V[2, 0] * inv
    e01 = V[0, 1] * inv
    e11 = V[1, 1] * inv
    e21 = V[2, 1] * inv
    e02 = V[0, 2] * inv
    e12 = V[1, 2] * inv
    e22 = V[2, 2] * inv
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
    s10 = s11 = s12 = s13 = s14 = s15 = s16 = s17 = s18 = s19 = 0.0
    bx = px[lo:hi]
    by = py[lo:hi]
    bz = pz[lo:hi]
    bm = mask[lo:hi]
    for t in range(bx.shape[0]):
        dx = bx[t] - x
        dy = by[t] - y
        dz = bz[t] - z
        m = bm[t]
        ex = dx - ox
        ey = dy - oy
        ez = dz - oz
        u = e00 * ex + e10 * ey + e20 * ez
        v = e01 * ex + e11 * ey + e21 * ez
        h = (e02 * ex + e12 * ey + e22 * ez) * m
        mu = m * u
        mv = m * v
        uu = u * u
        uv = u * v
        vv = v * v
        s0 += mu
        s1 += mv
        s2 += mu * u
        s3 += mu * v
        s4 += mv * v
        s5 += mu * uu
        s6 += mu * uv
        s7 += mu * vv
        s8 += mv * vv
        s9 += mu * u * uu
        s10 += mu * u * uv
        s11 += mu * u * vv
        s12 += mu * v * vv
        s13 += mv * v * vv
        s14 += h
        s15 += h * u
        s16 += h * v
        s17 += h * uu
        s18 += h * uv
        s19 += h * vv
    acc[0] += s0
    acc[1] += s1
    acc[2] += s2
    acc[3] += s3
    acc[4] += s4
    acc[5] += s5
    acc[6] += s6
    acc[7] += s7
    acc[8] += s8
    acc[9] += s9
    acc[10] += s10
    acc[11] += s11
    acc[12] += s12
    acc[13] += s13
    acc[14] += s14
    acc[15] += s15
    acc[16] += s16
    acc[17] += s17
    acc[18] += s18
    acc[19] += s19


@njit(**_JIT)
def _curvature(M, bb, xx, V, mx, my, mz, inv):
    """|H| at the query point from the solved quadric; NaN if the normal equations are singular."""
    if not _solve6(M, bb, xx):
        return np.nan
    uq = -(V[0, 0] * mx + V[1, 0] * my + V[2, 0] * mz) * inv
    vq = -(V[0, 1] * mx + V[1, 1] * my + V[2, 1] * mz) * inv
    fx = xx[1] + 2.0 * xx[3] * uq + xx[4] * vq
    fy = xx[2] + xx[4] * uq + 2.0 * xx[5] * vq
    fxx = 2.0 * xx[3]
    fxy = xx[4]
    fyy = 2.0 * xx[5]
    g = 1.0 + fx * fx + fy * fy
    H = ((1.0 + fy * fy) * fxx - 2.0 * fx * fy * fxy + (1.0 + fx * fx) * fyy) / (2.0 * g ** 1.5)
    return abs(H) * inv


@njit(**_JIT)
def _orient(V, normal, i):
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
    return n0, n1, n2


@njit(**_JIT)
def _exact(buf, n, px, py, pz, x, y, z, sj, radius, do_rough, do_curv, i,
           lam, normal, rough, curv, A, C, V, w, M, bb, xx):
    """Two-pass path for one neighbourhood (indices buf[:n]): centred on its own mean."""
    tiny_extent = (1e-9 * radius) ** 2
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
        return  # all duplicates: nothing defined beyond counts and z
    lam[i, 0] = l1
    lam[i, 1] = l2
    lam[i, 2] = l3
    if not l2 > 1e-10 * l1:
        return  # collinear: no plane, no normal
    n0, n1, n2 = _orient(V, normal, i)
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
        curv[i] = _curvature(M, bb, xx, V, mx, my, mz, inv)


@njit(**_JIT)
def _fill_quad(M, bb, n, acc):
    """Normal equations of the quadric fit from the moment sums of `_scan_quad`."""
    su, sv, suu, suv, svv = acc[0], acc[1], acc[2], acc[3], acc[4]
    s3u, s2uv, su2v, s3v = acc[5], acc[6], acc[7], acc[8]
    s4u, s3uv, s22, s3vu, s4v = acc[9], acc[10], acc[11], acc[12], acc[13]
    row0 = (n, su, sv, suu, suv, svv)
    row1 = (su, suu, suv, s3u, s2uv, su2v)
    row2 = (sv, suv, svv, s2uv, su2v, s3v)
    row3 = (suu, s3u, s2uv, s4u, s3uv, s22)
    row4 = (suv, s2uv, su2v, s3uv, s22, s3vu)
    row5 = (svv, su2v, s3v, s22, s3vu, s4v)
    for b in range(6):
        M[0, b] = row0[b]
        M[1, b] = row1[b]
        M[2, b] = row2[b]
        M[3, b] = row3[b]
        M[4, b] = row4[b]
        M[5, b] = row5[b]
    for a in range(6):
        bb[a] = acc[14 + a]


@njit(parallel=True, **_JIT)
def neighbourhoods(px, py, pz, pkeys, zbits, zq, ucol, cstart, qx, qy, qz, qidx, qself, gstart, gcol,
                   blocks, block, nxc, nyc, s, gox, goy, kcols, radius, min_points, do_eig, do_rough, do_z, do_curv, do_cyl,
                   count, lam, normal, rough, zrank, zrange, curv, ncyl, nexact):
    """Per query: neighbour count and, as asked, eigenvalues/normal, roughness, z rank/range,
    curvature, cylinder count.

    px.. cloud sorted by pkeys = (column << zbits) | floor(z / zq), column (ix, iy) being
    [gox + ix s, gox + (ix+1) s) x [goy + iy s, ...) (up to rounding: boxes get a margin);
    coordinates as given (no shift: distances are the reference's to the last bit); columns ucol (sorted) start at
    cstart; qx.. queries sorted the same way, group g = queries gstart[g]:gstart[g+1], all
    in column gcol[g]. blocks: order in which blocks of `block` groups are handed to prange
    (interleaved, for load balance). qself[i] = index of the query in the sorted cloud or -1.
    Outputs are indexed by the query's original index qidx[i] and written here (NaN where
    undefined, see `quakescan.change.features` for the rule), only those asked for (the others may be
    empty); nexact = 1 where the two-pass path ran."""
    r2 = radius * radius
    marg = 1e-7 * s
    nucol = ucol.shape[0]
    ngroup = gcol.shape[0]
    side = 2 * kcols + 1
    do_mom = do_eig or do_rough or do_curv
    inv = 1.0 / radius
    for bi in prange(blocks.shape[0]):
        A = np.empty((3, 3))
        C = np.empty((3, 3))
        V = np.empty((3, 3))
        w = np.empty(3)
        M = np.empty((6, 6))
        bb = np.empty(6)
        xx = np.empty(6)
        acc = np.empty(20)
        ncmax = side * side
        clo = np.empty(ncmax, np.int64)
        chi = np.empty(ncmax, np.int64)
        cs = np.empty(ncmax, np.int64)
        ce = np.empty(ncmax, np.int64)
        off = np.empty(ncmax + 1, np.int64)
        cky = np.empty(ncmax, np.int64)
        rowx = np.empty(side, np.int64)
        rowc = np.empty(side + 1, np.int64)
        doff = np.empty((side, side + 1), np.int64)
        dcs = np.empty((side, side + 1), np.int64)
        rlo = np.empty(side, np.int64)
        rhi = np.empty(side, np.int64)
        zb = np.empty(2, np.int64)
        zf = zb.view(np.float64)
        cap = 4096
        gx_ = np.empty(cap)
        gy_ = np.empty(cap)
        gz_ = np.empty(cap)
        gzi = gz_.view(np.int64)
        gm = np.empty(cap)
        buf = np.empty(0, np.int64)
        g0 = blocks[bi] * block
        for g in range(g0, min(g0 + block, ngroup)):
            key = gcol[g]
            ix = key // nyc
            iy = key % nyc
            q0 = gstart[g]
            q1 = gstart[g + 1]
            zlo = np.inf
            zhi = -np.inf
            for i in range(q0, q1):
                zlo = min(zlo, qz[i])
                zhi = max(zhi, qz[i])
            zlo -= radius + marg
            zhi += radius + marg
            izmax_ = (np.int64(1) << zbits) - 1
            izlo = min(max(np.int64(math.floor(zlo / zq)), 0), izmax_)
            izhi = min(max(np.int64(math.floor(zhi / zq)), 0), izmax_)
            ncol = 0
            nrow = 0
            total = 0
            for dx in range(-kcols, kcols + 1):
                kx = ix + dx
                if kx < 0 or kx >= nxc:
                    continue
                gx = max(abs(dx) - 1, 0) * s
                ky0 = max(iy - kcols, 0)
                ky1 = min(iy + kcols, nyc - 1)
                p = np.searchsorted(ucol, kx * nyc + ky0)
                c_first = ncol
                for ky in range(ky0, ky1 + 1):
                    k2 = kx * nyc + ky
                    while p < nucol and ucol[p] < k2:
                        p += 1
                    if p >= nucol or ucol[p] != k2:
                        continue
                    gy = max(abs(ky - iy) - 1, 0) * s
                    if gx * gx + gy * gy > r2 + marg:
                        continue  # no point of this column within r of the group's column
                    a = cstart[p]
                    b = cstart[p + 1]
                    cs[ncol] = a
                    ce[ncol] = b
                    clo[ncol] = _lower_bound(pkeys, a, b, (k2 << zbits) | izlo)
                    chi[ncol] = _upper_bound(pkeys, clo[ncol], b, (k2 << zbits) | izhi)
                    cky[ncol] = ky
                    off[ncol] = total
                    total += chi[ncol] - clo[ncol]
                    ncol += 1
                if ncol > c_first:
                    rowx[nrow] = kx
                    rowc[nrow] = c_first
                    nrow += 1
            rowc[nrow] = ncol
            off[ncol] = total
            # per row, dense by column slot t (ky = iy - kcols + t): where the slot's points
            # start in the group buffer (doff) and in the cloud (dcs, whole columns)
            for rw in range(nrow):
                c = rowc[rw]
                c1 = rowc[rw + 1]
                for t in range(side + 1):
                    kyt = iy - kcols + t
                    while c < c1 and cky[c] < kyt:
                        c += 1
                    doff[rw, t] = off[c]
                    dcs[rw, t] = cs[c] if c < c1 else ce[c1 - 1]
            # the group's candidates, contiguous: row by row, column by column, z runs
            if total > cap:
                cap = max(total, 2 * cap)
                gx_ = np.empty(cap)
                gy_ = np.empty(cap)
                gz_ = np.empty(cap)
                gzi = gz_.view(np.int64)
                gm = np.empty(cap)
            for c in range(ncol):
                o = off[c] - clo[c]
                for j in range(clo[c], chi[c]):
                    gx_[o + j] = px[j]
                    gy_[o + j] = py[j]
                    gz_[o + j] = pz[j]
            for i in range(q0, q1):
                x = qx[i]
                y = qy[i]
                z = qz[i]
                oi = qidx[i]
                # outputs come uninitialised: NaN unless defined below
                if do_z:
                    zrange[oi] = np.nan
                    zrank[oi] = np.nan
                if do_mom:
                    for a in range(3):
                        lam[oi, a] = np.nan
                        normal[oi, a] = np.nan
                if do_rough:
                    rough[oi] = np.nan
                if do_curv:
                    curv[oi] = np.nan
                nexact[oi] = 0
                n = 0.0
                sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
                izmin = _IMAX
                izmax = np.int64(-1)
                below = 0.0
                cyl = 0
                nrun = 0
                for rw in range(nrow):
                    x0 = gox + rowx[rw] * s
                    ex = max(x0 - x, 0.0, x - (x0 + s))
                    if ex > radius + marg:
                        continue
                    # columns of the row within r: the slots meeting [y - h, y + h]
                    h = math.sqrt(max(r2 - ex * ex, 0.0)) + marg
                    t0 = max(math.floor((y - goy - h) / s) - (iy - kcols), 0)
                    t1 = min(math.floor((y - goy + h) / s) - (iy - kcols), side - 1)
                    if t0 > t1:
                        continue
                    lo = doff[rw, t0]
                    hi = doff[rw, t1 + 1]
                    if do_cyl:
                        cyl += _count_xy(px, py, dcs[rw, t0], dcs[rw, t1 + 1], x, y, r2)
                    if hi <= lo:
                        continue
                    rlo[nrun] = lo
                    rhi[nrun] = hi
                    nrun += 1
                    n += _mask(gx_, gy_, gz_, gm, lo, hi, x, y, z, r2)
                    if do_mom:
                        sx, sy, sz, sxx, sxy, sxz, syy, syz, szz = _scan_mom(
                            gx_, gy_, gz_, gm, lo, hi, x, y, z, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz)
                    if do_z:
                        izmin, izmax, below = _scan_z(gz_, gzi, gm, lo, hi, z, izmin, izmax, below)
                if do_cyl:
                    ncyl[oi] = cyl
                nn = int(n)
                count[oi] = nn
                if nn < min_points:
                    continue
                sj = qself[i]
                if do_z:
                    zb[0] = izmin
                    zb[1] = izmax
                    zrange[oi] = zf[1] - zf[0]
                    zrank[oi] = below / (nn - 1.0) if sj >= 0 else below / n
                if not do_mom:
                    continue
                mx = sx / n
                my = sy / n
                mz = sz / n
                _eig3(sxx / n - mx * mx, sxy / n - mx * my, sxz / n - mx * mz,
                      syy / n - my * my, syz / n - my * mz, szz / n - mz * mz, V, w)
                l1 = max(w[0], 0.0)
                l2 = max(w[1], 0.0)
                l3 = max(w[2], 0.0)
                exact = l1 <= 1e-4 * r2 or l2 <= 1e-6 * l1 or l3 <= 1e-6 * l1
                rgh = np.nan
                if not exact and do_rough and sj >= 0:
                    n1 = n - 1.0
                    ox = sx / n1
                    oy = sy / n1
                    oz = sz / n1
                    _eig3(sxx / n1 - ox * ox, sxy / n1 - ox * oy, sxz / n1 - ox * oz,
                          syy / n1 - oy * oy, syz / n1 - oy * oz, szz / n1 - oz * oz, C, xx)
                    o1 = max(xx[0], 0.0)
                    if o1 <= 1e-4 * r2 or max(xx[1], 0.0) <= 1e-6 * o1:
                        exact = True
                    else:
                        rgh = abs(C[0, 2] * ox + C[1, 2] * oy + C[2, 2] * oz)
                if exact:
                    nexact[oi] = 1
                    if buf.shape[0] < total:
                        buf = np.empty(total, np.int64)
                    k = 0
                    for ru in range(nrun):
                        for j in range(rlo[ru], rhi[ru]):
                            if _d2(gx_[j] - x, gy_[j] - y, gz_[j] - z) <= r2:
                                buf[k] = j
                                k += 1
                    # the point itself, by position in the group buffer: its d is exactly 0
                    sb = -1
                    if sj >= 0:
                        for t in range(k):
                            if gx_[buf[t]] == x and gy_[buf[t]] == y and gz_[buf[t]] == z:
                                sb = buf[t]
                                break
                    _exact(buf, k, gx_, gy_, gz_, x, y, z, sb, radius, do_rough, do_curv, oi,
                           lam, normal, rough, curv, A, C, V, w, M, bb, xx)
                    continue
                lam[oi, 0] = l1
                lam[oi, 1] = l2
                lam[oi, 2] = l3
                n0, n1_, n2 = _orient(V, normal, oi)
                if do_rough:
                    rough[oi] = rgh if sj >= 0 else abs(n0 * mx + n1_ * my + n2 * mz)
                if do_curv and nn >= 6:
                    for a in range(20):
                        acc[a] = 0.0
                    for ru in range(nrun):
                        _scan_quad(gx_, gy_, gz_, gm, rlo[ru], rhi[ru], x, y, z, mx, my, mz, V, inv, acc)
                    _fill_quad(M, bb, n, acc)
                    curv[oi] = _curvature(M, bb, xx, V, mx, my, mz, inv)


@njit(parallel=True, **_JIT)
def grid_keys(x, y, z, sx, sy, s, q, nxc, nyc, zbits, keys):
    """Sort key of each point: column (ix * nyc + iy, side s, from sx, sy) in the high bits,
    z quantised by q in the low `zbits` bits (clipped; z >= 0 in the local frame)."""
    zmax = (np.int64(1) << zbits) - 1
    for i in prange(x.shape[0]):
        ix = min(max(np.int64(math.floor((x[i] - sx) / s)), 0), nxc - 1)
        iy = min(max(np.int64(math.floor((y[i] - sy) / s)), 0), nyc - 1)
        iz = min(max(np.int64(math.floor(z[i] / q)), 0), zmax)
        keys[i] = ((ix * nyc + iy) << zbits) | iz


@njit(parallel=True, **_JIT)
def gather(x, y, z, order, ox, oy, oz):
    """ox[i] = x[order[i]] etc."""
    for i in prange(order.shape[0]):
        j = order[i]
        ox[i] = x[j]
        oy[i] = y[j]
        oz[i] = z[j]


@njit(parallel=True, **_JIT)
def eigen_features(lam, codes, out):
    """out[k] = eigen feature codes[k] of every row of lam (l1 >= l2 >= l3, NaN rows stay NaN):
    0 linearity, 1 planarity, 2 sphericity, 3 anisotropy, 4 surface_variation, 5 omnivariance,
    6 eigenentropy, 7 eigenvalue_sum: the `compiled` codes of `quakescan.change.features.REGISTRY`, whose
    `derive` is the definition each branch must reproduce."""
    for i in prange(lam.shape[0]):
        l1 = lam[i, 0]
        l2 = lam[i, 1]
        l3 = lam[i, 2]
        sm = l1 + l2 + l3
        for k in range(codes.shape[0]):
            c = codes[k]
            if c == 0:
                v = (l1 - l2) / l1
            elif c == 1:
                v = (l2 - l3) / l1
            elif c == 2:
                v = l3 / l1
            elif c == 3:
                v = (l1 - l3) / l1
            elif c == 4:
                v = l3 / sm
            elif c == 5:
                v = np.cbrt((l1 / sm) * (l2 / sm) * (l3 / sm))
            elif c == 6:
                v = 0.0
                if math.isnan(sm):
                    v = np.nan
                else:
                    for e in (l1 / sm, l2 / sm, l3 / sm):
                        if e > 0.0:
                            v -= e * math.log(e)
            else:
                v = sm
            out[k, i] = v
