"""Robust change-feature selection (Zahs et al., "Object-specific change feature selection").

The experiment: geometric features are computed per point at neighbourhood radii 1.0-4.0 m
(step 0.5); the relative change of every feature between a pre- and a post-event epoch is
measured on laser scanning (ULS) and on photogrammetric (DIM) clouds of the same buildings;
a feature is robust when its relative change differs by at most THRESHOLD_PCT percentage
points between ULS and DIM; the radius where the two agree best is selected.

    >>> res = robustness(uls_pre, uls_post, dim_pre, dim_post, radii=(1.0, 2.0))
    >>> res.best_radius, res.robust
    >>> write_report(res, "out/robustness")  # quakescan.studies.robustness.report
    >>> # the paper's design: two demolition stages, every cloud thinned to 0.1 m
    >>> res = robustness(uls_pre, [uls_s1, uls_s2], dim_pre, [dim_s1, dim_s2], spacing=0.1)
    >>> res.stage_robust_at("post1", res.best_radius), quiet_features(res)

Definitions (the choices this module makes; the paper does not spell them out)
    Pairing: as in the paper, the change of a feature at a pre-event building point
        (building_id > 0) is taken against the nearest point of the post-event cloud (the
        whole post cloud: a collapsed roof maps onto debris or ground). Features use the
        whole cloud of each epoch for the neighbourhoods (ground included). At most
        `sample` pre building points are used (a seeded random subset; default
        DEFAULT_SAMPLE), which keeps the 4 m radius affordable; the medians are stable long
        before that.
    Relative change of a feature f, in %:
        100 * (median_post - median_pre) / scale_f
        median_pre over f at the pre building points, median_post over f at their nearest
        post points, both over the same pairs: pairs where either value is NaN (degenerate
        neighbourhood, see quakescan.change.features) are dropped. The median, not the mean, because
        roughness, curvature and the eigenvalues have heavy tails at edges.
    Scale (near-zero features): scale_f = |median_pre|, unless |median_pre| is below
        NEAR_ZERO (0.1) x the pre-event interquartile range IQR_pre of f: then scale_f =
        IQR_pre. Features centred at 0 (e.g. sphericity or eigenvalue3 on planar roofs,
        curvature) would otherwise give arbitrarily large percentages for tiny absolute
        changes. If the scale is 0 too (a constant feature), the relative change is 0 when
        the medians agree and NaN (never robust) otherwise.
    Normal vector: normal_x/y/z are one feature, "normal_vector" (the paper lists "the
        normal vector"). Its change at a pair is the angle between the pre and the post
        normal, arccos |n_pre . n_post| in [0, 90] degrees (sign-free: normals are oriented
        only up to sign); its relative change is 100 * median angle / 90 degrees (0 %
        unchanged orientation, 100 % every normal turned perpendicular).
    Difference: |relative change ULS - relative change DIM| in percentage points; NaN when
        either is NaN (such a feature is never robust).
    Stages: the paper compares one pre-event epoch with two demolition stages. Several
        post-event epochs ("stages") can be given; the relative changes and differences are
        computed per stage, against the same pre-event building points (same sample), and
        the difference of a feature at a radius is the LARGEST difference over the stages
        (NaN if it is NaN at any stage). So a feature is robust at a radius only when ULS and
        DIM agree within the threshold at every stage. RobustnessResult.uls/dim hold the
        relative changes at the stage that decides that maximum (`deciding_stage`), so
        difference = |uls - dim| holds throughout; the per-stage tables are in `stage_uls`,
        `stage_dim`, `stage_difference`. With one stage this is exactly the two-epoch design.
    Thinning (`spacing`, default none): before any feature, every cloud is thinned on a 3-D
        voxel grid of edge `spacing` (cells aligned to the local frame's origin, i.e.
        floor(xyz / spacing)), keeping ONE point per occupied cell, drawn at random with a
        seeded generator (seed, then seed + 1, + 2, ... for the clouds in the order ULS pre,
        ULS stages, DIM pre, DIM stages): the same inputs and seed give the same points. On
        a plane parallel to the grid this gives exactly 1 / spacing^2 points per m^2 where
        the input was denser (the paper thins to 0.1 m spacing, 100 pts/m^2); an inclined
        plane crossing two voxel layers per cell keeps up to twice that; a sparser input is
        left unchanged.
    Best radius: the radius with the most robust features at the threshold; ties go to the
        smallest mean difference over the features with a finite difference, then to the
        smallest radius.
    Pre-event values per surface (`pre_values`): at the best radius, the median and the
        interquartile range of every feature on the sampled pre-event ULS and DIM building
        points, split by the simulators' `surface` label (roof, wall), to see where the two
        sources differ before any change (e.g. the smallest eigenvalue).
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ...change.features import FEATURES, compute_features
from ...change.settings import PAPER_FEATURES
from ...errors import QuakeScanError
from ...formats.pointcloud import Epoch
from ...runtime.progress import ProgressCallback

log = logging.getLogger(__name__)

RADII = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
THRESHOLD_PCT = 10.0
THRESHOLDS = tuple(float(t) for t in range(51))  # counts_by_threshold: 0..50 % step 1
NORMAL = "normal_vector"
NORMAL_COMPONENTS = ("normal_x", "normal_y", "normal_z")
NEAR_ZERO = 0.1  # |median| below NEAR_ZERO x IQR: the IQR is the scale
DEFAULT_SAMPLE = 20_000
SURFACES = {1: "roof", 2: "wall"}  # quakescan.formats.pointcloud surface codes looked at in pre_values
PRE_VALUE_FEATURES = ("surface_variation", "eigenvalue3", "sphericity", "omnivariance", "roughness", "planarity",
                      "eigenvalue_sum", "curvature", "point_density", "num_neighbours")  # in the report's table
# All 24 per-point features with the normal's components as one feature: 22 names.
REPORT_FEATURES = tuple(f for f in FEATURES if f not in NORMAL_COMPONENTS) + (NORMAL,)
PAPER_SET = tuple(f for f in PAPER_FEATURES if f not in NORMAL_COMPONENTS) + (NORMAL,)


class RobustnessError(QuakeScanError):
    """The robustness experiment cannot run on its input (no building points, bad radii...)."""


def report_features(features: Sequence[str] | None = None) -> tuple[str, ...]:
    """Feature names as the experiment reports them: normal_x/y/z (any of them) become one
    "normal_vector"; order kept, duplicates dropped."""
    if features is None:
        return REPORT_FEATURES
    out: list[str] = []
    for f in features:
        name = NORMAL if f in NORMAL_COMPONENTS else f
        if name != NORMAL and name not in FEATURES:
            raise RobustnessError(f"unknown feature {f!r}; known: {', '.join(REPORT_FEATURES)}")
        if name not in out:
            out.append(name)
    if not out:
        raise RobustnessError("no features to compare")
    return tuple(out)


def _compute_names(names: Sequence[str]) -> tuple[str, ...]:
    out = []
    for f in names:
        out.extend(NORMAL_COMPONENTS if f == NORMAL else (f,))
    return tuple(out)


def _positive_metres(value, what: str) -> float:
    """A positive finite number of metres, or a RobustnessError naming `what` and the value."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise RobustnessError(f"{what} must be a number of metres, got {value!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise RobustnessError(f"{what} must be a positive number of metres, got {value!r}")
    return x


def check_spacing(spacing) -> float | None:
    """None, or a positive finite number of metres (RobustnessError naming the value)."""
    return None if spacing is None else _positive_metres(spacing, "spacing")


def thin_index(xyz: np.ndarray, spacing: float, seed: int = 0) -> np.ndarray:
    """Sorted indices of the points kept by voxel thinning (module doc): one point per occupied
    cell floor(xyz / spacing), drawn at random with `seed`."""
    s = check_spacing(spacing)
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(xyz / s).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0 ** 62:
        keys = np.ravel_multi_index(cells.T, dims)
    else:  # an enormous extent for the spacing: unique rows instead of one integer key
        keys = np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    perm = np.random.default_rng(seed).permutation(n)
    _, first = np.unique(keys[perm], return_index=True)  # the first of each cell in random order
    return np.sort(perm[first])


def _subset(epoch: Epoch, idx: np.ndarray) -> Epoch:
    def take(a):
        return None if a is None else a[idx]

    return Epoch(xyz=epoch.xyz[idx], origin=epoch.origin, classification=epoch.classification[idx],
                 building_id=take(epoch.building_id), grade=take(epoch.grade), surface=take(epoch.surface),
                 crs=epoch.crs, source=epoch.source)


def thin(epoch: Epoch, spacing: float | None, seed: int = 0) -> Epoch:
    """The epoch thinned to about `spacing` m (voxel grid, one random point per cell, seeded;
    module doc); every attribute kept for the kept points. spacing None: the epoch itself."""
    if check_spacing(spacing) is None:
        return epoch
    return _subset(epoch, thin_index(epoch.xyz, spacing, seed))


def _building_index(epoch: Epoch, role: str) -> np.ndarray:
    if len(epoch) == 0:
        raise RobustnessError(f"{epoch.source}: the {role} point cloud is empty")
    if epoch.building_id is None:
        raise RobustnessError(f"{epoch.source}: the {role} point cloud has no building_id attribute; "
                              "the experiment needs building points (building_id > 0)")
    idx = np.flatnonzero(epoch.building_id > 0)
    if len(idx) == 0:
        raise RobustnessError(f"{epoch.source}: the {role} point cloud has no building points (building_id > 0)")
    return idx


@dataclass
class _Pair:
    """Pre building points (maybe a sample) and their nearest post points."""

    pre: Epoch
    post: Epoch
    pre_idx: np.ndarray
    post_idx: np.ndarray  # nearest post point of each pre_idx


def _pair(pre: Epoch, post: Epoch, role: str = "", sample: int | None = DEFAULT_SAMPLE, seed: int = 0,
          workers: int = -1) -> _Pair:
    from ...change.split import nearest_neighbours

    tag = f"{role} " if role else ""
    idx = _building_index(pre, f"{tag}pre-event")
    _building_index(post, f"{tag}post-event")
    if sample is not None and len(idx) > sample:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(idx, size=int(sample), replace=False))
    nn, _ = nearest_neighbours(pre.xyz[idx], post.xyz, workers=-1 if workers is None else workers)
    return _Pair(pre, post, idx, nn)


