"""Robust change-feature selection (Zahs et al., "Object-specific change feature selection").

The experiment: geometric features are computed per point at neighbourhood radii 1.0-4.0 m
(step 0.5); the relative change of every feature between a pre- and a post-event epoch is
measured on laser scanning (ULS) and on photogrammetric (DIM) clouds of the same buildings;
a feature is robust when its relative change differs by at most THRESHOLD_PCT percentage
points between ULS and DIM; the radius where the two agree best is selected.

    >>> res = robustness(uls_pre, uls_post, dim_pre, dim_post, radii=(1.0, 2.0))
    >>> res.best_radius, res.robust
    >>> write_report(res, "out/robustness")

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
        neighbourhood, see core.features) are dropped. The median, not the mean, because
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
    Best radius: the radius with the most robust features at the threshold; ties go to the
        smallest mean difference over the features with a finite difference, then to the
        smallest radius.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import QuakeScanError
from .features import FEATURES, compute_features
from .pipeline import PAPER_FEATURES
from .pointcloud import Epoch

log = logging.getLogger(__name__)

RADII = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
THRESHOLD_PCT = 10.0
THRESHOLDS = tuple(float(t) for t in range(51))  # counts_by_threshold: 0..50 % step 1
NORMAL = "normal_vector"
NORMAL_COMPONENTS = ("normal_x", "normal_y", "normal_z")
NEAR_ZERO = 0.1  # |median| below NEAR_ZERO x IQR: the IQR is the scale
DEFAULT_SAMPLE = 20_000
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
          workers: int | None = None) -> _Pair:
    from .change import nearest_neighbours

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


def _changes(pair: _Pair, radius: float, names: Sequence[str], workers: int | None) -> dict[str, float]:
    comp = _compute_names(names)
    fpre = compute_features(pair.pre.xyz, radius, comp, query_index=pair.pre_idx, workers=workers)
    uniq, inv = np.unique(pair.post_idx, return_inverse=True)
    fpost_u = compute_features(pair.post.xyz, radius, comp, query_index=uniq, workers=workers)
    fpost = {k: v[inv] for k, v in fpost_u.items()}
    out = {}
    for f in names:
        if f == NORMAL:
            out[f] = normal_change(np.column_stack([fpre[c] for c in NORMAL_COMPONENTS]),
                                   np.column_stack([fpost[c] for c in NORMAL_COMPONENTS]))
        else:
            out[f] = relative_change(fpre[f], fpost[f])
    return out


def _check_radius(radius) -> float:
    try:
        r = float(radius)
    except (TypeError, ValueError):
        raise RobustnessError(f"radius must be a number, got {radius!r}") from None
    if not math.isfinite(r) or r <= 0:
        raise RobustnessError(f"radius must be a positive number of metres, got {radius!r}")
    return r


def relative_changes(pre: Epoch, post: Epoch, radius: float, features: Sequence[str] | None = FEATURES,
                     workers: int | None = None, sample: int | None = DEFAULT_SAMPLE,
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

    def robust_at(self, radius: float, threshold_pct: float | None = None) -> list[str]:
        t = self.threshold_pct if threshold_pct is None else threshold_pct
        d = self.difference[radius]
        return [f for f in self.features if _le(d[f], t)]

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
        }


def _le(x: float, t: float) -> bool:
    return x is not None and math.isfinite(x) and x <= t + 1e-9


def robustness(uls_pre: Epoch, uls_post: Epoch, dim_pre: Epoch, dim_post: Epoch,
               radii: Sequence[float] = RADII, threshold_pct: float = THRESHOLD_PCT,
               features: Sequence[str] | None = None, workers: int | None = None, progress=None,
               sample: int | None = DEFAULT_SAMPLE, seed: int = 0) -> RobustnessResult:
    """Relative change of every feature on the ULS pair and on the DIM pair at every radius,
    their difference, the best radius and the robust features (module doc). `progress` is
    called with (steps_done, steps_total), one step per radius and source."""
    started = time.perf_counter()
    if not radii:
        raise RobustnessError("no radii given")
    radii = sorted({_check_radius(r) for r in radii})
    if not (isinstance(threshold_pct, (int, float)) and math.isfinite(threshold_pct) and threshold_pct >= 0):
        raise RobustnessError(f"threshold_pct must be a number >= 0, got {threshold_pct!r}")
    names = report_features(features)
    pairs = {"uls": _pair(uls_pre, uls_post, "ULS", sample, seed, workers),
             "dim": _pair(dim_pre, dim_post, "DIM", sample, seed, workers)}
    tables: dict[str, dict[float, dict[str, float]]] = {"uls": {}, "dim": {}}
    total, done = 2 * len(radii), 0
    for r in radii:
        for src, pair in pairs.items():
            t0 = time.perf_counter()
            tables[src][r] = _changes(pair, r, names, workers)
            done += 1
            log.info("robustness: %s r=%g m in %.1f s", src, r, time.perf_counter() - t0)
            if progress:
                progress(done, total)
    diff = {r: {f: abs(tables["uls"][r][f] - tables["dim"][r][f]) for f in names} for r in radii}
    for r in radii:
        for f in names:
            if not math.isfinite(diff[r][f]):
                diff[r][f] = math.nan

    def key(r):
        n = sum(_le(diff[r][f], threshold_pct) for f in names)
        v = [x for x in diff[r].values() if math.isfinite(x)]
        return (-n, float(np.mean(v)) if v else math.inf, r)

    best = min(radii, key=key)
    robust = [f for f in names if _le(diff[best][f], threshold_pct)]
    counts = {t: sum(_le(diff[best][f], t) for f in names) for t in THRESHOLDS}
    return RobustnessResult(radii=list(radii), features=list(names), uls=tables["uls"], dim=tables["dim"],
                            difference=diff, best_radius=best, threshold_pct=float(threshold_pct),
                            robust=robust, counts_by_threshold=counts,
                            points={k: len(p.pre_idx) for k, p in pairs.items()},
                            wall_time_s=time.perf_counter() - started)


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


# Report -----------------------------------------------------------------------------------

def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)
    os.replace(tmp, path)


def _atomic_fig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    tmp = path.with_name(path.name + ".part")
    fig.savefig(tmp, format="png")
    plt.close(fig)
    os.replace(tmp, path)


def _fmt(x) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.4f}"


def _plot_counts(result: RobustnessResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    ts = np.array(THRESHOLDS)
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    cmap = plt.get_cmap("viridis")
    for k, r in enumerate(result.radii):
        counts = [len(result.robust_at(r, t)) for t in ts]
        best = r == result.best_radius
        ax.step(ts, counts, where="post", lw=3.0 if best else 1.2, color="black" if best else
                cmap(k / max(1, len(result.radii) - 1)), label=f"r = {r:g} m" + (" (selected)" if best else ""),
                zorder=3 if best else 2)
    ax.axvline(result.threshold_pct, color="red", ls="--", lw=1)
    ax.text(result.threshold_pct, 0.2, f" {result.threshold_pct:g} %", color="red", va="bottom")
    ax.set_xlabel("allowed difference in relative change, ULS vs DIM [percentage points]")
    ax.set_ylabel("number of robust change features")
    ax.set_xlim(0, ts[-1])
    ax.set_ylim(0, len(result.features) + 0.5)
    ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    _atomic_fig(fig, path)


def _plot_heatmap(result: RobustnessResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = np.array([[result.difference[r][f] for r in result.radii] for f in result.features], dtype=float)
    shown = np.clip(m, 0, 50)
    fig, ax = plt.subplots(figsize=(1.6 + 0.75 * len(result.radii), 1.4 + 0.28 * len(result.features)), dpi=120)
    im = ax.imshow(np.ma.masked_invalid(shown), cmap="magma_r", vmin=0, vmax=50, aspect="auto")
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            v = m[i, j]
            txt = "n/a" if not math.isfinite(v) else (f"{v:.0f}" if v < 999 else ">999")
            ax.text(j, i, txt, ha="center", va="center", fontsize=6,
                    color="white" if math.isfinite(v) and v > 30 else "black")
    ax.set_xticks(range(len(result.radii)), [f"{r:g}" + (" *" if r == result.best_radius else "")
                                             for r in result.radii])
    ax.set_yticks(range(len(result.features)), result.features, fontsize=7)
    ax.set_xlabel("radius [m] (* selected)")
    ax.set_title("|relative change ULS - DIM| [percentage points]", fontsize=9)
    fig.colorbar(im, ax=ax, label="clipped at 50")
    fig.tight_layout()
    _atomic_fig(fig, path)


def _readme(result: RobustnessResult, context: str) -> str:
    cmp = compare_with_paper(result)
    lines = [
        "# Robust change-feature selection", "",
        ("Zahs et al., \"Object-specific change feature selection\": relative change of each geometric "
        "feature between the pre- and the post-event epoch, on ULS and on DIM clouds of the same buildings; "
        f"a feature is robust when the two differ by at most {result.threshold_pct:g} percentage points."), "",
    ]
    if context:
        lines += [context, ""]
    lines += [
        (f"- radii: {', '.join(f'{r:g}' for r in result.radii)} m; features: {len(result.features)} "
        "(normal_x/y/z as one normal_vector)"),
        f"- pre-event building points used: ULS {result.points.get('uls', 0)}, DIM {result.points.get('dim', 0)}",
        ("- relative change = 100 (median post - median pre) / scale over pre building points paired with their "
        "nearest post point (NaN pairs dropped); scale = |median pre|, or the pre IQR when |median| < 0.1 IQR; "
        "normal_vector: 100 x median angle between paired normals / 90 deg"),
        (f"- selected radius: **{result.best_radius:g} m** ({len(result.robust)} robust features, mean difference "
        f"{result.mean_difference(result.best_radius):.1f} percentage points)"),
        f"- robust features: {', '.join(result.robust) or '(none)'}",
        f"- run time: {result.wall_time_s:.1f} s", "",
        "| radius [m] | robust at threshold | mean difference [pp] |", "|---|---|---|",
    ]
    for r in result.radii:
        lines.append(f"| {r:g}{' (selected)' if r == result.best_radius else ''} | {len(result.robust_at(r))} | "
                     f"{result.mean_difference(r):.1f} |")
    lines += ["", "## Comparison with the paper's set", "",
              f"Paper: {', '.join(PAPER_SET)}.", "",
              f"- in both: {', '.join(cmp['both']) or '(none)'}",
              f"- only ours: {', '.join(cmp['only_ours']) or '(none)'}",
              f"- only the paper's: {', '.join(cmp['only_paper']) or '(none)'}",
              f"- agreement (Jaccard): {cmp['agreement']:.2f}", "",
              ("Files: robustness.json, robustness.csv (radius, feature, uls %, dim %, difference), "
              "features_vs_threshold.png, difference_heatmap.png."), ""]
    return "\n".join(lines)


def write_report(result: RobustnessResult, out_dir: str | os.PathLike, context: str = "") -> None:
    """robustness.json, robustness.csv, features_vs_threshold.png, difference_heatmap.png and
    README.md in `out_dir` (created), each written to a .part file and renamed."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RobustnessError(f"{out}: cannot create the report folder ({e})") from None
    _atomic_text(out / "robustness.json", json.dumps(result.to_json(), indent=2) + "\n")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["radius_m", "feature", "uls_pct", "dim_pct", "difference_pct_points", "robust"])
    for r in result.radii:
        for f in result.features:
            d = result.difference[r][f]
            w.writerow([f"{r:g}", f, _fmt(result.uls[r][f]), _fmt(result.dim[r][f]), _fmt(d),
                        int(_le(d, result.threshold_pct))])
    _atomic_text(out / "robustness.csv", buf.getvalue())
    _plot_counts(result, out / "features_vs_threshold.png")
    _plot_heatmap(result, out / "difference_heatmap.png")
    _atomic_text(out / "README.md", _readme(result, context))


