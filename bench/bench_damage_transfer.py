#!/usr/bin/env python3
"""Does the shipped model recognise damage made by another procedure? One command from nothing.

    .venv/bin/python bench/bench_damage_transfer.py [--work out/bench_damage_transfer] [--model MODEL]

The shipped model learned damage from the add-on's parametric patterns only. The held-out
city of `bench_transfer.py` (region-specific buildings, the paper's mix 35/19/32/35, generator
seed 90001, never in training) is generated twice: once with the patterns, once with its
grade-4 and grade-5 buildings collapsed by rigid-body simulation (`--damage physics`:
fracture where the grade removes support, settling under gravity; a collapse that does not
come to rest falls back to the patterns and is counted). Same buildings, same grades, same
preset sensors (paper ULS, paper DIM) and seeds: any difference between the two rows is the
damage procedure. Overall accuracy, F1 per grade and damaged vs undamaged for each.

Writes the table to stdout, BENCHMARKS.md (section "damage transfer") and WORK/results.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, peak_rss_mb, table, write_section  # noqa: E402
from bench_transfer import TEST_MIX, TEST_SEED, run_classify  # noqa: E402

SENSORS = {"ULS pair": ("uls", 11), "DIM pair": ("dim", 12)}


def city(work: Path, damage: str) -> tuple[Path, dict, float, list]:
    """The held-out city made with `damage`, its preset-acquired pairs, the generation seconds
    and the buildings whose collapse fell back to the patterns."""
    from core.acquisition import Acquisition, acquire
    from core.demo import generate
    from core.dim import preset_dim
    from core.scene import read_scene
    from core.survey import preset

    folder = work / f"city_{damage}"
    t0 = time.perf_counter()
    generate("region", "mixed", None, TEST_SEED, folder, grade_mix=TEST_MIX, damage=damage)
    seconds = time.perf_counter() - t0
    fallback = []
    if damage != "patterns":
        for b in read_scene(folder / "post").buildings:
            if b.grade >= 4 and "physics_collapse" not in {p["name"] for p in b.patterns}:
                fallback.append(b.id)
    acq = {"uls": Acquisition("uls", preset("paper")), "dim": Acquisition("dim", preset_dim("paper"))}
    pairs = {}
    for name, (kind, seed) in SENSORS.items():
        paths = []
        for scene, k in (("pre", 0), ("post", 1)):
            p = work / "clouds" / damage / f"{scene}_{kind}.las"
            p.parent.mkdir(parents=True, exist_ok=True)
            acquire(folder / scene, acq[kind], p, seed=seed * 10 + k)
            paths.append(p)
        pairs[name] = tuple(paths)
    return folder, pairs, seconds, fallback


def main(argv=None) -> int:
    from core.classify import DEFAULT_MODEL
    from core.evaluate import evaluate_files

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_damage_transfer"))
    p.add_argument("--model", default=str(DEFAULT_MODEL))
    p.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    a = p.parse_args(argv)
    work = Path(a.work)
    t_start = time.perf_counter()
    rows, results = [], {"machine": machine(), "model": a.model, "rows": []}
    for damage in ("patterns", "physics"):
        folder, pairs, gen_s, fallback = city(work, damage)
        print(f"{damage}: city generated in {gen_s:.0f} s; collapses that fell back to the patterns: "
              f"{len(fallback)}", flush=True)
        for name, (pre, post) in pairs.items():
            tag = f"{damage}_{name.replace(' ', '_')}"
            summary, secs = run_classify(pre, post, work / "results" / tag, a.model)
            ev = evaluate_files(work / "results" / tag / "buildings.csv", folder / "post")
            f1 = {g: m["f1"] for g, m in ev.per_grade.items()}
            row = {"damage": damage, "pair": name, "overall_accuracy": ev.overall_accuracy, "n": ev.n,
                   "not_assessable": ev.not_assessable, "f1": {str(g): v for g, v in f1.items()},
                   "damaged_f1": ev.damaged["f1"], "generate_s": round(gen_s, 1), "classify_s": round(secs, 1),
                   "fallback": len(fallback)}
            results["rows"].append(row)
            print(f"  {damage} {name}: OA {100 * ev.overall_accuracy:.1f} % on {ev.n} (F1 "
                  + ", ".join(f"{g}: {100 * v:.0f}" for g, v in f1.items())
                  + f"; damaged {100 * ev.damaged['f1']:.1f}), {secs:.0f} s", flush=True)

            def pct(v):
                return "n/a" if v is None else f"{100 * v:.0f}"

            rows.append([damage, name, f"{100 * ev.overall_accuracy:.1f}",
                         *[pct(f1.get(g)) for g in (0, 3, 4, 5)], f"{100 * ev.damaged['f1']:.1f}",
                         f"{ev.n} ({ev.not_assessable})"])
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    results["peak_mib"] = round(peak_rss_mb())
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    fell = {r["damage"]: r["fallback"] for r in results["rows"]}
    gen = {r["damage"]: r["generate_s"] for r in results["rows"]}
    text = "\n".join([
        "## Damage made by another procedure (`bench/bench_damage_transfer.py`)", "",
        f"Machine: {machine()}. Command: `.venv/bin/python bench/bench_damage_transfer.py`; "
        f"{results['seconds'] / 60:.1f} min, of which generating the cities (skipped when their bundles are up to "
        f"date) {gen['patterns']:.0f} s with the patterns and {gen['physics']:.0f} s by physics; peak "
        f"{results['peak_mib']:,} MiB. Model: {Path(a.model).name} "
        "(trained on the add-on's parametric patterns only). The held-out city of bench_transfer (seed "
        f"{TEST_SEED}, 121 buildings, the paper's mix), once with the patterns and once with its grade-4/5 "
        f"buildings collapsed by rigid-body simulation ({fell.get('physics', 0)} collapses did not come to rest "
        "and kept the patterns); paper ULS and DIM presets, same seeds. Overall accuracy %, F1 % per grade, "
        "damaged vs undamaged F1 %.", "",
        table(["damage", "pair", "OA", "F1 0", "F1 3", "F1 4", "F1 5", "F1 damaged", "assessed (not)"], rows)])
    print(text)
    if not a.no_write:
        write_section("damage transfer", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
