"""Per-point features: ours against jakteristics 0.6.2 on the same points, in one run.

    .venv/bin/pip install jakteristics==0.6.2     # benchmark-only dependency
    .venv/bin/python bench/bench_features.py      # prints the table, rewrites BENCHMARKS.md's section

Cloud: a virtual ULS scan (`paper` survey) of a box city at UTM-like coordinates, read back from
LAS (>= 1 M points). Exact features at r = 1.5 m: the set jakteristics also has (eigen features,
normal, verticality, number of neighbours) for ours and jakteristics on the same points, the damage
pipeline's default set (`DEFAULT_PIPELINE_FEATURES`), all 24 of ours, densities + z only.
Core-point subsampling (features at every k-th point, mapped to all points by nearest core point)
with its error against exact. Nearest-neighbour mapping (`quakescan.change.split.nearest_neighbours`, index
build + queries) of the cloud onto a second scan of the same city (new noise); the row says which
core/change/split.py it measured (committed or not).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._report import machine, peak_rss_mb, table, write_section
from quakescan.change.features import DEFAULT_PIPELINE_FEATURES, compute_features

COMMON = ("linearity", "planarity", "omnivariance", "surface_variation", "sphericity", "verticality",
          "eigenentropy", "anisotropy", "eigenvalue1", "eigenvalue2", "eigenvalue3", "eigenvalue_sum",
          "num_neighbours", "normal_x", "normal_y", "normal_z")
JAK = ("linearity", "planarity", "omnivariance", "surface_variation", "sphericity", "verticality",
       "eigenentropy", "anisotropy", "eigenvalue1", "eigenvalue2", "eigenvalue3", "eigenvalue_sum",
       "number_of_neighbors", "nx", "ny", "nz")


def cloud(min_points: int, seed: int = 1) -> np.ndarray:
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.formats.pointcloud import read_epoch
    from quakescan.formats.synthetic import box_city

    rows = 4
    while True:
        rng = np.random.default_rng(112)
        cols = rows * 2
        heights = rng.choice([6.0, 9.0, 12.0, 15.0, 18.0, 24.0], size=rows * cols)
        city = box_city(rows=rows, cols=cols, footprint=14.0, street=12.0, height=heights,
                        origin=(500000.0, 5000000.0, 200.0))
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "city.las"
            scan(city, preset("paper"), out, seed=seed)
            ep = read_epoch(out)
        xyz = ep.xyz + ep.origin  # world coordinates, as a user would hand them over
        if len(xyz) >= min_points:
            return xyz
        rows += 2


def _head() -> str:
    import subprocess

    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, check=False)
    return out.stdout.strip() or "unknown commit"


def timed(fn, repeat=1):
    best = np.inf
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--radius", type=float, default=1.5)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    r = args.radius
    xyz = cloud(args.points)
    n = len(xyz)
    compute_features(xyz[:2000], r)  # load the compiled kernel (numba cache) before timing
    rows = []
    t_common, ours = timed(lambda: compute_features(xyz, r, features=COMMON), repeat=2)
    rows.append(["ours, jakteristics' set", f"{t_common:.2f}", f"{n / t_common / 1e3:.0f}", "exact"])
    jak_line = None
    t_jak = None
    try:
        import jakteristics

        local = xyz - xyz.min(axis=0)  # jakteristics gets the local frame (it is float32 inside)
        t_jak, jf = timed(lambda: jakteristics.compute_features(np.ascontiguousarray(local), search_radius=r,
                                                                feature_names=list(JAK)), repeat=2)
        rows.append(["jakteristics 0.6.2, same set", f"{t_jak:.2f}", f"{n / t_jak / 1e3:.0f}", "exact (float32 out)"])
        jak_line = f"speed-up over jakteristics (same set, same points, same run): {t_jak / t_common:.1f}x"
        ok = ~np.isnan(ours["planarity"]) & ~np.isnan(jf[:, JAK.index("planarity")])
        d = np.abs(ours["planarity"][ok] - jf[ok, JAK.index("planarity")])
        jak_line += f"; planarity |ours - jak| median {np.median(d):.1e}, p99 {np.quantile(d, 0.99):.1e}"
        del jf
    except ImportError:
        jak_line = "jakteristics not installed: `.venv/bin/pip install jakteristics==0.6.2`"
    del ours
    t_pipe, _ = timed(lambda: compute_features(xyz, r, features=DEFAULT_PIPELINE_FEATURES), repeat=2)
    rows.append(["ours, default pipeline set (13 incl. curvature)", f"{t_pipe:.2f}", f"{n / t_pipe / 1e3:.0f}",
                 "exact"])
    t_all, exact = timed(lambda: compute_features(xyz, r), repeat=2)
    rows.append(["ours, all 24 features", f"{t_all:.2f}", f"{n / t_all / 1e3:.0f}", "exact"])
    t_dens, _ = timed(lambda: compute_features(xyz, r, features=("num_neighbours", "surface_density",
                                                                 "z_range", "z_rank")), repeat=2)
    rows.append(["ours, densities + z only", f"{t_dens:.2f}", f"{n / t_dens / 1e3:.0f}", "exact"])
    # approximate mode: core points every k-th point (Morton order), nearest core point's values
    from scipy.spatial import cKDTree

    from quakescan.change.split import morton_order

    order = morton_order(xyz - xyz.min(axis=0))
    for k in (4, 16):
        def approx(k=k):
            core = xyz[order[::k]]
            fc = compute_features(xyz, r, core_points=core)
            _, idx = cKDTree(core - xyz.min(axis=0)).query(xyz - xyz.min(axis=0), workers=-1)
            return {f: v[idx] for f, v in fc.items()}
        t_a, fa = timed(approx)
        errs = []
        for f in ("planarity", "roughness", "normal_z", "surface_density"):
            ok = ~np.isnan(exact[f]) & ~np.isnan(fa[f])
            errs.append(f"{f} {np.median(np.abs(fa[f][ok] - exact[f][ok])):.2g}")
        rows.append([f"ours, core points every {k}th + NN", f"{t_a:.2f}", f"{n / t_a / 1e3:.0f}",
                     "median |err|: " + ", ".join(errs)])
    # nearest-neighbour mapping onto a second scan of the same city (kd-tree build + queries)
    from quakescan.change.split import nearest_neighbours

    post = cloud(args.points, seed=2)
    o = np.minimum(xyz.min(axis=0), post.min(axis=0))
    pre_l, post_l = xyz - o, post - o
    nearest_neighbours(pre_l[:1000], post_l[:1000])
    t_nn, (_, dist) = timed(lambda: nearest_neighbours(pre_l, post_l), repeat=2)
    import subprocess

    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "core/change/split.py"],
                           cwd=Path(__file__).resolve().parents[1], check=False).returncode != 0
    what = "uncommitted core/change/split.py" if dirty else f"core/change/split.py at {_head()}"
    rows.append([f"NN mapping onto a second scan ({len(post):,} points), index build + queries ({what})",
                 f"{t_nn:.2f}", f"{n / t_nn / 1e3:.0f}", f"exact; distance median {np.median(dist):.3f} m"])
    nn = exact["num_neighbours"]
    text = "\n".join([
        "## Per-point features (`bench/bench_features.py`)",
        "",
        (f"Machine: {machine()}. Cloud: virtual ULS of a box city at UTM coordinates, {n:,} points, "
         f"neighbours at r = {r} m: median {np.median(nn):.0f}, p99 {np.quantile(nn, 0.99):.0f}."),
        "",
        table(["run", "wall s (best of 2; approx.: 1)", "k points/s", "accuracy"], rows),
        "",
        jak_line,
        (f"Targets (r = {r} m, >= 1 M points, same run): >= 500 k points/s and >= 5x jakteristics for its "
         f"set: {n / t_common / 1e3:.0f} k points/s"
         + (f", {t_jak / t_common:.1f}x" if t_jak else "")
         + f"; NN mapping >= 2 M points/s: {n / t_nn / 1e6:.2f} M points/s."),
        f"Peak memory of the run: {peak_rss_mb():.0f} MiB.",
        "Command: `.venv/bin/python bench/bench_features.py`",
    ])
    print(text)
    if not args.no_write:
        write_section("bench_features", text)


if __name__ == "__main__":
    main()
