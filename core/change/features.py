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
    planes); see `quakescan.change._feature_kernels`. The numpy reference (`quakescan.change._feature_reference`,
    one point at a time) always centres on the mean.

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

Registry: how a feature is declared
    One pass over each neighbourhood measures what the requested features need (`MEASURES`:
    count, eigen, normal, roughness, z, curvature, cylinder), into a `Measures`; every
    feature is then a function of those measures and r. `REGISTRY` holds one `Feature` per
    name: its category, the measures it needs and `derive`, its numpy definition. FEATURES,
    what the kernel is asked to measure and the derivation all read it; the reference
    (`quakescan.change._feature_reference`) derives every feature with the same `derive`.
    * A feature derived from existing measures: one `Feature` entry, appended at the end of
      REGISTRY (FEATURES is its order, and models and cached training tables name their
      columns in it). `compiled=` is optional: a code of `_feature_kernels.eigen_features`
      computing the same formula in the compiled pass over the eigenvalues (then add the
      code there; the tests compare it with `derive`).
    * A feature needing a new measure (a new moment of the neighbourhood): a name in
      MEASURES with the kernel switch that computes it, a field of `Measures` (and its
      undefined value in `Measures.undefined`), its accumulation and output array in
      `_feature_kernels.neighbourhoods` (and the switch in `_kernel_measures`), the same
      quantity in `_feature_reference.neighbourhoods`, then the `Feature` entry.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import QuakeScanError
from ..runtime.progress import ProgressCallback

log = logging.getLogger(__name__)

MIN_POINTS = 4

# What one pass over a neighbourhood can measure, and the switch of
# `_feature_kernels.neighbourhoods` (and of the reference) that measures it; the count is
# always measured. eigen and normal come from one eigen decomposition, hence one switch.
MEASURES = {
    "count": None,  # N, points within r
    "eigen": "do_eig",  # l1 >= l2 >= l3 of the population covariance
    "normal": "do_eig",  # unit eigenvector of l3, oriented
    "roughness": "do_rough",  # distance to the plane of the other neighbours
    "z": "do_z",  # z range and z rank
    "curvature": "do_curv",  # |H| of the quadric
    "cylinder": "do_cyl",  # N_cyl, points in the vertical cylinder of radius r
}
KERNEL_SWITCHES = ("do_eig", "do_rough", "do_z", "do_curv", "do_cyl")  # the kernel's argument order


@dataclass
class Measures:
    """Per query point (m of them): what the features are derived from. Arrays not measured
    are NaN (ncyl None); see the module's degenerate rule for where measured ones are NaN."""

    count: np.ndarray  # (m,) int64
    lam: np.ndarray  # (m, 3) eigenvalues, descending
    normal: np.ndarray  # (m, 3)
    rough: np.ndarray  # (m,)
    zrank: np.ndarray
    zrange: np.ndarray
    curv: np.ndarray
    ncyl: np.ndarray | None  # (m,) float64

    @classmethod
    def undefined(cls, m: int) -> Measures:
        """m queries with no neighbour at all (an empty cloud)."""
        return cls(np.zeros(m, np.int64), np.full((m, 3), np.nan), np.full((m, 3), np.nan),
                   *(np.full(m, np.nan) for _ in range(4)), np.zeros(m))

    @property
    def n(self) -> np.ndarray:
        return self.count.astype(np.float64)

    @property
    def l1(self) -> np.ndarray:
        return self.lam[:, 0]

    @property
    def l2(self) -> np.ndarray:
        return self.lam[:, 1]

    @property
    def l3(self) -> np.ndarray:
        return self.lam[:, 2]

    @property
    def eigensum(self) -> np.ndarray:
        return self.l1 + self.l2 + self.l3


