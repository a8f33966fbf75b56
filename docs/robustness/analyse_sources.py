"""Why ULS and DIM disagree on some change features: numbers from a `quakescan robustness`
run's clouds (run from the repository root with the project's Python).

    python docs/robustness/analyse_sources.py out/robustness_b_s0 [more run folders] -o docs/robustness/sources.json

For every run folder (its clouds/ and robustness.json: seed, spacing, stages, best radius,
sample), the clouds are thinned and paired exactly as the run did, then per source:
  * building points by surface (roof, wall, debris, interior) per epoch, after thinning;
  * median nearest-neighbour spacing of roof and wall points (same surface only);
  * noise across the surface: sqrt(eigenvalue3) at r = 0.5 m on roof and wall points
    (a plane with noise sigma along its normal gives sigma);
  * surface variation at r = 1, 2, 4 m on roof and wall points (median, IQR);
  * at the best radius, the relative change of every feature per stage on roof points
    only, on wall points only, and on DIM re-weighted to ULS's roof/wall mix (walls or
    roofs dropped at random until the shares match): if ULS and DIM agree per surface but
    not overall, the disagreement is the surface mix, not the per-surface measurement;
  * counterfactual reruns of the whole selection (all radii) on the thinned clouds:
    "uls_plus_noise": Gaussian noise of NOISE_M per axis added to every ULS cloud (DIM-like
    noise across surfaces); "dim_uls_coverage": DIM wall points farther than COVER_M from
    every ULS building point of the same epoch dropped (ULS-like facade coverage); both.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from quakescan.change.features import compute_features
from quakescan.formats.pointcloud import read_epoch
from quakescan.studies.robustness.selection import (
    _compare,
    _compute_names,
    _pair,
    _post_values,
    _subset,
    report_features,
    robustness,
    thin,
    within,
)

SURF = {1: "roof", 2: "wall", 3: "debris", 4: "interior"}
NOISE_M = 0.02
COVER_M = 0.3


def _q(v):
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return None
    q1, m, q3 = np.percentile(v, [25, 50, 75])
    return {"median": round(float(m), 6), "q1": round(float(q1), 6), "q3": round(float(q3), 6), "n": len(v)}


def _nn_spacing(xyz):
    from scipy.spatial import cKDTree

    if len(xyz) < 2:
        return None
    d, _ = cKDTree(xyz).query(xyz, k=2, workers=2)
    return round(float(np.median(d[:, 1])), 4)


def analyse(run: Path) -> dict:
    js = json.loads((run / "robustness.json").read_text())
    stages = js["stages"]
    spacing = js.get("spacing_m")
    radius = js["best_radius_m"]
    seed = int(js.get("seed", 0))
    sample = js.get("sample", 20000)
    names = report_features(None)
    clouds = run / "clouds"
    uls_pre = read_epoch(clouds / "uls_pre.las")
    origin = uls_pre.origin
    raw = {"uls": [uls_pre] + [read_epoch(clouds / f"uls_{s}.las", origin=origin) for s in stages],
           "dim": [read_epoch(clouds / f"{'dim'}_{s}.las", origin=origin) for s in ["pre"] + stages]}
    k = 0
    eps = {}
    for src in ("uls", "dim"):  # same thinning seeds as quakescan.studies.robustness.selection.robustness
        eps[src] = []
        for e in raw[src]:
            eps[src].append(thin(e, spacing, seed + k) if spacing else e)
            k += 1
    out = {"run": str(run), "seed": seed, "spacing_m": spacing, "best_radius_m": radius, "stages": stages,
           "sources": {}}
    pairs = {src: [_pair(eps[src][0], p, src, sample, seed, 2) for p in eps[src][1:]] for src in ("uls", "dim")}
    comp = _compute_names(names)
    fpre, fpost = {}, {}
    for src in ("uls", "dim"):
        p0 = pairs[src][0]
        fpre[src] = compute_features(p0.pre.xyz, radius, comp, query_index=p0.pre_idx, workers=2)
        fpost[src] = [_post_values(p.post, p.post_idx, radius, comp, 2) for p in pairs[src]]
    for src in ("uls", "dim"):
        pre = eps[src][0]
        b = pre.building_id > 0
        rec = {"building_points_by_surface": {}, "spacing_m": {}, "sqrt_eigenvalue3_r0.5_m": {},
               "surface_variation_pre": {}}
        for label, e in zip(["pre"] + stages, eps[src]):
            bb = e.building_id > 0
            rec["building_points_by_surface"][label] = {SURF.get(int(c), str(c)): int(n) for c, n in
                                                        zip(*np.unique(e.surface[bb], return_counts=True))}
        bidx = np.flatnonzero(b)
        rng = np.random.default_rng(seed)
        for code in (1, 2):
            idx = bidx[pre.surface[bidx] == code]
            if len(idx) == 0:
                continue
            lab = SURF[code]
            rec["spacing_m"][lab] = _nn_spacing(pre.xyz[idx])
            q = np.sort(rng.choice(idx, size=min(len(idx), 4000), replace=False))
            f = compute_features(pre.xyz, 0.5, ("eigenvalue3",), query_index=q, workers=2)
            rec["sqrt_eigenvalue3_r0.5_m"][lab] = _q(np.sqrt(np.clip(f["eigenvalue3"], 0, None)))
            rec["surface_variation_pre"][lab] = {
                f"{r:g}": _q(compute_features(pre.xyz, r, ("surface_variation",), query_index=q,
                                              workers=2)["surface_variation"]) for r in (1.0, 2.0, 4.0)}
        out["sources"][src] = rec
    # relative changes per surface and DIM re-weighted to ULS's mix, at the best radius
    surf = {src: eps[src][0].surface[pairs[src][0].pre_idx] for src in ("uls", "dim")}
    uls_share_wall = float(np.mean(surf["uls"] == 2) / max(1e-9, np.mean(np.isin(surf["uls"], (1, 2)))))
    dim_mask = np.isin(surf["dim"], (1, 2))
    rng = np.random.default_rng(seed)
    sel = np.flatnonzero(dim_mask)
    roofs, walls = sel[surf["dim"][sel] == 1], sel[surf["dim"][sel] == 2]
    if len(walls) / max(1, len(sel)) > uls_share_wall:  # drop walls
        n_w = round(uls_share_wall / (1 - uls_share_wall) * len(roofs))
        walls = rng.choice(walls, size=min(n_w, len(walls)), replace=False)
    else:  # drop roofs
        n_r = round((1 - uls_share_wall) / max(1e-9, uls_share_wall) * len(walls))
        roofs = rng.choice(roofs, size=min(n_r, len(roofs)), replace=False)
    reweighted = np.sort(np.concatenate([roofs, walls]))
    masks = {"all": {s: np.ones(len(surf[s]), bool) for s in surf},
             "roof": {s: surf[s] == 1 for s in surf},
             "wall": {s: surf[s] == 2 for s in surf},
             "dim_as_uls_mix": {"uls": np.isin(surf["uls"], (1, 2)),
                                "dim": np.isin(np.arange(len(surf["dim"])), reweighted)}}
    out["uls_wall_share_of_sampled_pre_points"] = round(uls_share_wall, 4)
    out["dim_wall_share_of_sampled_pre_points"] = round(float(np.mean(surf["dim"][dim_mask] == 2)), 4)
    out["subsets"] = {}
    for name, m in masks.items():
        ch = {}
        for src in ("uls", "dim"):
            mm = m[src]
            ch[src] = [_compare({k2: v[mm] for k2, v in fpre[src].items()},
                                {k2: v[mm] for k2, v in fpost[src][i].items()}, names) for i in range(len(stages))]
        diff = {f: max(abs(ch["uls"][i][f] - ch["dim"][i][f]) for i in range(len(stages))) for f in names}
        diff = {f: (d if math.isfinite(d) else None) for f, d in diff.items()}
        robust = [f for f in names if diff[f] is not None and within(diff[f], js["threshold_pct"])]
        out["subsets"][name] = {
            "points": {src: int(m[src].sum()) for src in ("uls", "dim")},
            "robust": robust,
            "difference_pct_points": {f: (None if d is None else round(d, 2)) for f, d in diff.items()},
            "relative_change_pct": {src: {st: {f: (None if not math.isfinite(v) else round(v, 2))
                                               for f, v in ch[src][i].items()}
                                          for i, st in enumerate(stages)} for src in ("uls", "dim")}}
    out["counterfactuals"] = _counterfactuals(eps, js, seed, sample)
    # pre and post medians of a few features over all pairs (where the relative change comes from)
    out["medians_all_pairs"] = {}
    for f in ("surface_variation", "eigenvalue3", "sphericity", "roughness", "verticality", "curvature"):
        out["medians_all_pairs"][f] = {src: {"pre": round(float(np.nanmedian(fpre[src][f])), 6),
                                             **{st: round(float(np.nanmedian(fpost[src][i][f])), 6)
                                                for i, st in enumerate(stages)}} for src in ("uls", "dim")}
    return out


def _noisy(e, rng):
    from quakescan.formats.pointcloud import Epoch

    return Epoch(xyz=e.xyz + rng.normal(0.0, NOISE_M, e.xyz.shape), origin=e.origin,
                 classification=e.classification, building_id=e.building_id, grade=e.grade, surface=e.surface,
                 crs=e.crs, source=e.source)


def _covered(dim, uls):
    from scipy.spatial import cKDTree

    ub = uls.xyz[uls.building_id > 0]
    d, _ = cKDTree(ub).query(dim.xyz, k=1, workers=2)
    keep = ~((dim.surface == 2) & (d > COVER_M))
    return _subset(dim, np.flatnonzero(keep))


def _counterfactuals(eps, js, seed, sample):
    radii = js["radii_m"]
    stages = js["stages"]
    rng = np.random.default_rng(seed + 1000)
    noisy = [_noisy(e, rng) for e in eps["uls"]]
    covered = [_covered(d, u) for d, u in zip(eps["dim"], eps["uls"])]
    cases = {"as_run": (eps["uls"], eps["dim"]), "uls_plus_noise": (noisy, eps["dim"]),
             "dim_uls_coverage": (eps["uls"], covered), "both": (noisy, covered)}
    out = {}
    for name, (u, d) in cases.items():
        r = robustness(u[0], u[1:], d[0], d[1:], radii=radii, threshold_pct=js["threshold_pct"], workers=2,
                       sample=sample, seed=seed, stage_names=stages)
        out[name] = {"best_radius_m": r.best_radius, "robust": r.robust,
                     "dim_wall_points_pre": int(np.sum((d[0].building_id > 0) & (d[0].surface == 2))),
                     "robust_count_by_radius": {f"{x:g}": len(r.robust_at(x)) for x in r.radii},
                     "difference_pct_points": {f"{x:g}": {f: (None if not math.isfinite(v) else round(v, 2))
                                                          for f, v in r.difference[x].items()} for x in r.radii}}
        print(f"  counterfactual {name}: best {r.best_radius:g} m, {len(r.robust)} robust: {', '.join(r.robust)}",
              flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args(argv)
    res = [analyse(Path(r)) for r in a.runs]
    Path(a.output).write_text(json.dumps(res, indent=1) + "\n")
    for r in res:
        print(r["run"], "wall share ULS", r["uls_wall_share_of_sampled_pre_points"], "DIM",
              r["dim_wall_share_of_sampled_pre_points"])
        for name, s in r["subsets"].items():
            print(f"  {name:15s} robust {len(s['robust']):2d}: {', '.join(s['robust'])}")


if __name__ == "__main__":
    main()