# The whole experiment -------------------------------------------------------------------------

def run_experiment(pre_scene_dir: str | os.PathLike, post_scene_dir: str | os.PathLike,
                   out_dir: str | os.PathLike, radii: Sequence[float] = RADII, seed: int = 0,
                   workers: int | None = None, progress=None, survey=None, photo_survey=None,
                   threshold_pct: float = THRESHOLD_PCT, sample: int | None = DEFAULT_SAMPLE) -> RobustnessResult:
    """Scan both scenes with ULS (`survey`, default the paper preset) and DIM (`photo_survey`,
    default the paper preset) into out_dir/clouds/ (existing clouds are kept: resumable; each
    is written as .part and renamed), read all four in the pre ULS cloud's frame, run
    `robustness` and write the report to out_dir. `progress(done, total)` over the four
    clouds and then the radii."""
    from .dim import preset_dim, simulate_dim
    from .pointcloud import read_epoch
    from .scan import scan
    from .scene import read_scene
    from .survey import preset

    started = time.perf_counter()
    survey = survey or preset("paper")
    photo_survey = photo_survey or preset_dim("paper")
    out = Path(out_dir)
    clouds = out / "clouds"
    clouds.mkdir(parents=True, exist_ok=True)
    scenes = {"pre": Path(pre_scene_dir), "post": Path(post_scene_dir)}
    loaded = {}
    paths = {}
    total_steps = 4 + 2 * len(set(radii))
    step = 0
    for src in ("uls", "dim"):
        for ep, folder in scenes.items():
            path = clouds / f"{src}_{ep}.las"
            paths[(src, ep)] = path
            if not path.exists():
                if ep not in loaded:
                    loaded[ep] = read_scene(folder)
                tmp = path.with_name(f"{src}_{ep}.part.las")
                s = seed if ep == "pre" else seed + 1  # different noise per epoch
                t0 = time.perf_counter()
                if src == "uls":
                    scan(loaded[ep], survey, tmp, seed=s, threads=workers, source=str(folder))
                else:
                    simulate_dim(loaded[ep], photo_survey, tmp, seed=s, threads=workers, source=str(folder))
                os.replace(tmp, path)
                log.info("robustness: %s %s cloud in %.1f s", src, ep, time.perf_counter() - t0)
            else:
                log.info("robustness: keeping %s", path)
            step += 1
            if progress:
                progress(step, total_steps)
    uls_pre = read_epoch(paths[("uls", "pre")])
    origin = uls_pre.origin
    ep = {k: read_epoch(p, origin=origin) for k, p in paths.items() if k != ("uls", "pre")}

    def inner(done, total):
        if progress:
            progress(4 + done, total_steps)

    res = robustness(uls_pre, ep[("uls", "post")], ep[("dim", "pre")], ep[("dim", "post")], radii=radii,
                     threshold_pct=threshold_pct, workers=workers, progress=inner, sample=sample, seed=seed)
    res.wall_time_s = time.perf_counter() - started
    counts = {f"{s}_{e}": len(x) for (s, e), x in [(("uls", "pre"), uls_pre)] + list(ep.items())}
    context = (f"Scenes: pre `{scenes['pre']}`, post `{scenes['post']}`; ULS survey '{survey.name}' "
               f"(pulse rate {survey.pulse_rate_hz:g} Hz), DIM photo survey '{photo_survey.name}' "
               f"(point step {photo_survey.point_step_px:g} px); seed {seed}. Cloud points: "
               + ", ".join(f"{k} {v}" for k, v in counts.items()) + ".")
    write_report(res, out, context)
    return res
