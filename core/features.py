"""Per-point geometric features in a spherical neighbourhood (Zahs et al., "Object-specific
change feature selection"; radii 1.0-4.0 m).

    >>> feats = compute_features(xyz, radius=1.5, features=("planarity", "roughness"))
    >>> feats["planarity"].shape        # (n,) float64

Neighbourhood
    All cloud points p with |p - q| <= r, the query point itself included when it belongs to
    the cloud (N counts it), up to a relative 1e-9 (`RADIUS_TOLERANCE`: ties at exactly r,
    common on the mm grid of LAS files, stay neighbours in any frame). The whole cloud is
    shifted once to a local origin (its minimum corner), so a cloud at UTM coordinates
    gives the same features as at the origin. The
    compiled kernel sums the moments of d = p - q relative to the query point in one pass
    (|d| <= r, error <= ~3 (N + 3) eps r^2 on every eigenvalue) and redoes, centred on the
    neighbourhood's own mean (two passes), every neighbourhood where a small eigenvalue
    decides: l1 <= 1e-4 r^2, l2 <= 1e-6 l1 or l3 <= 1e-6 l1 (near-collinear, near-exact
    planes); see `quakescan._feature_kernels`. The numpy reference always centres on the mean.

Definitions (CloudCompare / CCCoreLib "Geometric features"; jakteristics copies them)
    C = (1/N) sum (p - mean)(p - mean)^T (population covariance, as CloudCompare; jakteristics
    uses 1/(N-1)); eigenvalues l1 >= l2 >= l3 >= 0 (tiny negative round-off clipped to 0).
    eigenvalue1/2/3, eigenvalue_sum : raw l1, l2, l3 and l1+l2+l3, in m^2.
    linearity (l1-l2)/l1, planarity (l2-l3)/l1, sphericity l3/l1, anisotropy (l1-l3)/l1,
    surface_variation l3/(l1+l2+l3) : ratios, unchanged by normalisation.
    omnivariance (e1 e2 e3)^(1/3), eigenentropy -sum e_i ln e_i with e_i = l_i/(l1+l2+l3)
    (normalised by the sum, as CloudCompare; 0 ln 0 := 0). jakteristics uses raw l_i here.
    normal_x/y/z : unit eigenvector of l3, oriented n_z >= 0 (if n_z == 0 exactly: n_y >= 0,
    then n_x >= 0). verticality 1 - |n_z| (wall 1, roof 0).
    roughness : distance of the point to the least-squares plane of its neighbours *without
    the point itself* (CloudCompare's Roughness). For core points not in the cloud, the plane
    of all neighbours.
    curvature : CloudCompare's mean curvature |H| in 1/m: a quadric h = a + bu + cv + du^2 +
    euv + fv^2 fitted by least squares in the PCA frame (e1, e2, normal) of the neighbourhood
    centred on its mean, evaluated at the query point's (u, v). A sphere of radius R gives
    ~1/R; a plane 0. (The "change of curvature" l3/sum is `surface_variation`.)
    num_neighbours N; surface_density N/(pi r^2); volume_density N/(4/3 pi r^3)
    (CloudCompare's precise "Density": number of neighbours / surface / volume).
    point_density : planimetric density N_cyl/(pi r^2), points per m^2 of ground, N_cyl =
    points in the infinite vertical cylinder of radius r (the usual LiDAR "point density",
    which differs from surface_density on walls and under vegetation).
    echo_ratio : Hoefle et al. (2009) 100 * N / N_cyl in percent (sphere over vertical
    cylinder of the same radius); meaningful when the cloud holds all echoes of the pulses.
    z_range : max z - min z in the neighbourhood. z_rank : share of the other neighbours
    strictly below the point, #{z_j < z_q}/(N-1) in [0, 1] (0 lowest, 1 highest); for a core
    point not in the cloud #{z_j < z_q}/N.

Degenerate neighbourhoods: one rule
    counts, densities and echo ratio are always finite (echo ratio NaN only for a core point
    with no cloud point in its cylinder). Everything else is NaN when
      * N < 4 (MIN_POINTS, the point itself included);
      * eigen features, normal, verticality, roughness, curvature: the neighbourhood has no
        extent (l1 <= (1e-9 r)^2: all duplicates);
      * normal, verticality, roughness, curvature: no plane is defined (collinear:
        l2 <= 1e-10 l1; for roughness the same test on the neighbours without the point);
      * curvature: the quadric's normal equations are singular (fewer than 6 points or a
        degenerate layout; relative pivot 1e-12).
    An exact plane (l3 = 0) is not degenerate: eigenentropy stays finite (0 ln 0 := 0),
    sphericity and omnivariance are 0. No feature is ever silently inf.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from .errors import QuakeScanError

log = logging.getLogger(__name__)

FEATURES = (
    "linearity", "planarity", "omnivariance", "surface_variation", "curvature", "point_density",
    "num_neighbours", "surface_density", "volume_density", "sphericity", "verticality",
    "eigenentropy", "anisotropy", "eigenvalue1", "eigenvalue2", "eigenvalue3", "eigenvalue_sum",
    "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z", "echo_ratio",
)
# what the damage pipeline computes by default: the paper's robust set plus curvature (the
# changed/unchanged split needs it)
DEFAULT_PIPELINE_FEATURES = (
    "planarity", "surface_variation", "point_density", "num_neighbours", "surface_density",
    "volume_density", "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z", "curvature",
)
MIN_POINTS = 4
_EIGEN = {"linearity", "planarity", "omnivariance", "surface_variation", "sphericity", "eigenentropy",
          "anisotropy", "eigenvalue1", "eigenvalue2", "eigenvalue3", "eigenvalue_sum"}
_NORMAL = {"verticality", "normal_x", "normal_y", "normal_z"}
_Z = {"z_rank", "z_range"}
_EIG_CODES = {"linearity": 0, "planarity": 1, "sphericity": 2, "anisotropy": 3, "surface_variation": 4,
              "omnivariance": 5, "eigenentropy": 6, "eigenvalue_sum": 7}
_CYL = {"point_density", "echo_ratio"}


class FeatureError(QuakeScanError):
    """Features cannot be computed as asked (bad radius, names or coordinates)."""


def _check(xyz, radius, features, core_points):
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise FeatureError(f"xyz must be an (n, 3) array, got shape {xyz.shape}")
    if not np.all(np.isfinite(xyz)):
        raise FeatureError("xyz holds NaN or inf coordinates; drop those points first")
    if not (isinstance(radius, (int, float, np.floating)) and math.isfinite(radius) and radius > 0):
        raise FeatureError(f"radius must be a positive number of metres, got {radius!r}")
    names = FEATURES if features is None else tuple(features)
    unknown = [f for f in names if f not in FEATURES]
    if unknown:
        raise FeatureError(f"unknown features {unknown}; known: {', '.join(FEATURES)}")
    if core_points is not None:
        core_points = np.asarray(core_points, dtype=np.float64)
        if core_points.ndim != 2 or core_points.shape[1] != 3 or not np.all(np.isfinite(core_points)):
            raise FeatureError(f"core_points must be a finite (m, 3) array, got shape {core_points.shape}")
    return xyz, float(radius), names, core_points


# Neighbours are the points with |p - q| <= r (1 + RADIUS_TOLERANCE). On the millimetre grid
# of LAS files many points lie at exactly r from a query; the same points in a local frame
# and at UTM coordinates differ by ~1e-10 m of rounding, which would flip such ties in or
# out. The next distance a mm grid allows beyond r is ~1e-6 relative away, so 1e-9 keeps
# every tie inside in any frame and admits nothing else.
RADIUS_TOLERANCE = 1e-9


def _derive(names, radius, count, lam, normal, rough, zrank, zrange, curv, ncyl):
    """Feature arrays from the per-neighbourhood quantities (same for fast and reference)."""
    out = {}
    n = count.astype(np.float64)
    eig = [f for f in _EIG_CODES if f in names]
    if eig:  # the ratios in one compiled parallel pass (numpy's temporaries cost more than the kernel)
        from . import _feature_kernels as K

        arr = np.empty((len(eig), len(count)))
        K.eigen_features(np.ascontiguousarray(lam), np.array([_EIG_CODES[f] for f in eig], np.int64), arr)
        out.update(zip(eig, arr))
    with np.errstate(divide="ignore", invalid="ignore"):
        for name in names:
            if name in out:
                continue
            if name == "num_neighbours":
                v = n
            elif name == "surface_density":
                v = n / (math.pi * radius ** 2)
            elif name == "volume_density":
                v = n / (4.0 / 3.0 * math.pi * radius ** 3)
            elif name == "point_density":
                v = ncyl / (math.pi * radius ** 2)
            elif name == "echo_ratio":
                v = np.where(ncyl > 0, 100.0 * n / np.maximum(ncyl, 1), np.nan)
            elif name in ("eigenvalue1", "eigenvalue2", "eigenvalue3"):
                v = lam[:, int(name[-1]) - 1].copy()
            elif name == "verticality":
                v = 1.0 - np.abs(normal[:, 2])
            elif name in ("normal_x", "normal_y", "normal_z"):
                v = normal[:, "xyz".index(name[-1])].copy()
            elif name == "roughness":
                v = rough
            elif name == "z_rank":
                v = zrank
            elif name == "z_range":
                v = zrange
            elif name == "curvature":
                v = curv
            out[name] = np.asarray(v, dtype=np.float64)
    return out


def _needs(names):
    names = set(names)
    do_curv = "curvature" in names
    do_rough = "roughness" in names
    do_eig = bool(names & (_EIGEN | _NORMAL))
    return do_eig, do_rough, bool(names & _Z), do_curv, bool(names & _CYL)


CELLS_PER_RADIUS = 3  # grid columns of side r/3: 1.45x the sphere's points tested (side r: 2.5x)
_BLOCK = 8  # query groups per prange block (blocks are interleaved over the threads)
PROGRESS_STEPS = 50  # kernel calls when progress is reported (each call a 2 % share of the query groups)


def _fast(cloud, query, radius, names, workers, cells_per_radius=None, stats=None, query_index=None,
          progress=None):
    """Run the numba kernel. cloud: (x, y, z) contiguous arrays in the local frame (z >= 0);
    query: the same for core points, or None for the cloud's own points (all of them, or
    those in `query_index`).

    Returns count, lam, normal, rough, zrank, zrange, curv, ncyl (None where not asked for)."""
    from numba import get_num_threads, set_num_threads

    from . import _feature_kernels as K

    k = CELLS_PER_RADIUS if cells_per_radius is None else int(cells_per_radius)
    s = radius / k
    lo = np.array([min(float(c.min()), float(qc.min()) if query is not None else np.inf)
                   for c, qc in zip(cloud, query if query is not None else cloud)])
    hi = np.array([max(float(c.max()), float(qc.max()) if query is not None else -np.inf)
                   for c, qc in zip(cloud, query if query is not None else cloud)])
    nxc, nyc = (int(d) for d in np.floor((hi[:2] - lo[:2]) / s).astype(np.int64) + 1)
    colbits = max(int(nxc * nyc - 1).bit_length(), 1)
    zbits = min(62 - colbits, 40)
    if zbits < 8:
        raise FeatureError(f"the cloud spans {hi - lo} m: too many cells of {s} m; split it into tiles")
    q = s / 64.0  # z order within a column, to 1/64 of a cell (the kernel cuts z runs on it)
    zext = max(float(hi[2]), 0.0)
    sh = 6
    if zext / q >= 2.0 ** zbits - 2:
        q, sh = zext / (2.0 ** zbits - 2), 0

    old = get_num_threads()
    if workers is not None and workers > 0:
        set_num_threads(min(workers, old))  # for the sort and the kernel
    try:
        def sort(x, y, z):
            keys = np.empty(len(x), np.int64)
            K.grid_keys(x, y, z, lo[0], lo[1], s, q, nxc, nyc, zbits, keys)
            order = np.argsort(keys)
            keys = keys[order]
            out = [np.empty(len(x)) for _ in range(3)]
            K.gather(x, y, z, order, *out)
            return order, keys, out

        porder, pkeys, (px, py, pz) = sort(*cloud)
        pcol = pkeys >> zbits
        brk = np.flatnonzero(pcol[1:] != pcol[:-1]) + 1
        cstart = np.concatenate([[0], brk, [len(pcol)]]).astype(np.int64)
        ucol = pcol[cstart[:-1]]
        del pcol, brk
        if query is None and query_index is None:
            qorder, qkeys, (qx, qy, qz) = porder, pkeys, (px, py, pz)
            qs = np.arange(len(px), dtype=np.int64)  # query i of the sorted order is cloud point i
        elif query is None:
            # a subset of the cloud's own points: their places in the sorted cloud, in key order
            inv = np.empty(len(porder), np.int64)
            inv[porder] = np.arange(len(porder))
            sp = inv[query_index]
            qorder = np.argsort(sp, kind="stable")  # query i -> output position qorder[i]
            qs = sp[qorder]
            qkeys, qx, qy, qz = pkeys[qs], px[qs], py[qs], pz[qs]
        else:
            qorder, qkeys, (qx, qy, qz) = sort(*query)
            qs = np.full(len(qx), -1, np.int64)
        # groups: one column, one z slab of height s (sh = 6: 64 q) -- or of q if z spans too much
        gkey = qkeys >> sh
        gstart = np.concatenate([[0], np.flatnonzero(gkey[1:] != gkey[:-1]) + 1, [len(gkey)]]).astype(np.int64)
        gcol = qkeys[gstart[:-1]] >> zbits
        del gkey
        do_eig, do_rough, do_z, do_curv, do_cyl = _needs(names)
        do_mom = do_eig or do_rough or do_curv
        m = len(qx)
        empty1, empty3 = np.empty(0), np.empty((0, 3))
        count = np.empty(m, np.int64)
        lam = np.empty((m, 3)) if do_mom else empty3
        normal = np.empty((m, 3)) if do_mom else empty3
        rough = np.empty(m) if do_rough else empty1
        zrank = np.empty(m) if do_z else empty1
        zrange = np.empty(m) if do_z else empty1
        curv = np.empty(m) if do_curv else empty1
        ncyl = np.empty(m if do_cyl else 0, np.int64)
        nexact = np.empty(m, np.int8)
        kcols = int(np.floor(radius / s * (1 + 1e-9))) + 1
        threads = get_num_threads()
        nb = -(-len(gcol) // _BLOCK)
        # with a progress callback the blocks go to the kernel in PROGRESS_STEPS calls; each
        # query's result is its own, so the outputs are the same as in one call
        parts = np.array_split(np.arange(nb, dtype=np.int64), PROGRESS_STEPS if progress else 1)
        for k, part in enumerate(parts, 1):
            if len(part) == 0:
                continue
            blocks = np.concatenate([part[t::threads] for t in range(threads)]).astype(np.int64)
            K.neighbourhoods(px, py, pz, pkeys, zbits, q, ucol, cstart, qx, qy, qz, qorder, qs, gstart, gcol,
                             blocks, _BLOCK, nxc, nyc, s, lo[0], lo[1], kcols, radius, MIN_POINTS,
                             do_eig, do_rough, do_z, do_curv, do_cyl,
                             count, lam, normal, rough, zrank, zrange, curv, ncyl, nexact)
            if progress:
                progress(int(gstart[min(int(part[-1] + 1) * _BLOCK, len(gcol))]), m)
    finally:
        set_num_threads(old)
    if stats is not None:
        stats["exact_share"] = float(nexact.mean()) if m else 0.0
        stats["groups"] = len(gcol)
    nan1 = np.full(m, np.nan)
    return (count, lam if do_mom else np.full((m, 3), np.nan), normal if do_mom else np.full((m, 3), np.nan),
            rough if do_rough else nan1, zrank if do_z else nan1, zrange if do_z else nan1,
            curv if do_curv else nan1, ncyl if do_cyl else None)


def position_keys(xyz) -> np.ndarray:
    """(n,) uint64 hash of each point's exact float64 coordinates: equal points, equal keys
    (different points collide with probability ~n²/2**64; `duplicate_groups` checks)."""
    u = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3).view(np.uint64)
    h = u[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    h ^= u[:, 1]
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= u[:, 2]
    h ^= h >> np.uint64(32)
    h *= np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def duplicate_groups(xyz):
    """(first, inverse) when some points of `xyz` coincide exactly: `first` indexes one point
    of each distinct position, xyz[first][inverse] == xyz. None when all are distinct (the
    common case: one hash and one sort of the keys)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    keys = position_keys(xyz)
    order = np.argsort(keys, kind="stable")
    ks = keys[order]
    same = ks[1:] == ks[:-1]
    if not same.any():
        return None
    n = len(xyz)
    starts = np.concatenate([[True], ~same])
    run_first = order[np.maximum.accumulate(np.where(starts, np.arange(n), 0))]
    exact = np.all(xyz[order] == xyz[run_first], axis=1)  # a hash collision stays its own point
    rep = np.empty(n, np.int64)
    rep[order] = np.where(exact, run_first, order)
    first, inverse = np.unique(rep, return_inverse=True)
    if len(first) == n:
        return None
    return first, inverse.reshape(-1)