def _scale(pre_vals: np.ndarray, med: float) -> float:
    q1, q3 = np.percentile(pre_vals, [25, 75])
    iqr = float(q3 - q1)
    return abs(med) if abs(med) >= NEAR_ZERO * iqr else iqr


def relative_change(pre_vals: np.ndarray, post_vals: np.ndarray) -> float:
    """Relative change in % of one feature over paired values (see the module doc): NaN pairs
    dropped; 100 (median post - median pre) / scale, scale |median pre| or, near 0, the IQR."""
    pre_vals = np.asarray(pre_vals, dtype=np.float64)
    post_vals = np.asarray(post_vals, dtype=np.float64)
    ok = np.isfinite(pre_vals) & np.isfinite(post_vals)
    if not ok.any():
        return math.nan
    a, b = pre_vals[ok], post_vals[ok]
    ma, mb = float(np.median(a)), float(np.median(b))
    diff = mb - ma
    scale = _scale(a, ma)
    if scale <= 0.0:
        return 0.0 if diff == 0.0 else math.nan
    return 100.0 * diff / scale


def normal_change(pre_n: np.ndarray, post_n: np.ndarray) -> float:
    """Relative change in % of the normal vector: 100 x median angle (deg) / 90 between
    paired unit normals (n, 3), sign-free; pairs with a NaN normal dropped."""
    ok = np.isfinite(pre_n).all(axis=1) & np.isfinite(post_n).all(axis=1)
    if not ok.any():
        return math.nan
    c = np.abs(np.einsum("ij,ij->i", pre_n[ok], post_n[ok]))
    ang = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    return 100.0 * float(np.median(ang)) / 90.0


