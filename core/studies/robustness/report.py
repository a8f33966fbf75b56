"""The robustness report's text and tables: README.md (what was measured, the selected
radius, the per-stage and per-surface tables, the comparison with the paper's set),
robustness.json and the CSV tables, beside the figures of `plots`."""
from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path

from ...runtime.atomic import write_text
from .plots import plot_counts, plot_heatmap
from .selection import (PAPER_SET, PRE_VALUE_FEATURES, SURFACES, RobustnessError, RobustnessResult, compare_with_paper,
                        quiet_features, within)


def _fmt(x) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.4f}"


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
        (f"- of these, changed by less than {result.threshold_pct:g} % on both sources at every stage (robust "
         f"because neither source sees a change): {', '.join(quiet_features(result)) or '(none)'}"),
        f"- run time: {result.wall_time_s:.1f} s", "",
    ]
    multi = len(result.stages) > 1 and bool(result.stage_difference)
    if result.spacing_m is not None or result.clouds:
        sp = "none" if result.spacing_m is None else f"{result.spacing_m:g} m (voxel grid, one random point per cell)"
        lines.insert(len(lines) - 1, f"- thinning: {sp}")
    if result.clouds:
        lines.insert(len(lines) - 1, "- clouds (points before -> after thinning; median nearest-neighbour distance "
                     "between building points): " + "; ".join(
                         f"{k} {v.get('points_in', 0)} -> {v.get('points', 0)}, "
                         f"{_fmt_m(v.get('building_spacing_m'))}" for k, v in result.clouds.items()))
    if multi:
        lines.insert(len(lines) - 1, (f"- stages: {', '.join(result.stages)}; a feature is robust at a radius when "
                                      "ULS and DIM agree within the threshold at every stage (difference = the "
                                      "largest over the stages)"))
        head = "| radius [m] | robust at every stage | " + " | ".join(
            f"robust at {st}" for st in result.stages) + " | mean difference [pp] |"
        lines += [head, "|---|---|" + "---|" * len(result.stages) + "---|"]
        for r in result.radii:
            lines.append(f"| {r:g}{' (selected)' if r == result.best_radius else ''} | {len(result.robust_at(r))} | "
                         + " | ".join(str(len(result.stage_robust_at(st, r))) for st in result.stages)
                         + f" | {result.mean_difference(r):.1f} |")
    else:
        lines += ["| radius [m] | robust at threshold | mean difference [pp] |", "|---|---|---|"]
        for r in result.radii:
            lines.append(f"| {r:g}{' (selected)' if r == result.best_radius else ''} | {len(result.robust_at(r))} | "
                         f"{result.mean_difference(r):.1f} |")
    b = result.best_radius
    if result.stage_uls:
        lines += ["", f"## Relative change per stage at the selected radius ({b:g} m)", "",
                  "| feature | " + " | ".join(f"{st} ULS % | {st} DIM % | {st} diff" for st in result.stages)
                  + " | robust |",
                  "|---|" + "---|---|---|" * len(result.stages) + "---|"]
        for f in result.features:
            cells = []
            for st in result.stages:
                cells += [_fmt1(result.stage_uls[st][b][f]), _fmt1(result.stage_dim[st][b][f]),
                          _fmt1(result.stage_difference[st][b][f])]
            lines.append(f"| {f} | " + " | ".join(cells) + f" | {'yes' if f in result.robust else 'no'} |")
    if result.pre_values:
        lines += ["", f"## Pre-event values by surface at {b:g} m (median [q1, q3])", "",
                  "| feature | " + " | ".join(f"{src.upper()} {surf}" for src in result.pre_values
                                             for surf in SURFACES.values()) + " |",
                  "|---|" + "---|" * (len(result.pre_values) * len(SURFACES))]
        for f in PRE_VALUE_FEATURES:
            cells = []
            for src in result.pre_values:
                for surf in SURFACES.values():
                    d = result.pre_values[src].get(surf, {}).get(f)
                    cells.append("" if d is None else f"{d['median']:.3g} [{d['q1']:.3g}, {d['q3']:.3g}]")
            if any(cells):
                lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", "## Comparison with the paper's set", "",
              f"Paper: {', '.join(PAPER_SET)}.", "",
              f"- in both: {', '.join(cmp['both']) or '(none)'}",
              f"- only ours: {', '.join(cmp['only_ours']) or '(none)'}",
              f"- only the paper's: {', '.join(cmp['only_paper']) or '(none)'}",
              f"- agreement (Jaccard): {cmp['agreement']:.2f}", "",
              ("Files: robustness.json, robustness.csv (radius, feature, uls %, dim %, difference: at the "
              "deciding stage), robustness_stages.csv (the same per stage), features_vs_threshold.png, "
              "difference_heatmap.png."), ""]
    return "\n".join(lines)


def _fmt1(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.1f}"


def _fmt_m(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.3f} m"


def write_report(result: RobustnessResult, out_dir: str | os.PathLike, context: str = "") -> None:
    """robustness.json, robustness.csv, features_vs_threshold.png, difference_heatmap.png and
    README.md in `out_dir` (created), each written to a .part file and renamed."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RobustnessError(f"{out}: cannot create the report folder ({e})") from None
    write_text(out / "robustness.json", json.dumps(result.to_json(), indent=2) + "\n")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["radius_m", "feature", "uls_pct", "dim_pct", "difference_pct_points", "robust"])
    for r in result.radii:
        for f in result.features:
            d = result.difference[r][f]
            w.writerow([f"{r:g}", f, _fmt(result.uls[r][f]), _fmt(result.dim[r][f]), _fmt(d),
                        int(within(d, result.threshold_pct))])
    write_text(out / "robustness.csv", buf.getvalue())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["stage", "radius_m", "feature", "uls_pct", "dim_pct", "difference_pct_points", "robust_at_stage"])
    for st in result.stages:
        if st not in result.stage_uls:
            continue
        for r in result.radii:
            for f in result.features:
                d = result.stage_difference[st][r][f]
                w.writerow([st, f"{r:g}", f, _fmt(result.stage_uls[st][r][f]), _fmt(result.stage_dim[st][r][f]),
                            _fmt(d), int(within(d, result.threshold_pct))])
    write_text(out / "robustness_stages.csv", buf.getvalue())
    plot_counts(result, out / "features_vs_threshold.png")
    plot_heatmap(result, out / "difference_heatmap.png")
    write_text(out / "README.md", _readme(result, context))