@dataclass(frozen=True)
class Feature:
    """One point feature: `derive(measures, r)` gives its (m,) values from the measures it
    `needs` (names of MEASURES); `compiled` is its code in `_feature_kernels.eigen_features`
    when a compiled pass computes the same formula (eigen ratios: numpy's temporaries would
    cost more than the neighbourhood kernel)."""

    name: str
    category: str  # one of CATEGORIES
    needs: frozenset
    derive: Callable[[Measures, float], np.ndarray]
    compiled: int | None = None

    def value(self, measures: Measures, radius: float) -> np.ndarray:
        """(m,) float64; NaN (never inf) where the measures are undefined."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(self.derive(measures, radius), dtype=np.float64)


def _omnivariance(q, r):
    s = q.eigensum
    return np.cbrt((q.l1 / s) * (q.l2 / s) * (q.l3 / s))


def _eigenentropy(q, r):
    s = q.eigensum
    v = np.zeros(len(s))
    for lam in (q.l1, q.l2, q.l3):
        e = lam / s
        pos = e > 0.0  # 0 ln 0 := 0
        v -= np.where(pos, e * np.log(np.where(pos, e, 1.0)), 0.0)
    return np.where(np.isnan(s), np.nan, v)


def _echo_ratio(q, r):
    return np.where(q.ncyl > 0, 100.0 * q.n / np.maximum(q.ncyl, 1), np.nan)


CATEGORIES = ("eigen", "normal", "density", "height", "surface")


def _entry(name, category, needs, derive, compiled=None):
    unknown = set(needs.split()) - set(MEASURES)
    if unknown or category not in CATEGORIES:
        raise ValueError(f"feature {name}: category {category!r}, measures {needs!r}; "
                         f"known: {CATEGORIES}, {tuple(MEASURES)}")
    return Feature(name, category, frozenset(needs.split()), derive, compiled)


# q: the Measures, r: the radius asked for. In FEATURES order: a new feature goes at the end.
_ENTRIES = (
    _entry("linearity", "eigen", "eigen", lambda q, r: (q.l1 - q.l2) / q.l1, compiled=0),
    _entry("planarity", "eigen", "eigen", lambda q, r: (q.l2 - q.l3) / q.l1, compiled=1),
    _entry("omnivariance", "eigen", "eigen", _omnivariance, compiled=5),
    _entry("surface_variation", "eigen", "eigen", lambda q, r: q.l3 / q.eigensum, compiled=4),
    _entry("curvature", "surface", "curvature", lambda q, r: q.curv),
    _entry("point_density", "density", "cylinder", lambda q, r: q.ncyl / (math.pi * r ** 2)),
    _entry("num_neighbours", "density", "count", lambda q, r: q.n),
    _entry("surface_density", "density", "count", lambda q, r: q.n / (math.pi * r ** 2)),
    _entry("volume_density", "density", "count", lambda q, r: q.n / (4.0 / 3.0 * math.pi * r ** 3)),
    _entry("sphericity", "eigen", "eigen", lambda q, r: q.l3 / q.l1, compiled=2),
    _entry("verticality", "normal", "normal", lambda q, r: 1.0 - np.abs(q.normal[:, 2])),
    _entry("eigenentropy", "eigen", "eigen", _eigenentropy, compiled=6),
    _entry("anisotropy", "eigen", "eigen", lambda q, r: (q.l1 - q.l3) / q.l1, compiled=3),
    _entry("eigenvalue1", "eigen", "eigen", lambda q, r: q.l1.copy()),
    _entry("eigenvalue2", "eigen", "eigen", lambda q, r: q.l2.copy()),
    _entry("eigenvalue3", "eigen", "eigen", lambda q, r: q.l3.copy()),
    _entry("eigenvalue_sum", "eigen", "eigen", lambda q, r: q.eigensum, compiled=7),
    _entry("roughness", "surface", "roughness", lambda q, r: q.rough),
    _entry("z_rank", "height", "z", lambda q, r: q.zrank),
    _entry("z_range", "height", "z", lambda q, r: q.zrange),
    _entry("normal_x", "normal", "normal", lambda q, r: q.normal[:, 0].copy()),
    _entry("normal_y", "normal", "normal", lambda q, r: q.normal[:, 1].copy()),
    _entry("normal_z", "normal", "normal", lambda q, r: q.normal[:, 2].copy()),
    _entry("echo_ratio", "density", "count cylinder", _echo_ratio),
)
REGISTRY: dict[str, Feature] = {f.name: f for f in _ENTRIES}
FEATURES = tuple(REGISTRY)
# what the damage pipeline computes by default: the paper's robust set plus curvature (the
# changed/unchanged split needs it)
DEFAULT_PIPELINE_FEATURES = (
    "planarity", "surface_variation", "point_density", "num_neighbours", "surface_density",
    "volume_density", "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z", "curvature",
)


def needs(names) -> frozenset:
    """The measures the features `names` need."""
    return frozenset().union(*(REGISTRY[f].needs for f in names))


def kernel_switches(names) -> tuple:
    """(do_eig, do_rough, do_z, do_curv, do_cyl) for the features `names`."""
    on = {MEASURES[m] for m in needs(names)}
    return tuple(s in on for s in KERNEL_SWITCHES)


class FeatureError(QuakeScanError):
    """Features cannot be computed as asked (bad radius, names or coordinates)."""


def _check(xyz, radius, features, core_points, query_index):
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise FeatureError(f"xyz must be an (n, 3) array, got shape {xyz.shape}")
    if not np.all(np.isfinite(xyz)):
        raise FeatureError("xyz holds NaN or inf coordinates; drop those points first")
    if not (isinstance(radius, (int, float, np.floating)) and math.isfinite(radius) and radius > 0):
        raise FeatureError(f"radius must be a positive number of metres, got {radius!r}")
    names = FEATURES if features is None else tuple(features)
    unknown = [f for f in names if f not in REGISTRY]
    if unknown:
        raise FeatureError(f"unknown features {unknown}; known: {', '.join(FEATURES)}")
    if core_points is not None:
        core_points = np.asarray(core_points, dtype=np.float64)
        if core_points.ndim != 2 or core_points.shape[1] != 3 or not np.all(np.isfinite(core_points)):
            raise FeatureError(f"core_points must be a finite (m, 3) array, got shape {core_points.shape}")
    n = len(xyz)
    if query_index is not None:
        if core_points is not None:
            raise FeatureError("give core_points or query_index, not both")
        query_index = np.asarray(query_index, dtype=np.int64)
        if query_index.ndim != 1 or (len(query_index) and (query_index.min() < 0 or query_index.max() >= n)):
            raise FeatureError(f"query_index must index the {n} points of the cloud")
    return xyz, float(radius), names, core_points, query_index


def _query_count(xyz, core_points, query_index) -> int:
    if query_index is not None:
        return len(query_index)
    return len(xyz) if core_points is None else len(core_points)


def _evaluate(names, radius, measures: Measures) -> dict[str, np.ndarray]:
    """Every feature from its numpy definition, in the order asked."""
    return {f: REGISTRY[f].value(measures, radius) for f in names}


def _derive(names, radius, measures: Measures) -> dict[str, np.ndarray]:
    """The features from the kernel's measures: those with a compiled code in one parallel
    pass, the others from their definition. The compiled ones come first, by code: the
    dict's order has always been so, and the change descriptors are listed in it."""
    compiled = sorted((REGISTRY[f] for f in set(names) if REGISTRY[f].compiled is not None),
                      key=lambda f: f.compiled)
    out = {}
    if compiled:
        from . import _feature_kernels as K

        arr = np.empty((len(compiled), len(measures.count)))
        K.eigen_features(np.ascontiguousarray(measures.lam), np.array([f.compiled for f in compiled], np.int64),
                         arr)
        out.update(zip((f.name for f in compiled), arr))
    for f in names:
        if f not in out:
            out[f] = REGISTRY[f].value(measures, radius)
    return out


