"""Plain numpy references of `quakescan.change._feature_kernels`, one per compiled function, for the
tests (and benchmarks) that compare the two; nothing in production calls them.

`neighbourhoods` reads the definitions of `quakescan.change.features` literally: one query at a time,
neighbours from a kd-tree filtered by the kernel's own distance test, the covariance
centred on the neighbourhood's mean (the kernel sums relative to the query point and
recentres only where a small eigenvalue decides), a quadric fitted by `numpy.linalg`.
`reference_features` is `quakescan.change.features.compute_features` on top of it, each feature from
its registry definition (no compiled eigen pass, no duplicate folding).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import features as F


def neighbourhoods(cloud, query, qself, radius, do_eig, do_rough, do_z, do_curv, do_cyl) -> F.Measures:
    """`_feature_kernels.neighbourhoods`: the measures at each query point. cloud (n, 3) and
    query (m, 3) in one local frame; qself[i] = index of query i in the cloud, or -1 for a
    core point; radius the tested radius (tolerance included)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(cloud)
    m = len(query)
    count = np.zeros(m, np.int64)
    lam = np.full((m, 3), np.nan)
    normal = np.full((m, 3), np.nan)
    rough, zrank, zrange, curv = (np.full(m, np.nan) for _ in range(4))
    ncyl = None
    if do_cyl:
        ncyl = np.asarray(cKDTree(cloud[:, :2]).query_ball_point(query[:, :2], radius, return_length=True),
                          dtype=np.float64)
    tiny = (1e-9 * radius) ** 2
    for i, q in enumerate(query):
        idx = np.array(sorted(tree.query_ball_point(q, radius)), dtype=np.int64)
        # query_ball_point tests the distance as scipy does; use the kernel's test exactly
        d = cloud[idx] - q
        idx = idx[np.sum(d * d, axis=1) <= radius * radius]
        nb = cloud[idx]
        k = len(idx)
        count[i] = k
        if k < F.MIN_POINTS:
            continue
        if do_z:
            zrange[i] = nb[:, 2].max() - nb[:, 2].min()
            below = np.sum(nb[:, 2] < q[2])
            zrank[i] = below / (k - 1) if qself[i] >= 0 else below / k
        if not (do_eig or do_rough or do_curv):
            continue
        mean = nb.mean(axis=0)
        c = nb - mean
        w, v = np.linalg.eigh(c.T @ c / k)
        w = np.clip(w[::-1], 0.0, None)
        v = v[:, ::-1]
        if w[0] <= tiny:
            continue
        lam[i] = w
        if w[1] <= 1e-10 * w[0]:
            continue
        nrm = v[:, 2] * (1 if (v[2, 2], v[1, 2], v[0, 2]) >= (0, 0, 0) else -1)
        normal[i] = nrm
        if do_rough:
            if qself[i] >= 0:
                others = nb[idx != qself[i]]
                mo = others.mean(axis=0)
                wo, vo = np.linalg.eigh((others - mo).T @ (others - mo) / len(others))
                if wo[1] > 1e-10 * wo[2] and wo[2] > tiny:
                    rough[i] = abs(vo[:, 0] @ (q - mo))
            else:
                rough[i] = abs(nrm @ (q - mean))
        if do_curv and k >= 6:
            u, vv, h = (c @ v / radius).T
            X = np.column_stack([np.ones(k), u, vv, u * u, u * vv, vv * vv])
            MtM = X.T @ X
            if np.linalg.cond(MtM) < 1e12:
                coef = np.linalg.solve(MtM, X.T @ h)
                uq, vq = (q - mean) @ v[:, :2] / radius
                fx = coef[1] + 2 * coef[3] * uq + coef[4] * vq
                fy = coef[2] + coef[4] * uq + 2 * coef[5] * vq
                fxx, fxy, fyy = 2 * coef[3], coef[4], 2 * coef[5]
                g = 1 + fx * fx + fy * fy
                curv[i] = abs(((1 + fy * fy) * fxx - 2 * fx * fy * fxy + (1 + fx * fx) * fyy)
                              / (2 * g ** 1.5)) / radius
    return F.Measures(count, lam, normal, rough, zrank, zrange, curv, ncyl)


def eigen_features(lam, codes, out):
    """`_feature_kernels.eigen_features`: out[k] = the registry's definition of the feature
    with compiled code codes[k], at every row of lam."""
    by_code = {f.compiled: f for f in F.REGISTRY.values() if f.compiled is not None}
    measures = replace(F.Measures.undefined(len(lam)), lam=np.asarray(lam, dtype=np.float64))
    for k, c in enumerate(codes):
        out[k] = by_code[int(c)].value(measures, np.nan)  # eigen ratios do not depend on r


def grid_keys(x, y, z, sx, sy, s, q, nxc, nyc, zbits, keys):
    """`_feature_kernels.grid_keys`: column (ix * nyc + iy) above, quantised z below."""
    ix = np.clip(np.floor((x - sx) / s).astype(np.int64), 0, nxc - 1)
    iy = np.clip(np.floor((y - sy) / s).astype(np.int64), 0, nyc - 1)
    iz = np.clip(np.floor(z / q).astype(np.int64), 0, (1 << zbits) - 1)
    keys[:] = ((ix * nyc + iy) << zbits) | iz


def gather(x, y, z, order, ox, oy, oz):
    """`_feature_kernels.gather`."""
    ox[:], oy[:], oz[:] = x[order], y[order], z[order]


def reference_features(xyz, radius, features=None, core_points=None, query_index=None) -> dict[str, np.ndarray]:
    """`quakescan.change.features.compute_features` in plain numpy (same definitions, same NaN rule)."""
    xyz, radius, names, core_points, query_index = F._check(xyz, radius, features, core_points, query_index)
    m = F._query_count(xyz, core_points, query_index)
    n = len(xyz)
    if m == 0 or n == 0:
        return F._evaluate(names, radius, F.Measures.undefined(m))
    origin = xyz.min(axis=0)
    cloud = xyz - origin
    if core_points is not None:
        query, qself = core_points - origin, np.full(m, -1, np.int64)
    elif query_index is not None:
        query, qself = cloud[query_index], query_index
    else:
        query, qself = cloud, np.arange(n, dtype=np.int64)
    measures = neighbourhoods(cloud, query, qself, radius * (1.0 + F.RADIUS_TOLERANCE), *F.kernel_switches(names))
    return F._evaluate(names, radius, measures)
