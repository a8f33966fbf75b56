"""Surface change with its own level of detection: M3C2 on core points (Lague et al. 2013).

A point-to-point height difference is not a surface change: on a pitched roof sampled at
7 pts/m² the nearest post-event point 0.3 m away is 0.3 m higher or lower although
nothing moved. M3C2 compares the two epochs' *surfaces* instead:

1. at a core point c with surface normal n (PCA of the pre-event points within
   `normal_radius_m`), both epochs' points inside a cylinder of radius r around the axis
   c + t·n, |t| <= `max_depth_m`, are projected on the axis;
2. the change is the difference of their positions along the axis, d = m_post − m_pre, with
   m the median of the projections (default: at building edges and corners a cylinder also
   catches a little of the neighbouring wall, roof or ground, and two samplings catch
   different amounts of it; the median follows the surface the core lies on) or their mean
   (Lague et al.'s original, `statistic="mean"`);
3. its level of detection at 95 % confidence is
   LoD = t · e · sqrt(s_pre²/n_pre + s_post²/n_post) + 1.96 · reg,
   s the spread of the projections (1.4826 × median absolute deviation, or the standard
   deviation: surface roughness, noise and misfit of the local plane together), n the
   number of points the statistic is taken from (medians: at most `sample` per cylinder),
   e = sqrt(π/2) for medians (their scatter relative to means) and 1 for means, reg the
   registration error between the epochs, and t Student's quantile for the Welch–Satterthwaite
   degrees of freedom of the two spreads (1.96 for many points; larger where a sparse
   epoch's handful of points gives an uncertain spread, Lague et al.'s normal quantile would
   flag far more than 5 % of an unchanged surface there). |d| > LoD is a significant change. On an unchanged surface a 95 % test
   flags ~5 % of the core points by construction, so a building-level decision must look
   for a share clearly above that and for spatially coherent change, not for any flag.

Where the post-event cylinder holds no point while the pre-event one does, the surface
moved farther than `max_depth_m` or vanished (a hole, a collapsed roof): `lost`; or the
post-event flight did not observe it. `seen_through` (points behind the surface) and
`lost_beyond_chance` (the count an unchanged surface would have had) tell the two apart. The cylinder radius grows with the sparser epoch's spacing so that a cylinder
holds at least `min_points` points of it on a plane (`cylinder_radius`).

`curvature_lod` gives the same kind of level of detection for the change of the mean
curvature (`quakescan.change.features` "curvature") from the neighbourhood's eigenvalues: for a
least-squares quadric over N points spread uniformly on a disc of radius R with noise σ
along the normal, Var(H) = 48 σ² / (N R⁴); with λ1 = λ2 = R²/4 and λ3 = σ² this is
3 λ3 / (N λ1 λ2), which holds for any neighbourhood in terms of its own eigenvalues.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..errors import QuakeScanError

Z95 = 1.96


class M3C2Error(QuakeScanError):
    """M3C2 cannot run as asked (bad parameters or inputs)."""


@dataclass(frozen=True)
class M3C2Settings:
    """Cylinder and detection settings; every length in metres."""

    cylinder_radius_m: float = 0.5  # smallest radius; grown for sparse epochs (cylinder_radius)
    min_points: int = 10  # expected points of the sparser epoch in a cylinder on a plane
    min_comparable: int = 4  # fewer points in either cylinder: no distance (its spread is unknown)
    normal_radius_m: float = 1.5
    max_depth_m: float = 2.0  # half length of the cylinder: changes beyond it are "lost"
    # how far behind the surface (along -normal) the post-event epoch is searched for points
    # that show the surface is gone (see `M3C2Result.lost`)
    see_through_m: float = 30.0
    registration_error_m: float = 0.0
    z: float = Z95
    # "median": median and 1.4826 x MAD of the projections (robust to the other surfaces a
    # cylinder catches at edges and corners); "mean": mean and standard deviation (Lague et al.)
    statistic: str = "median"
    sample: int = 32  # median mode: projections per cylinder the statistics are taken from
    near_m: float = 0.15  # "still there": points within this distance of the core point (`displaced`)
    # a surface counts as displaced only where so few post-event points near it are unlikely by
    # chance (binomial lower tail below this; `M3C2Result.displaced`); 0 = the fixed share rule
    # alone, which a model file without the setting asks for (`M3C2Settings.from_json`)
    displaced_alpha: float = 0.01

    def __post_init__(self):
        if self.statistic not in ("median", "mean"):
            raise M3C2Error(f"M3C2 statistic must be 'median' or 'mean', got {self.statistic!r}")
        if not (isinstance(self.sample, int) and self.sample >= 8):
            raise M3C2Error(f"M3C2 sample must be an integer >= 8, got {self.sample!r}")
        for name in ("cylinder_radius_m", "normal_radius_m", "max_depth_m", "z", "see_through_m", "near_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise M3C2Error(f"M3C2 {name} must be a positive number, got {v!r}")
        if not (isinstance(self.displaced_alpha, (int, float)) and 0.0 <= self.displaced_alpha < 1.0):
            raise M3C2Error(f"M3C2 displaced_alpha must be in [0, 1), got {self.displaced_alpha!r}")
        if not (math.isfinite(self.registration_error_m) and self.registration_error_m >= 0):
            raise M3C2Error(f"M3C2 registration_error_m must be >= 0, got {self.registration_error_m!r}")
        for name in ("min_points", "min_comparable"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 2):
                raise M3C2Error(f"M3C2 {name} must be an integer >= 2, got {v!r}")

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> M3C2Settings:
        """Settings as stored (in a model or a training-set record); keys added later take the
        values the versions before them used."""
        d = dict(d)
        d.setdefault("displaced_alpha", 0.0)
        return cls(**d)


@dataclass
class M3C2Result:
    distance: np.ndarray  # (m,) mean_post - mean_pre along the normal; NaN where not comparable
    lod: np.ndarray  # (m,) level of detection; NaN where not comparable
    n_pre: np.ndarray  # (m,) points in the pre-event cylinder
    n_post: np.ndarray
    std_pre: np.ndarray  # (m,) sample standard deviation along the normal (NaN for n < 2)
    std_post: np.ndarray
    radius_m: float
    min_comparable: int = 2
    behind_post: np.ndarray | None = None  # (m,) post-event points behind the surface (see `lost`)
    near_pre: np.ndarray | None = None  # (m,) points within near_m of the core point, per epoch
    near_post: np.ndarray | None = None
    displaced_alpha: float = 0.0  # see `displaced`

    @property
    def displaced(self) -> np.ndarray:
        """`significant` where the pre-event surface itself is gone from the cylinder: the share
        of post-event points within near_m of the core point is below a quarter of the
        pre-event share. At edges and steps a cylinder holds two surfaces, and two samplings
        weight them differently, so their medians differ by the step although both surfaces
        are still there; a surface that really moved leaves nothing where it was.

        With `displaced_alpha` > 0 the few near points must also be unlikely by chance: an
        unchanged surface puts Binomial(n_post, pre-event share) of the post-event cylinder's
        points near the core point, and a sparse epoch's handful of points misses it often (a
        25 % thinning of an AHN3 tile: 10 points in a cylinder straddling a roof step, 5
        expected near the upper roof, 1 or none found 4 % of the time). Dense epochs decide as
        before: there the share rule is far stricter than the test."""
        if self.near_pre is None or self.near_post is None:
            return self.significant
        with np.errstate(invalid="ignore", divide="ignore"):
            share_pre = self.near_pre / np.maximum(self.n_pre, 1)
            share_post = self.near_post / np.maximum(self.n_post, 1)
        out = self.significant & (share_post < 0.25 * share_pre)
        if self.displaced_alpha > 0 and out.any():
            from scipy.stats import binom

            i = np.flatnonzero(out)
            tail = binom.cdf(self.near_post[i], self.n_post[i], np.clip(share_pre[i], 0.0, 1.0))
            out[i] = tail < self.displaced_alpha
        return out

    @property
    def comparable(self) -> np.ndarray:
        """Both cylinders hold at least `min_comparable` points: distance and LoD defined."""
        return (self.n_pre >= self.min_comparable) & (self.n_post >= self.min_comparable)

    @property
    def significant(self) -> np.ndarray:
        return self.comparable & (np.abs(np.nan_to_num(self.distance)) > np.nan_to_num(self.lod, nan=np.inf))

    @property
    def lost(self) -> np.ndarray:
        """The pre-event surface has no post-event counterpart within max_depth_m."""
        return (self.n_pre >= self.min_comparable) & (self.n_post == 0)

    @property
    def seen_through(self) -> np.ndarray:
        """The post-event epoch has points *behind* the surface (along −normal, beyond
        max_depth_m up to see_through_m): the floor below a roof hole, the rubble below a
        collapsed roof. Where a lost surface has nothing behind it either, it may simply not
        have been observed (occlusion, another flight direction)."""
        if self.behind_post is None:
            return np.ones(len(self.n_post), bool)
        return self.behind_post > 0

    def lost_beyond_chance(self, density_ratio, alpha: float = 0.05) -> np.ndarray:
        """`lost` where an empty post-event cylinder is unlikely by chance: with the epochs'
        density ratio (post/pre, a number or one per core point) an unchanged surface puts a
        Poisson number of mean λ = n_pre · ratio points in it, and P(0) = exp(−λ) must be
        below `alpha` (λ >= 3 at 5 %). A sparse post-event epoch, or a facade the post-event
        flight hardly sees, does not make surfaces 'lost'."""
        expected = self.n_pre * np.asarray(density_ratio, dtype=np.float64)
        return self.lost & (expected >= -math.log(alpha))

    @property
    def unseen(self) -> np.ndarray:
        """Neither comparable nor lost-and-seen-through."""
        return ~self.comparable & ~(self.lost & self.seen_through)


MAD_EFFICIENCY = 0.37  # the median absolute deviation estimates a normal spread like a std from 0.37 n points


def _critical_value(z: float, v1, v2, n1, n2, median: bool):
    """Student's t quantile at the confidence of `z` with Welch–Satterthwaite degrees of freedom:
    a spread estimated from a handful of points (a sparse epoch's cylinder holds 5–10) is
    itself uncertain, and the normal quantile would flag far more than 5 % of an unchanged
    surface. A robust spread (MAD) carries less information than a standard deviation from
    the same points, so its degrees of freedom are scaled by its efficiency."""
    from scipy.stats import norm, t

    q = float(norm.cdf(z))
    scale = MAD_EFFICIENCY if median else 1.0
    d1 = np.maximum(scale * (np.asarray(n1, np.float64) - 1), 1.0)
    d2 = np.maximum(scale * (np.asarray(n2, np.float64) - 1), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        df = (v1 + v2) ** 2 / (v1 ** 2 / d1 + v2 ** 2 / d2)
    df = np.where(np.isfinite(df) & (df > 0), df, np.minimum(d1, d2))
    return t.ppf(q, np.maximum(df, 1.0))


def cylinder_radius(settings: M3C2Settings, sparser_density_pts_m2: float) -> float:
    """Radius at which a cylinder on a plane holds `min_points` points of the sparser epoch."""
    if not (math.isfinite(sparser_density_pts_m2) and sparser_density_pts_m2 > 0):
        return settings.cylinder_radius_m
    return max(settings.cylinder_radius_m, math.sqrt(settings.min_points / (math.pi * sparser_density_pts_m2)))


@dataclass
class CylinderStats:
    """Per cylinder: points within the half length, the median and robust spread (1.4826 MAD)
    of their projections on the axis (from a sample), the points behind it (-behind_length ..
    -half_length), those within near_length of the centre, and the mean and population
    variance of all projections."""

    count: np.ndarray
    median: np.ndarray
    spread: np.ndarray
    behind: np.ndarray
    near: np.ndarray
    mean: np.ndarray
    var: np.ndarray


class ColumnGrid:
    """Points bucketed in x/y columns sorted by z, for cylinder queries (built once per epoch)."""

    def __init__(self, xyz: np.ndarray, cell: float):
        from . import _nn_kernels as K

        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        self.n = len(xyz)
        if self.n == 0:
            self.lo = np.zeros(2)
            self.cell, self.nx, self.ny = float(cell), 1, 1
            self.starts = np.zeros(2, np.int64)
            self.px = self.py = self.pz = np.zeros(0)
            return
        from ..grid.cells import row_bounds

        lo, hi = row_bounds(xyz[:, :2])
        span = np.maximum(hi - lo, 1e-9)
        cell = float(cell)
        nx, ny = int(span[0] // cell) + 1, int(span[1] // cell) + 1
        while nx * ny > 4 * self.n + 1024:  # sparse, far-flung points: keep the column table small
            cell *= 2
            nx, ny = int(span[0] // cell) + 1, int(span[1] // cell) + 1
        order, starts = K.counting_sort(K.column_index(xyz, lo[0], lo[1], cell, nx, ny), nx * ny)
        self.px, self.py, self.pz = K.sort_columns_by_z(order, starts, xyz)
        self.lo, self.cell, self.nx, self.ny, self.starts = lo, cell, nx, ny, starts

    def cylinders(self, centres, axes, radius, half_length, behind_length=0.0, sample: int = 32,
                  chunk: int = 200_000, near_length: float = 0.0) -> CylinderStats:
        """Statistics of the projections on the axis per cylinder (`CylinderStats`)."""
        from . import _m3c2_kernels as K

        m = len(centres)
        count = np.zeros(m, np.int64)
        behind = np.zeros(m, np.int64)
        near = np.zeros(m, np.int64)
        median, spread, mean, var = (np.full(m, np.nan) for _ in range(4))
        if m == 0 or self.n == 0:
            return CylinderStats(count, median, spread, behind, near, mean, var)
        c = np.ascontiguousarray(centres, dtype=np.float64)
        a = np.ascontiguousarray(axes, dtype=np.float64)
        r = np.broadcast_to(np.asarray(radius, np.float64), (m,)).copy()
        h = np.broadcast_to(np.asarray(half_length, np.float64), (m,)).copy()
        hb = np.broadcast_to(np.asarray(behind_length, np.float64), (m,)).copy()
        hn = np.broadcast_to(np.asarray(near_length, np.float64), (m,)).copy()
        for s0 in range(0, m, chunk):  # bounded memory for the samples
            sl = slice(s0, min(m, s0 + chunk))
            buf = np.empty((sl.stop - sl.start, sample))
            K.cylinder_robust(c[sl, 0].copy(), c[sl, 1].copy(), c[sl, 2].copy(), a[sl, 0].copy(), a[sl, 1].copy(),
                              a[sl, 2].copy(), r[sl], h[sl], hb[sl], hn[sl], self.px, self.py, self.pz, self.starts,
                              self.lo[0], self.lo[1], self.cell, self.nx, self.ny, buf, count[sl], median[sl],
                              spread[sl], behind[sl], near[sl], mean[sl], var[sl])
        return CylinderStats(count, median, spread, behind, near, mean, var)


def _check_inputs(core, normals):
    core = np.asarray(core, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if core.ndim != 2 or core.shape[1] != 3 or normals.shape != core.shape:
        raise M3C2Error(f"core points and normals must be (m, 3) arrays of one shape, got {core.shape} "
                        f"and {normals.shape}")
    if not np.all(np.isfinite(core)):
        raise M3C2Error("core points hold NaN or inf coordinates")
    return core, normals


def m3c2(core, normals, pre: ColumnGrid, post: ColumnGrid, settings: M3C2Settings,
         radius_m: float | None = None, student: bool = True) -> M3C2Result:
    """Distances and levels of detection at the core points (all in one local frame).
    `student=False` uses the normal quantile `settings.z` (Lague et al., py4dgeo) instead of
    Student's for the spreads' degrees of freedom.

    Core points whose normal is undefined (NaN: a degenerate neighbourhood) are not
    comparable: their distance and LoD are NaN and they are neither significant nor lost."""
    core, normals = _check_inputs(core, normals)
    r = settings.cylinder_radius_m if radius_m is None else float(radius_m)
    if not (math.isfinite(r) and r > 0):
        raise M3C2Error(f"cylinder radius must be a positive number of metres, got {radius_m!r}")
    ok = np.all(np.isfinite(normals), axis=1)
    m = len(core)
    n1 = np.zeros(m, np.int64)
    n2 = np.zeros(m, np.int64)
    behind = np.zeros(m, np.int64)
    near1 = np.zeros(m, np.int64)
    near2 = np.zeros(m, np.int64)
    loc1, s1, loc2, s2 = (np.full(m, np.nan) for _ in range(4))
    if ok.any():
        c, a = core[ok], normals[ok] / np.linalg.norm(normals[ok], axis=1, keepdims=True)
        one = pre.cylinders(c, a, r, settings.max_depth_m, 0.0, settings.sample, near_length=settings.near_m)
        two = post.cylinders(c, a, r, settings.max_depth_m, settings.see_through_m, settings.sample,
                             near_length=settings.near_m)
        n1[ok], near1[ok], n2[ok], near2[ok], behind[ok] = one.count, one.near, two.count, two.near, two.behind
        if settings.statistic == "median":
            loc1[ok], s1[ok], loc2[ok], s2[ok] = one.median, one.spread, two.median, two.spread
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                loc1[ok], s1[ok] = one.mean, np.sqrt(one.var * one.count / np.maximum(one.count - 1, 1))
                loc2[ok], s2[ok] = two.mean, np.sqrt(two.var * two.count / np.maximum(two.count - 1, 1))
    # the median of n normal values scatters sqrt(pi / 2) times as much as their mean, and it is
    # taken from a sample of at most `sample` of them
    median = settings.statistic == "median"
    efficiency = math.sqrt(math.pi / 2) if median else 1.0
    m1 = np.minimum(n1, settings.sample) if median else n1
    m2 = np.minimum(n2, settings.sample) if median else n2
    with np.errstate(invalid="ignore", divide="ignore"):
        s1 = np.where(n1 >= 2, s1, np.nan)
        s2 = np.where(n2 >= 2, s2, np.nan)
        k = settings.min_comparable
        comparable = (n1 >= k) & (n2 >= k)
        distance = np.where(comparable, loc2 - loc1, np.nan)
        v1, v2 = s1 ** 2 / m1, s2 ** 2 / m2
        factor = _critical_value(settings.z, v1, v2, m1, m2, median) if student else settings.z
        lod = np.where(comparable, factor * efficiency * np.sqrt(v1 + v2)
                       + settings.z * settings.registration_error_m, np.nan)
    return M3C2Result(distance, lod, n1, n2, s1, s2, r, k, behind, near1, near2, settings.displaced_alpha)


def voxel_core_points(xyz: np.ndarray, spacing_m: float) -> np.ndarray:
    """Indices of one point per occupied cubic voxel (the one nearest the voxel's centre, ties
    to the lower index), sorted: core points spread evenly over the surface whatever the
    density, so shares over core points are shares of surface area."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise M3C2Error(f"core point spacing must be a positive number of metres, got {spacing_m!r}")
    from ..grid.cells import row_bounds

    lo = row_bounds(xyz)[0]
    ijk = np.floor((xyz - lo) / spacing_m).astype(np.int64)
    dims = row_bounds(ijk)[1] + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    off = np.sum((xyz - lo - (ijk + 0.5) * spacing_m) ** 2, axis=1)
    order = np.lexsort((np.arange(len(xyz)), off, key))
    first = np.ones(len(order), bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    return np.sort(order[first])


def orient_normals(normals: np.ndarray, xy: np.ndarray, centre_xy: np.ndarray, vertical_below: float = 0.5):
    """Normals of `quakescan.change.features` point up (n_z >= 0); on walls (|n_z| < vertical_below) that
    sign is arbitrary, so there they are turned to point away from the building's centre:
    a wall that falls outwards or inwards then gives a distance of a known sign."""
    n = np.array(normals, dtype=np.float64, copy=True)
    wall = np.abs(n[:, 2]) < vertical_below
    out = (xy - np.asarray(centre_xy)[None, :])
    flip = wall & (np.einsum("ij,ij->i", n[:, :2], out) < 0)
    n[flip] *= -1.0
    return n


def curvature_standard_error(lam1, lam2, lam3, count):
    """Standard error of the mean curvature fitted to a neighbourhood (1/m), from its
    eigenvalues (m², population covariance) and point count: sqrt(3 λ3 / (N λ1 λ2)).
    NaN where the neighbourhood is degenerate (N < 6 or λ2 = 0)."""
    lam1, lam2, lam3 = (np.asarray(v, dtype=np.float64) for v in (lam1, lam2, lam3))
    n = np.asarray(count, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.sqrt(3.0 * np.maximum(lam3, 0.0) / (n * lam1 * lam2))
    return np.where((n >= 6) & (lam2 > 0) & np.isfinite(se), se, np.nan)


def curvature_lod(se_pre, se_post, z: float = Z95):
    """Level of detection of a change of curvature between two neighbourhoods."""
    return z * np.sqrt(np.asarray(se_pre) ** 2 + np.asarray(se_post) ** 2)
