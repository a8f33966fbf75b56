#!/usr/bin/env python3
"""QuakeScan's M3C2 (core/change/m3c2.py) beside py4dgeo's on the same real pair, in one run.

    .venv/bin/python bench/bench_m3c2.py [--py4dgeo-python PY]

Pair: the real AHN3 Delft tile 1 split into two random halves (`default_rng(5)`, as in
bench_transfer), 20,000 seeded building core points (real footprints), normals at 1.5 m,
cylinder radius 1 m, half length 2 m. Both programs get the same core points and the same
normals, so they compare the same cylinders. py4dgeo 1.2.0 (Heidelberg's reference
implementation) needs numpy 2, which the bpy module of QuakeScan's environment cannot take, so
it runs in its own environment (`--py4dgeo-python`, e.g. `python3.11 -m venv /tmp/p4d &&
/tmp/p4d/bin/pip install py4dgeo==1.2.0`), fed through an .npz file; without it the table
has QuakeScan's rows only.

Rows: Lague et al.'s mean and normal quantile (what py4dgeo computes), the mean with
Student's quantile for the Welch-Satterthwaite degrees of freedom, and the robust median form
QuakeScan's surface descriptors use. On an unchanged surface a 95 % test flags ~5 % of the core
points by construction; the issue measured py4dgeo here at a median LoD of 0.28 m and 5.9 %.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, table, write_section  # noqa: E402

CORE_POINTS = 20_000
RADIUS_M = 1.0
HALF_LENGTH_M = 2.0
NORMAL_RADIUS_M = 1.5

PY4DGEO_RUN = """
import sys, time, numpy as np, py4dgeo
d = np.load(sys.argv[1])
py4dgeo.set_interactive_backend = None
e1, e2 = py4dgeo.Epoch(d["pre"]), py4dgeo.Epoch(d["post"])
m = py4dgeo.M3C2(epochs=(e1, e2), corepoints=d["core"], cyl_radius=float(d["radius"]),
                 max_distance=float(d["half_length"]), corepoint_normals=d["normals"])
t = time.perf_counter()
dist, unc = m.run()
np.savez(sys.argv[2], distance=dist, lod=unc["lodetection"], n1=unc["num_samples1"], n2=unc["num_samples2"],
         seconds=time.perf_counter() - t, version=py4dgeo.__version__)
"""


def main(argv=None) -> int:
    from bench_transfer import real_pairs

    from quakescan.change.features import compute_features
    from quakescan.change.m3c2 import ColumnGrid, M3C2Settings, m3c2
    from quakescan.formats.pair import load_pair

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_m3c2"))
    p.add_argument("--py4dgeo-python", default="/tmp/p4d/bin/python",
                   help="a Python with py4dgeo 1.2.0 installed (its own environment)")
    p.add_argument("--no-write", action="store_true")
    a = p.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    name, tag, pre_path, post_path = next(r for r in real_pairs(work) if "tile 1: two random halves" in r[0])
    data = load_pair(pre_path, post_path, ROOT.parent / "shared" / "data" / "ahn3_footprints_rd.geojson")
    pre, post = data.pre.xyz, data.post.xyz
    building = np.flatnonzero(data.pre.building_id > 0)
    core_idx = np.sort(np.random.default_rng(0).choice(building, CORE_POINTS, replace=False))
    f = compute_features(pre, NORMAL_RADIUS_M, ("normal_x", "normal_y", "normal_z"), query_index=core_idx)
    normals = np.column_stack([f["normal_x"], f["normal_y"], f["normal_z"]])
    ok = np.all(np.isfinite(normals), axis=1)
    core, normals = pre[core_idx[ok]], normals[ok]
    rows, results = [], {}
    grid_pre, grid_post = ColumnGrid(pre, RADIUS_M), ColumnGrid(post, RADIUS_M)
    variants = {"QuakeScan, mean, normal quantile (Lague et al.)": dict(statistic="mean", student=False),
                "QuakeScan, mean, Student's quantile": dict(statistic="mean", student=True),
                "QuakeScan, median, Student's quantile (the descriptors')": dict(statistic="median", student=True)}
    for label, v in variants.items():
        s = M3C2Settings(cylinder_radius_m=RADIUS_M, max_depth_m=HALF_LENGTH_M, statistic=v["statistic"],
                         min_comparable=2)
        t = time.perf_counter()
        res = m3c2(core, normals, grid_pre, grid_post, s, RADIUS_M, student=v["student"])
        secs = time.perf_counter() - t
        results[label] = res
        ok_rows = res.comparable
        rows.append([label, f"{ok_rows.sum():,}", f"{np.median(res.lod[ok_rows]):.3f}",
                     f"{100 * res.significant[ok_rows].mean():.1f}", f"{np.median(res.n_pre[ok_rows]):.0f}",
                     "", f"{secs:.2f}"])
        print(rows[-1], flush=True)
    py = Path(a.py4dgeo_python)
    if py.is_file():
        with tempfile.TemporaryDirectory() as tmp:
            inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
            np.savez(inp, pre=pre, post=post, core=core, normals=normals, radius=RADIUS_M, half_length=HALF_LENGTH_M)
            (Path(tmp) / "run.py").write_text(PY4DGEO_RUN)
            subprocess.run([str(py), str(Path(tmp) / "run.py"), str(inp), str(out)], check=True,
                           capture_output=True)
            r = np.load(out)
            dist, lod, secs, version = r["distance"], r["lod"], float(r["seconds"]), str(r["version"])
        fin = np.isfinite(dist) & np.isfinite(lod)
        ours = results["QuakeScan, mean, normal quantile (Lague et al.)"]
        both = fin & ours.comparable
        agree = np.abs(ours.distance[both] - dist[both])
        lod_ratio = ours.lod[both] / lod[both]
        rows.append([f"py4dgeo {version} M3C2", f"{fin.sum():,}", f"{np.median(lod[fin]):.3f}",
                     f"{100 * np.mean(np.abs(dist[fin]) > lod[fin]):.1f}", f"{np.median(r['n1'][fin]):.0f}",
                     f"distance |Δ| median {np.median(agree):.4f} m, p99 {np.percentile(agree, 99):.4f}; "
                     f"LoD ratio median {np.median(lod_ratio):.3f}", f"{secs:.2f}"])
        print(rows[-1], flush=True)
    else:
        print(f"{py}: no py4dgeo environment; its row is left out", flush=True)
    text = "\n\n".join([
        "## M3C2 beside py4dgeo (`bench/bench_m3c2.py`)",
        f"Machine: {machine()}. Pair: real AHN3 tile 1 as two random halves (no change), {CORE_POINTS:,} seeded "
        f"building core points (footprints), the same normals (r = {NORMAL_RADIUS_M} m) for both, cylinder radius "
        f"{RADIUS_M} m, half length {HALF_LENGTH_M} m, no registration error. \"significant\" = |distance| > LoD. "
        "The last column compares py4dgeo with QuakeScan's Lague form on the core points both can compare.",
        table(["implementation", "core points compared", "median LoD m", "significant %", "median points per "
               "cylinder (pre)", "agreement with QuakeScan (Lague form)", "seconds"], rows),
        "Command: `.venv/bin/python bench/bench_m3c2.py --py4dgeo-python /tmp/p4d/bin/python` (py4dgeo in its own "
        "environment: it needs numpy 2).",
    ])
    print("\n" + text)
    (work / "results.json").write_text(json.dumps(rows, indent=1))
    if not a.no_write:
        write_section("bench_m3c2", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
