#!/usr/bin/env python3
"""Does the shipped model recognise damage made by another procedure? One command from nothing.

    .venv/bin/python bench/bench_damage_transfer.py [--work out/bench_damage_transfer] [--model MODEL]

The shipped model learned damage from the add-on's parametric patterns and from four
physics twins (a model trained on patterns only is asked with --model). The held-out
city of `bench_transfer.py` (region-specific buildings, the paper's mix 35/19/32/35, generator
seed 90001, never in training) is generated twice: once with the patterns, once with its
grade-4 and grade-5 buildings collapsed by rigid-body simulation (`--damage physics`:
fracture where the grade removes support, settling under gravity; a collapse that does not
come to rest falls back to the patterns and is counted). Same buildings, same grades, same
preset sensors (paper ULS, paper DIM) and seeds: any difference between the two rows is the
damage procedure. Overall accuracy, F1 per grade and damaged vs undamaged for each.

Then the cross-generator table: the shipped classifier configuration refitted on (a) four
mixed training cities made with the patterns, (b) their physics twins (`quakescan.learning.trainset`
PHYSICS_TWINS: the same buildings, grades and acquisitions, grades 4-5 collapsed by
simulation), (c) both, (d) the shipped model's training plan (bare and realistic scenes)
without physics twins, (e) with the full plan's four and (f) with every twin of its plan,
each scored on the same described rows of the four held-out pairs
(patterns and physics city, ULS and DIM). Builds the twins' training tables under
--training-work when missing (resumable; ~8 s of Blender per collapsed building).

Writes the tables to stdout, BENCHMARKS.md (section "damage transfer") and WORK/results.json.
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
from bench_transfer import TEST_MIX, TEST_SEED, _describe_rows, classify_and_evaluate, plan_size  # noqa: E402

SENSORS = {"ULS pair": ("uls", 11), "DIM pair": ("dim", 12)}


def city(work: Path, damage: str) -> tuple[Path, dict, float, list]:
    """The held-out city made with `damage`, its preset-acquired pairs, the generation seconds
    and the buildings whose collapse fell back to the patterns."""
    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.formats.scene import read_scene
    from quakescan.generator import GenerationSpec, generate

    folder = work / f"city_{damage}"
    t0 = time.perf_counter()
    generate(GenerationSpec("region", "mixed", None, TEST_SEED, folder, grade_mix=TEST_MIX, damage=damage,
                            force=True))
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
    from quakescan.learning.default_model import DEFAULT_MODEL

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_damage_transfer"))
    p.add_argument("--model", default=str(DEFAULT_MODEL))
    p.add_argument("--training-work", default=str(ROOT / "out" / "default_model"),
                   help="the shipped model's training-set folder (make_default_model.py --work)")
    p.add_argument("--no-cross", action="store_true", help="skip the cross-generator table")
    p.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    a = p.parse_args(argv)
    work = Path(a.work)
    t_start = time.perf_counter()
    rows, results = [], {"machine": machine(), "model": a.model, "rows": []}
    tests = {}
    for damage in ("patterns", "physics"):
        folder, pairs, gen_s, fallback = city(work, damage)
        tests[damage] = (folder, pairs)
        print(f"{damage}: city generated in {gen_s:.0f} s; collapses that fell back to the patterns: "
              f"{len(fallback)}", flush=True)
        for name, (pre, post) in pairs.items():
            tag = f"{damage}_{name.replace(' ', '_')}"
            summary, secs, ev = classify_and_evaluate(pre, post, work / "results" / tag, a.model, folder)
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
    cross = None if a.no_cross else cross_generator(Path(a.training_work), a.model, tests)
    if cross:
        results["cross_generator"] = cross["runs"]
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    results["peak_mib"] = round(peak_rss_mb())
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    from quakescan.learning.model import load_model

    trained_on = ("trained on the add-on's patterns and physics twins"
                  if load_model(a.model).provenance.get("damage") == "both"
                  else "trained on the add-on's parametric patterns only")
    fell = {r["damage"]: r["fallback"] for r in results["rows"]}
    gen = {r["damage"]: r["generate_s"] for r in results["rows"]}
    text = "\n".join([
        "## Damage made by another procedure (`bench/bench_damage_transfer.py`)", "",
        f"Machine: {machine()}. Command: `.venv/bin/python bench/bench_damage_transfer.py`; "
        f"{results['seconds'] / 60:.1f} min, of which generating the cities (skipped when their bundles are up to "
        f"date) {gen['patterns']:.0f} s with the patterns and {gen['physics']:.0f} s by physics; peak "
        f"{results['peak_mib']:,} MiB. Model: {Path(a.model).name} ({trained_on}). "
        "The held-out city of bench_transfer (seed "
        f"{TEST_SEED}, 121 buildings, the paper's mix), once with the patterns and once with its grade-4/5 "
        f"buildings collapsed by rigid-body simulation ({fell.get('physics', 0)} collapses did not come to rest "
        "and kept the patterns); paper ULS and DIM presets, same seeds. Overall accuracy %, F1 % per grade, "
        "damaged vs undamaged F1 %.", "",
        table(["damage", "pair", "OA", "F1 0", "F1 3", "F1 4", "F1 5", "F1 damaged", "assessed (not)"], rows)]
        + (["", cross["text"]] if cross else []))
    print(text)
    if not a.no_write:
        write_section("damage transfer", text)
    return 0


def cross_generator(training_work: Path, model_path: str, tests: dict) -> dict:
    """The shipped classifier configuration refitted on training rows made by each damage
    generator (and both), scored on the same described rows of every held-out pair."""
    import numpy as np

    from quakescan.change.pipeline import descriptor_matrix
    from quakescan.learning.prediction import model_settings
    from quakescan.learning.default_model import (CANDIDATES, TABLE_SETTINGS, cv_groups, model_columns, training_rows,
                                    transfer_training_table)
    from quakescan.learning.model import fit_classifier, load_model
    from quakescan.learning.trainset import PHYSICS_TWINS
    from quakescan.results.evaluation import evaluate_grades, read_truth

    t0 = time.perf_counter()
    model = load_model(model_path)
    seed = model.provenance.get("seed", 0) or 0
    print("cross-generator: training tables (the physics twins are generated, acquired and described when missing)",
          flush=True)
    size = plan_size(model.provenance)
    _, whole = transfer_training_table(training_work, seed=seed, size=size, scenes="both", damage="both")
    whole = training_rows(model_columns(whole, model.feature_names))
    pair_city = whole.pair_city.astype(str)
    twins = np.isin(pair_city, [f"{n}-physics" for n in PHYSICS_TWINS["full"]])
    bases = np.isin(pair_city, list(PHYSICS_TWINS["full"]))
    every_twin = np.char.endswith(pair_city, "-physics")
    n_twins = len(set(pair_city[every_twin]))
    t_tables = time.perf_counter() - t0

    rows = whole.subset

    variants = {"patterns: 4 cities": rows(bases), "physics: their 4 twins": rows(twins),
                "both: 4 + 4 twins": rows(bases | twins),
                f"{size} plan, patterns only": rows(~every_twin),
                f"{size} plan + 4 physics twins": rows(~every_twin | twins)}
    if n_twins > 4:
        variants[f"{size} plan + {n_twins} physics twins"] = rows(np.ones(len(whole.y), bool))
    limits = model_settings(model)
    described = {}
    for damage, (folder, pairs) in tests.items():
        truth = read_truth(folder / "post")
        for name, (pre, post) in pairs.items():
            r = [r for r in _describe_rows(pre, post, TABLE_SETTINGS, limits=limits) if r.building_id in truth]
            described[f"{damage} {name.split()[0]}"] = (descriptor_matrix(r, model.feature_names),
                                                        np.array([truth[b.building_id] for b in r]))
    chosen = model.provenance.get("classifier_selection", {}).get("chosen")
    config = next((c for c in CANDIDATES if c["name"] == chosen), CANDIDATES[1])
    args = {k: v for k, v in config.items() if k not in ("name", "rule")}
    runs, lines = {}, []
    for variant, tab in variants.items():
        t = time.perf_counter()
        est = fit_classifier(tab.x, tab.y, seed=0, groups=cv_groups(tab) if args.get("calibration") else None, **args)
        fit_s = time.perf_counter() - t
        runs[variant] = {"rows": int(len(tab.y)), "fit_s": round(fit_s, 1)}
        for test, (x, y) in described.items():
            ev = evaluate_grades(y, est.predict(x))
            f1 = {g: m["f1"] for g, m in ev.per_grade.items()}
            runs[variant][test] = {"oa": ev.overall_accuracy, "f1": {str(g): v for g, v in f1.items()},
                                   "damaged_f1": ev.damaged["f1"]}
            lines.append([variant, f"{len(tab.y):,}", test, f"{100 * ev.overall_accuracy:.1f}",
                          *[("n/a" if f1.get(g) is None else f"{100 * f1[g]:.0f}") for g in (0, 3, 4, 5)],
                          f"{100 * ev.damaged['f1']:.1f}"])
        print(f"  {variant}: {len(tab.y)} rows, fit {fit_s:.0f} s: "
              + ", ".join(f"{k} {100 * v['oa']:.1f}" for k, v in runs[variant].items() if isinstance(v, dict)),
              flush=True)
    mean = [[v, f"{100 * np.mean([r[k]['oa'] for k in described]):.1f}",
             f"{100 * np.mean([r[k]['oa'] for k in described if k.startswith('patterns')]):.1f}",
             f"{100 * np.mean([r[k]['oa'] for k in described if k.startswith('physics')]):.1f}"]
            for v, r in runs.items()]
    text = "\n".join([
        "### Cross-generator table", "",
        f"The shipped configuration ({config['name']}) refitted on each training variant and scored on the same "
        "described rows of the held-out city (assessable within the shipped model's limits); the first three "
        "variants are like for like: four mixed cities (generic_m0/m1, region_m0/m1) with the patterns, their "
        "physics twins (same buildings, grades, acquisitions and seeds; grades 4-5 collapsed by simulation), and "
        "both. Rows left out of training as for the shipped model (damage the acquisition did not see). "
        f"{time.perf_counter() - t0:.0f} s (training tables {t_tables:.0f} s). Overall accuracy %, F1 % per grade, "
        "damaged vs undamaged F1 %.", "",
        table(["trained on", "rows", "tested on", "OA", "F1 0", "F1 3", "F1 4", "F1 5", "F1 damaged"], lines), "",
        "Mean overall accuracy over the four held-out pairs, and per test generator:", "",
        table(["trained on", "mean OA", "patterns city", "physics city"], mean)])
    return {"runs": runs, "text": text}


if __name__ == "__main__":
    raise SystemExit(main())