def _post_values(post: Epoch, post_idx: np.ndarray, radius: float, comp, workers) -> dict[str, np.ndarray]:
    uniq, inv = np.unique(post_idx, return_inverse=True)
    fpost_u = compute_features(post.xyz, radius, comp, query_index=uniq, workers=workers)
    return {k: v[inv] for k, v in fpost_u.items()}


def _compare(fpre: dict, fpost: dict, names: Sequence[str]) -> dict[str, float]:
    out = {}
    for f in names:
        if f == NORMAL:
            out[f] = normal_change(np.column_stack([fpre[c] for c in NORMAL_COMPONENTS]),
                                   np.column_stack([fpost[c] for c in NORMAL_COMPONENTS]))
        else:
            out[f] = relative_change(fpre[f], fpost[f])
    return out


def _changes(pair: _Pair, radius: float, names: Sequence[str], workers: int | None) -> dict[str, float]:
    comp = _compute_names(names)
    fpre = compute_features(pair.pre.xyz, radius, comp, query_index=pair.pre_idx, workers=workers)
    return _compare(fpre, _post_values(pair.post, pair.post_idx, radius, comp, workers), names)


def _stage_changes(pairs: Sequence[_Pair], radius: float, names: Sequence[str], workers: int | None,
                   keep_pre: bool = False):
    """Relative changes per stage; the pairs share their pre epoch and pre points, whose
    features are computed once. With keep_pre also the pre features (dict of arrays)."""
    comp = _compute_names(names)
    p0 = pairs[0]
    fpre = compute_features(p0.pre.xyz, radius, comp, query_index=p0.pre_idx, workers=workers)
    out = [_compare(fpre, _post_values(p.post, p.post_idx, radius, comp, workers), names) for p in pairs]
    return (out, fpre) if keep_pre else out