def compute_features(xyz, radius: float, features: Sequence[str] | None = None, core_points=None,
                     workers: int | None = None, fast: bool = True, query_index=None,
                     progress=None) -> dict[str, np.ndarray]:
    """Geometric features of every point (or of every core point) at a spherical radius.

    Parameters
    ----------
    xyz : (n, 3) float64
        The point cloud, world or local coordinates (shifted to a local origin internally).
    radius : float
        Neighbourhood radius r in metres (the paper uses 1.0-4.0).
    features : sequence of str, optional
        Names from `FEATURES`; default all. Only what they need is computed (no eigen
        decomposition for densities or z features, no cylinder search without
        point_density/echo_ratio, no quadric fit without curvature).
    core_points : (m, 3) float64, optional
        Where to evaluate; default the cloud's own points (then each neighbourhood includes
        the point). Core points are not part of the cloud.
    query_index : (m,) int, optional
        Evaluate only at these points of the cloud (neighbourhoods from the whole cloud,
        the point itself included, as for the default); results in this order.
    workers : int, optional
        Threads for the compiled kernel (default: all of numba's). Load is balanced by
        handing the threads interleaved blocks of query groups.
    fast : bool
        False runs the plain numpy reference (slow; for tests).
    progress : callable, optional
        Called as progress(points_done, points_total) about 50 times (fast path only); the
        results are the same with and without it.

    Returns
    -------
    dict of str -> (n,) or (m,) float64
        One array per requested feature, NaN where the degenerate rule of the module says so.
    """
    xyz, radius, names, core_points = _check(xyz, radius, features, core_points)
    n = len(xyz)
    if query_index is not None:
        if core_points is not None:
            raise FeatureError("give core_points or query_index, not both")
        query_index = np.asarray(query_index, dtype=np.int64)
        if query_index.ndim != 1 or (len(query_index) and (query_index.min() < 0 or query_index.max() >= n)):
            raise FeatureError(f"query_index must index the {n} points of the cloud")
    m = n if core_points is None else len(core_points)
    if query_index is not None:
        m = len(query_index)
    if m == 0 or n == 0:
        nan = np.full(m, np.nan)
        return {f: (np.zeros(m) if f in ("num_neighbours", "surface_density", "volume_density",
                                         "point_density") else nan.copy()) for f in names}
    if fast and m > 1:
        # Coincident query points have one neighbourhood: computed once. Without this the
        # kernel is quadratic in the duplicates (200 000 copies of one point: hours).
        qpts = core_points if core_points is not None else (xyz if query_index is None else xyz[query_index])
        groups = duplicate_groups(qpts)
        if groups is not None:
            first, inverse = groups
            # progress in the caller's points: the distinct ones stand for all their copies
            scaled = None if progress is None else (lambda d, t: progress(m if d >= t else d * m // max(t, 1), m))
            if core_points is not None:
                once = compute_features(xyz, radius, names, core_points=core_points[first], workers=workers,
                                        progress=scaled)
            else:
                at = first if query_index is None else query_index[first]
                once = compute_features(xyz, radius, names, workers=workers, query_index=at, progress=scaled)
            return {k: v[inverse] for k, v in once.items()}
    origin = xyz.min(axis=0)
    cols = [np.ascontiguousarray(xyz[:, k] - origin[k]) for k in range(3)]
    r_test = radius * (1.0 + RADIUS_TOLERANCE)
    need_cyl = bool(set(names) & _CYL)
    if fast:
        query = None if core_points is None else [np.ascontiguousarray(core_points[:, k] - origin[k])
                                                  for k in range(3)]
        count, lam, normal, rough, zrank, zrange, curv, ncyl = _fast(cols, query, r_test, names, workers,
                                                                     query_index=query_index, progress=progress)
        ncyl = ncyl.astype(np.float64) if need_cyl else None
    else:
        cloud = np.column_stack(cols)
        if core_points is not None:
            query = core_points - origin
            qself = np.full(m, -1, np.int64)
        elif query_index is not None:
            query, qself = cloud[query_index], query_index
        else:
            query, qself = cloud, np.arange(n, dtype=np.int64)
        count, lam, normal, rough, zrank, zrange, curv, ncyl = _reference(cloud, query, qself, r_test, names)
    return _derive(names, radius, count, lam, normal, rough, zrank, zrange, curv, ncyl)


def _reference(cloud, query, qself, radius, names):
    """Plain numpy, one point at a time: the obvious reading of the module's definitions."""
    from scipy.spatial import cKDTree

    do_eig, do_rough, do_z, do_curv, do_cyl = _needs(names)
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
        if k < MIN_POINTS:
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
    return count, lam, normal, rough, zrank, zrange, curv, ncyl


def _reference_features(xyz, radius, features=None, core_points=None, query_index=None):
    """The slow numpy reference of `compute_features` (same definitions, same NaN rule)."""
    return compute_features(xyz, radius, features, core_points, fast=False, query_index=query_index)