# Neighbours are the points with |p - q| <= r (1 + RADIUS_TOLERANCE). On the millimetre grid
# of LAS files many points lie at exactly r from a query; the same points in a local frame
# and at UTM coordinates differ by ~1e-10 m of rounding, which would flip such ties in or
# out. The next distance a mm grid allows beyond r is ~1e-6 relative away, so 1e-9 keeps
# every tie inside in any frame and admits nothing else.
RADIUS_TOLERANCE = 1e-9
CELLS_PER_RADIUS = 3  # grid columns of side r/3: 1.45x the sphere's points tested (side r: 2.5x)
_BLOCK = 8  # query groups per prange block (blocks are interleaved over the threads)
PROGRESS_STEPS = 50  # kernel calls when progress is reported (each call a 2 % share of the query groups)


def _kernel_measures(cloud, query, radius, names, workers, cells_per_radius=None, stats=None, query_index=None,
                     progress=None) -> Measures:
    """What the features `names` need, by the numba kernel. cloud: (x, y, z) contiguous
    arrays in the local frame (z >= 0); query: the same for core points, or None for the
    cloud's own points (all of them, or those in `query_index`)."""
    from numba import get_num_threads

    from ..runtime.workers import kernel_threads
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

    with kernel_threads(workers):  # for the sort and the kernel
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
        do_eig, do_rough, do_z, do_curv, do_cyl = kernel_switches(names)
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
    if stats is not None:
        stats["exact_share"] = float(nexact.mean()) if m else 0.0
        stats["groups"] = len(gcol)
    nan1 = np.full(m, np.nan)
    return Measures(count, lam if do_mom else np.full((m, 3), np.nan), normal if do_mom else np.full((m, 3), np.nan),
                    rough if do_rough else nan1, zrank if do_z else nan1, zrange if do_z else nan1,
                    curv if do_curv else nan1, ncyl.astype(np.float64) if do_cyl else None)


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