def _check_radius(radius) -> float:
    return _positive_metres(radius, "radius")


def relative_changes(pre: Epoch, post: Epoch, radius: float, features: Sequence[str] | None = FEATURES,
                     workers: int = -1, sample: int | None = DEFAULT_SAMPLE,
                     seed: int = 0) -> dict[str, float]:
    """Relative change in % of each feature between two epochs (same local frame) over the
    pre-event building points and their nearest post-event points, at one radius.

    Keys as `report_features(features)` (normal_x/y/z -> "normal_vector"); see the module
    doc for the definitions. Raises RobustnessError naming the file when an epoch has no
    building points."""
    r = _check_radius(radius)
    names = report_features(features)
    return _changes(_pair(pre, post, sample=sample, seed=seed, workers=workers), r, names, workers)


@dataclass
class RobustnessResult:
    radii: list[float]
    features: list[str]
    uls: dict[float, dict[str, float]]  # radius -> feature -> relative change %
    dim: dict[float, dict[str, float]]
    difference: dict[float, dict[str, float]]  # radius -> feature -> |uls - dim| (percentage points)
    best_radius: float
    threshold_pct: float
    robust: list[str]  # at best_radius, difference <= threshold_pct
    counts_by_threshold: dict[float, int]  # threshold % -> robust features at best_radius
    points: dict[str, int] = field(default_factory=dict)  # pre building points used (uls, dim)
    wall_time_s: float = 0.0
    # several post-event epochs (module doc "Stages"); one stage "post" by default
    stages: list[str] = field(default_factory=lambda: ["post"])
    stage_uls: dict[str, dict[float, dict[str, float]]] = field(default_factory=dict)  # stage -> radius -> f
    stage_dim: dict[str, dict[float, dict[str, float]]] = field(default_factory=dict)
    stage_difference: dict[str, dict[float, dict[str, float]]] = field(default_factory=dict)
    deciding_stage: dict[float, dict[str, str]] = field(default_factory=dict)  # radius -> f -> stage of max
    spacing_m: float | None = None
    clouds: dict[str, dict] = field(default_factory=dict)  # cloud -> {points_in, points, building_spacing_m}
    # source -> surface -> feature -> {median, q1, q3, n}: pre-event values at the best radius
    pre_values: dict[str, dict[str, dict[str, dict[str, float]]]] = field(default_factory=dict)
    seed: int = 0
    sample: int | None = DEFAULT_SAMPLE

    def stage_robust_at(self, stage: str, radius: float, threshold_pct: float | None = None) -> list[str]:
        """Features whose ULS and DIM relative changes agree within the threshold at one stage."""
        t = self.threshold_pct if threshold_pct is None else threshold_pct
        d = self.stage_difference.get(stage, {}).get(radius) if self.stage_difference else None
        if d is None:
            d = self.difference[radius]
        return [f for f in self.features if within(d[f], t)]

    def robust_at(self, radius: float, threshold_pct: float | None = None) -> list[str]:
        t = self.threshold_pct if threshold_pct is None else threshold_pct
        d = self.difference[radius]
        return [f for f in self.features if within(d[f], t)]

    def mean_difference(self, radius: float) -> float:
        v = [x for x in self.difference[radius].values() if math.isfinite(x)]
        return float(np.mean(v)) if v else math.nan

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not math.isfinite(x) else round(float(x), 6)

        def table(t):
            return {f"{r:g}": {f: num(v) for f, v in t[r].items()} for r in self.radii}

        return {
            "radii_m": [float(r) for r in self.radii],
            "features": list(self.features),
            "threshold_pct": self.threshold_pct,
            "best_radius_m": self.best_radius,
            "robust": list(self.robust),
            "counts_by_threshold": {f"{t:g}": c for t, c in self.counts_by_threshold.items()},
            "robust_by_radius": {f"{r:g}": self.robust_at(r) for r in self.radii},
            "mean_difference_by_radius": {f"{r:g}": num(self.mean_difference(r)) for r in self.radii},
            "relative_change_uls_pct": table(self.uls),
            "relative_change_dim_pct": table(self.dim),
            "difference_pct_points": table(self.difference),
            "points": dict(self.points),
            "wall_time_s": round(self.wall_time_s, 3),
            "comparison_with_paper": compare_with_paper(self),
            "robust_without_change_seen": quiet_features(self),
            "spacing_m": self.spacing_m,
            "seed": self.seed,
            "sample": self.sample,
            "clouds": {k: {kk: (num(vv) if isinstance(vv, float) else vv) for kk, vv in v.items()}
                       for k, v in self.clouds.items()},
            "stages": list(self.stages),
            "deciding_stage": {f"{r:g}": dict(self.deciding_stage.get(r, {})) for r in self.radii},
            "per_stage": {st: {
                "relative_change_uls_pct": table(self.stage_uls[st]),
                "relative_change_dim_pct": table(self.stage_dim[st]),
                "difference_pct_points": table(self.stage_difference[st]),
                "robust_by_radius": {f"{r:g}": self.stage_robust_at(st, r) for r in self.radii},
            } for st in self.stages if st in self.stage_uls},
            "pre_values_at_best_radius": {src: {surf: {f: {k: num(v) if k != "n" else v for k, v in d.items()}
                                                       for f, d in fs.items()}
                                                for surf, fs in by.items()}
                                          for src, by in self.pre_values.items()},
        }


