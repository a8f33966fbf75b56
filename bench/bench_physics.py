"""Damage made by physics against the pattern generator, in the same run (issue 14).

    .venv/bin/python bench/bench_physics.py [--buildings 16] [--seed 1] [--jobs 2]   # BENCHMARKS.md "physics"

Generates the paper's generic dataset (pre + grade 3/4/5 scenes) twice in fresh processes
with the bpy module: `--damage patterns` and `--damage physics` (grades 4 and 5 collapse by
rigid-body simulation; grade 3 keeps the patterns in both). Reports:

- wall time and peak memory (of the largest process) of each, made by `--jobs` generator
  processes at once (the post-event scenes are independent), and the time per building
  (extrapolated to 112 unless --buildings is 112: then measured);
- how many collapses did not settle and fell back to the patterns;
- per grade, the share of the footprint still standing (0.5 m cells whose highest
  non-debris surface keeps at least 80 % of its pre-event height);
- the debris (the envelope of the building's debris faces above the structure still standing
  under them, or the ground; 0.5 m cells)
  against the catalogue's solid fraction × bulking × collapsed volume (the pre-event volume
  over the cells that no longer stand; solid fraction 0.225 masonry, 0.15 RC, bulking 1.5,
  the middles of the catalogue's ranges).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._report import machine, run_child, table, write_section  # noqa: E402
from quakescan.formats.scene import read_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "blender_scripts" / "generate_scenes.py"
CELL = 0.5
SOLID = {"masonry": 0.225, "reinforced_concrete": 0.15}
BULKING = 1.5
SCENES = (("post_extreme", 4), ("post_destruction", 5))


def run(cmd, out: Path) -> dict:
    r = run_child([*cmd, "--out", str(out)])
    if r["rc"] != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r['stderr'][-3000:]}")
    return {"wall_s": r["wall_s"], "peak_mb": r["peak_mb"],
            "fallbacks": r["stderr"].count("gets the patterns instead")}


def top_raster(verts, tris, origin, shape):
    """Highest surface per CELL over a grid, from points sampled on every triangle at a
    quarter of the cell size (large faces cover many cells)."""
    top = np.zeros(shape)
    if not len(tris):
        return top
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    edge = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)], axis=0)
    steps = np.maximum(1, np.ceil(edge / (CELL / 4))).astype(int)
    for n in np.unique(steps):
        sel = steps == n
        A, B, C = a[sel], b[sel], c[sel]
        for i in range(n + 1):
            for j in range(n + 1 - i):
                p = A + (i / n) * (B - A) + (j / n) * (C - A)
                ix = np.floor((p[:, 0] - origin[0]) / CELL).astype(int)
                iy = np.floor((p[:, 1] - origin[1]) / CELL).astype(int)
                ok = (ix >= 0) & (ix < shape[0]) & (iy >= 0) & (iy < shape[1]) & (p[:, 2] > 0)
                np.maximum.at(top, (ix[ok], iy[ok]), p[ok, 2])
    return top


def building_measures(pre_vertices, pre_tris, post_vertices, structure_tris, debris_tris, material):
    """One building: (share of its footprint standing, debris volume, the catalogue's expected
    debris volume) from its pre-event triangles and its post-event structure and debris triangles."""
    v = pre_vertices[np.unique(pre_tris)]
    lo = v[:, :2].min(axis=0) - 15.0
    shape = tuple(np.ceil((v[:, :2].max(axis=0) + 15.0 - lo) / CELL).astype(int))
    pre_top = top_raster(pre_vertices, pre_tris, lo, shape)
    foot = pre_top > 0.5
    post_top = top_raster(post_vertices, structure_tris, lo, shape)
    standing = foot & (post_top >= 0.8 * pre_top)
    collapsed_vol = float(pre_top[foot & ~standing].sum()) * CELL * CELL
    deb_top = top_raster(post_vertices, debris_tris, lo, shape)
    # a heap's height above whatever still stands under it (debris on a slab is not a column)
    debris = float(np.maximum(deb_top - post_top, 0.0).sum()) * CELL * CELL
    return float(standing.sum() / max(foot.sum(), 1)), debris, SOLID[material] * BULKING * collapsed_vol


def measure(pre, post, grade):
    """Per building: share standing, debris volume, expected debris, made by physics."""
    out = []
    post_b = {b.id: b for b in post.buildings}
    for b in pre.buildings:
        mine = post.face_building == b.id
        standing, debris, expected = building_measures(
            pre.vertices, pre.faces[pre.face_building == b.id], post.vertices,
            post.faces[mine & (post.face_surface != 3)], post.faces[mine & (post.face_surface == 3)], b.material)
        phys = any(p["name"] == "physics_collapse" for p in post_b[b.id].patterns)
        out.append({"standing": standing, "debris": debris, "expected": expected, "physics": phys})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--buildings", type=int, default=16)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2, help="generator processes at once (generate_scenes.py --jobs)")
    args = ap.parse_args(argv)
    base = ["--set", "generic", "--dataset", "paper", "--buildings", str(args.buildings), "--seed", str(args.seed)]
    rows, stats = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for method in ("patterns", "physics"):
            out = Path(tmp) / method
            r = run([sys.executable, str(SCRIPT), *base, "--damage", method, "--jobs", str(args.jobs)], out)
            pre = read_scene(out / "pre")
            per = {g: measure(pre, read_scene(out / name), g) for name, g in SCENES}
            stats[method] = (r, per)
            print(f"{method}: {r['wall_s']:.1f} s, peak {r['peak_mb']:.0f} MiB, fallbacks {r['fallbacks']}", flush=True)
    n = args.buildings
    head = ["damage", "processes", "wall time (s)", "per building and scene (s)",
            "112 buildings (min, " + ("measured" if n == 112 else "extrapolated") + ")",
            "peak MiB (largest process)", "collapses that did not settle (→ patterns)"]
    trows = []
    for method, (r, per) in stats.items():
        each = r["wall_s"] / (2 * n)
        trows.append((method, args.jobs, f"{r['wall_s']:.0f}", f"{each:.1f}", f"{each * 224 / 60:.1f}",
                      f"{r['peak_mb']:.0f}",
                      r["fallbacks"] if method == "physics" else "–"))
    for method, (r, per) in stats.items():
        for g, ms in per.items():
            st = np.array([m["standing"] for m in ms])
            ratio = np.array([m["debris"] / m["expected"] for m in ms if m["expected"] > 1.0])
            rows.append((method, g, len(ms), sum(m["physics"] for m in ms), f"{st.mean():.2f}",
                         f"{np.median(st):.2f}",
                         f"{np.median(ratio):.2f}" if len(ratio) else "–",
                         f"{np.percentile(ratio, 10):.2f}–{np.percentile(ratio, 90):.2f}" if len(ratio) else "–"))
    t1 = table(head, trows)
    t2 = table(["damage", "grade", "buildings", "made by physics", "share of footprint standing (mean)",
                "(median)", "debris / catalogue (median)", "(10th–90th percentile)"], rows)
    print(t1)
    print(t2)
    cmd = f".venv/bin/python bench/bench_physics.py --buildings {n} --seed {args.seed} --jobs {args.jobs}"
    write_section("physics", f"""## Damage made by physics (`bench/bench_physics.py`)

`{cmd}` — generic paper dataset of {n} buildings (pre + grades 3, 4, 5), generated with the
patterns and with `--damage physics` (grades 4-5 by rigid-body collapse) in one run, each by
{args.jobs} generator processes at once (`generate_scenes.py --jobs`); {machine()}.

{t1}

Standing: share of the footprint (0.5 m cells) whose highest non-debris surface keeps ≥ 80 %
of its pre-event height. Debris / catalogue: the envelope volume of the building's debris faces
above what still stands under them (or the ground) against solid fraction (0.225 masonry, 0.15 RC) × bulking 1.5 × the pre-event
volume over the cells that no longer stand (catalogue ranges: 0.15-0.30 / 0.10-0.20, 1.3-1.7,
so 0.6-2.0 × is within them).

{t2}
""")


if __name__ == "__main__":
    main()