# A few coincident points (34 among 8.6 M of a real-sized scan) cost nothing; a stack of
# thousands makes the neighbour kernels quadratic in it. Grouping costs two sorts of every
# point (5 s for 8.6 M), so the kernels group only when some position holds this many copies.
STACK_COPIES = 64


def duplicate_groups(xyz, min_copies: int = 2):
    """(first, inverse) when some point of `xyz` has at least `min_copies` exact copies
    (itself included): `first` indexes one point of each distinct position,
    xyz[first][inverse] == xyz. None otherwise (the common case, all distinct: one hash and
    one sort of the keys)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    keys = position_keys(xyz)
    ks = np.sort(keys)  # a plain sort is 6x faster than the argsort below, which only duplicates need
    same = ks[1:] == ks[:-1]
    if not same.any():
        return None
    if min_copies > 2:
        edges = np.flatnonzero(np.diff(np.concatenate([[0], same.view(np.int8), [0]])))
        if (edges[1::2] - edges[0::2]).max() + 1 < min_copies:  # runs of equal keys, + their first
            return None
    order = np.argsort(keys, kind="stable")  # the stable sort leaves `ks` (and so `same`) as they are
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
                     workers: int = -1, query_index=None, progress: ProgressCallback | None = None
                     ) -> dict[str, np.ndarray]:
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
        Threads for the compiled kernel (default -1: every core, all of numba's; None as -1). Load is balanced by
        handing the threads interleaved blocks of query groups.
    progress : quakescan.runtime.progress.ProgressCallback, optional
        Called as progress(points_done, points_total) about 50 times; the results are the
        same with and without it.

    Returns
    -------
    dict of str -> (n,) or (m,) float64
        One array per requested feature, NaN where the degenerate rule of the module says so.
        `quakescan.change._feature_reference.reference_features` computes the same with plain numpy.
    """
    xyz, radius, names, core_points, query_index = _check(xyz, radius, features, core_points, query_index)
    m = _query_count(xyz, core_points, query_index)
    if m == 0 or len(xyz) == 0:
        return _evaluate(names, radius, Measures.undefined(m))
    if m > 1:
        # Coincident query points have one neighbourhood: computed once. Without this the
        # kernel is quadratic in the duplicates (200 000 copies of one point: hours).
        qpts = core_points if core_points is not None else (xyz if query_index is None else xyz[query_index])
        groups = duplicate_groups(qpts, STACK_COPIES)
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
    from ..grid.cells import row_bounds

    origin = row_bounds(xyz)[0]
    cols = [np.ascontiguousarray(xyz[:, k] - origin[k]) for k in range(3)]
    query = None if core_points is None else [np.ascontiguousarray(core_points[:, k] - origin[k]) for k in range(3)]
    measures = _kernel_measures(cols, query, radius * (1.0 + RADIUS_TOLERANCE), names, workers,
                                query_index=query_index, progress=progress)
    return _derive(names, radius, measures)