def within(x: float, t: float) -> bool:
    return x is not None and math.isfinite(x) and x <= t + 1e-9


def _stage_list(post, role: str) -> list[Epoch]:
    if isinstance(post, Epoch):
        return [post]
    posts = list(post)
    if not posts or not all(isinstance(p, Epoch) for p in posts):
        raise RobustnessError(f"{role}: expected a post-event Epoch or a non-empty sequence of Epochs")
    return posts


def _median_spacing(epoch: Epoch, workers) -> float:
    """Median distance from a building point to its nearest other building point."""
    from scipy.spatial import cKDTree

    if epoch.building_id is None:
        return math.nan
    b = epoch.xyz[epoch.building_id > 0]
    if len(b) < 2:
        return math.nan
    d, _ = cKDTree(b).query(b, k=2, workers=-1 if workers is None else workers)
    return float(np.median(d[:, 1]))


def _pre_values(epoch: Epoch, idx: np.ndarray, fpre: dict, names: Sequence[str]) -> dict:
    if epoch.surface is None:
        return {}
    surf = epoch.surface[idx]
    out = {}
    for code, label in SURFACES.items():
        m = surf == code
        by = {}
        for f in names:
            if f == NORMAL:
                continue
            v = fpre[f][m]
            v = v[np.isfinite(v)]
            if len(v) == 0:
                continue
            q1, med, q3 = np.percentile(v, [25, 50, 75])
            by[f] = {"median": float(med), "q1": float(q1), "q3": float(q3), "n": len(v)}
        if by:
            out[label] = by
    return out


def robustness(uls_pre: Epoch, uls_post, dim_pre: Epoch, dim_post,
               radii: Sequence[float] = RADII, threshold_pct: float = THRESHOLD_PCT,
               features: Sequence[str] | None = None, workers: int = -1, progress: ProgressCallback | None = None,
               sample: int | None = DEFAULT_SAMPLE, seed: int = 0, spacing: float | None = None,
               stage_names: Sequence[str] | None = None) -> RobustnessResult:
    """Relative change of every feature on the ULS pairs and on the DIM pairs at every radius,
    their difference, the best radius and the robust features (module doc). `uls_post` and
    `dim_post` are one post-event Epoch or equally long sequences of them (demolition
    stages, in order; `stage_names` labels them, default "post" or "post1", "post2", ...);
    the difference is the largest over the stages. `spacing` thins every cloud first.
    `progress` is called with (steps_done, steps_total), one step per radius and source."""
    started = time.perf_counter()
    if not radii:
        raise RobustnessError("no radii given")
    radii = sorted({_check_radius(r) for r in radii})
    if not (isinstance(threshold_pct, (int, float)) and math.isfinite(threshold_pct) and threshold_pct >= 0):
        raise RobustnessError(f"threshold_pct must be a number >= 0, got {threshold_pct!r}")
    spacing = check_spacing(spacing)
    names = report_features(features)
    posts = {"uls": _stage_list(uls_post, "ULS"), "dim": _stage_list(dim_post, "DIM")}
    n_st = len(posts["uls"])
    if len(posts["dim"]) != n_st:
        raise RobustnessError(f"{n_st} ULS post-event epochs but {len(posts['dim'])} DIM ones; "
                              "every stage needs both")
    if stage_names is None:
        stages = ["post"] if n_st == 1 else [f"post{i + 1}" for i in range(n_st)]
    else:
        stages = [str(x) for x in stage_names]
        if len(stages) != n_st or len(set(stages)) != n_st:
            raise RobustnessError(f"stage_names: expected {n_st} distinct names, got {list(stage_names)!r}")
    pres = {"uls": uls_pre, "dim": dim_pre}
    clouds: dict[str, dict] = {}
    k = 0
    for src in ("uls", "dim"):
        eps = [pres[src]] + posts[src]
        labels = ["pre"] + stages
        thinned = []
        for label, e in zip(labels, eps):
            t = thin(e, spacing, seed + k) if spacing is not None else e
            k += 1
            thinned.append(t)
            clouds[f"{src}_{label}"] = {"points_in": len(e), "points": len(t)}
        pres[src] = thinned[0]
        posts[src] = thinned[1:]
    role = {"uls": "ULS", "dim": "DIM"}
    pairs = {src: [_pair(pres[src], p, role[src] if n_st == 1 else f"{role[src]} {st}", sample, seed, workers)
                   for st, p in zip(stages, posts[src])]
             for src in ("uls", "dim")}
    for src in ("uls", "dim"):
        for label, e in zip(["pre"] + stages, [pres[src]] + posts[src]):
            clouds[f"{src}_{label}"]["building_spacing_m"] = _median_spacing(e, workers)
    st_tab: dict[str, dict[str, dict[float, dict[str, float]]]] = {
        src: {st: {} for st in stages} for src in ("uls", "dim")}
    fpre_keep: dict[float, dict[str, dict]] = {}
    total, done = 2 * len(radii), 0
    for r in radii:
        fpre_keep[r] = {}
        for src in ("uls", "dim"):
            t0 = time.perf_counter()
            per, fpre_keep[r][src] = _stage_changes(pairs[src], r, names, workers, keep_pre=True)
            for st, ch in zip(stages, per):
                st_tab[src][st][r] = ch
            done += 1
            log.info("robustness: %s r=%g m (%d stages) in %.1f s", src, r, n_st, time.perf_counter() - t0)
            if progress:
                progress(done, total)
    st_diff = {st: {r: {} for r in radii} for st in stages}
    for st in stages:
        for r in radii:
            for f in names:
                d = abs(st_tab["uls"][st][r][f] - st_tab["dim"][st][r][f])
                st_diff[st][r][f] = d if math.isfinite(d) else math.nan
    diff: dict[float, dict[str, float]] = {r: {} for r in radii}
    uls_t: dict[float, dict[str, float]] = {r: {} for r in radii}
    dim_t: dict[float, dict[str, float]] = {r: {} for r in radii}
    deciding: dict[float, dict[str, str]] = {r: {} for r in radii}
    for r in radii:
        for f in names:
            ds = [st_diff[st][r][f] for st in stages]
            if any(not math.isfinite(d) for d in ds):
                i = next(j for j, d in enumerate(ds) if not math.isfinite(d))
                diff[r][f] = math.nan
            else:
                i = int(np.argmax(ds))
                diff[r][f] = ds[i]
            deciding[r][f] = stages[i]
            uls_t[r][f] = st_tab["uls"][stages[i]][r][f]
            dim_t[r][f] = st_tab["dim"][stages[i]][r][f]

    def key(r):
        n = sum(within(diff[r][f], threshold_pct) for f in names)
        v = [x for x in diff[r].values() if math.isfinite(x)]
        return (-n, float(np.mean(v)) if v else math.inf, r)

    best = min(radii, key=key)
    robust = [f for f in names if within(diff[best][f], threshold_pct)]
    counts = {t: sum(within(diff[best][f], t) for f in names) for t in THRESHOLDS}
    pre_values = {}
    for src in ("uls", "dim"):
        pv = _pre_values(pres[src], pairs[src][0].pre_idx, fpre_keep[best][src], names)
        if pv:
            pre_values[src] = pv
    return RobustnessResult(radii=list(radii), features=list(names), uls=uls_t, dim=dim_t,
                            difference=diff, best_radius=best, threshold_pct=float(threshold_pct),
                            robust=robust, counts_by_threshold=counts,
                            points={k: len(p[0].pre_idx) for k, p in pairs.items()},
                            wall_time_s=time.perf_counter() - started, stages=stages,
                            stage_uls=st_tab["uls"], stage_dim=st_tab["dim"], stage_difference=st_diff,
                            deciding_stage=deciding, spacing_m=spacing, clouds=clouds, pre_values=pre_values,
                            seed=seed, sample=sample)


def quiet_features(result: RobustnessResult, radius: float | None = None) -> list[str]:
    """Robust features at `radius` (default the best) whose relative change stays within the
    threshold on ULS and on DIM at every stage: their agreement says little (no change seen)."""
    r = result.best_radius if radius is None else radius
    tabs = ([result.stage_uls[st][r] for st in result.stages] + [result.stage_dim[st][r] for st in result.stages]
            if result.stage_uls else [result.uls[r], result.dim[r]])
    return [f for f in result.robust_at(r) if all(within(abs(t[f]), result.threshold_pct) for t in tabs)]


def compare_with_paper(result: RobustnessResult) -> dict:
    """The selected robust features against the paper's set (normal_x/y/z as "normal_vector"),
    only over features the experiment looked at: {"both", "only_ours", "only_paper",
    "not_tested"} (sorted lists) and "agreement" (Jaccard index of the two sets)."""
    ours = set(result.robust)
    tested = set(result.features)
    paper = set(PAPER_SET) & tested
    union = ours | paper
    return {"both": sorted(ours & paper), "only_ours": sorted(ours - paper), "only_paper": sorted(paper - ours),
            "not_tested": sorted(set(PAPER_SET) - tested),
            "agreement": round(len(ours & paper) / len(union), 4) if union else 1.0}
