#!/usr/bin/env python3
"""Does the shipped model transfer to data QuakeScan did not make? One command from nothing.

    .venv/bin/python bench/bench_transfer.py [--work out/bench_transfer] [--model MODEL.skops]

Rows (the shipped model only, nothing trained on the test data):

- real no-change pairs: the real AHN3 Delft tiles (`../shared/data/ahn3_cropped_*.laz`, real
  footprints) split into two random halves (numpy `default_rng(5).random(n) < 0.5`, one half
  pre, the other post), and each tile against itself thinned to 25 % (`default_rng(5)`):
  the share of assessable buildings called damaged (target <= 1 %);
- a held-out simulated city: region-specific (L'Aquila-like) buildings with the paper's class
  mix (35 / 19 / 32 / 35), a generator seed no training city has, acquired with the *preset*
  sensors (the training set only ever saw randomised ones): DIM pair, ULS pair, ALS-like pre +
  DIM post, ALS-like pre + ULS post; overall accuracy, F1 per grade, damaged vs undamaged;
- the shipped model's own held-out score (cross-validation holding out cities, provenance).

Every row also runs the previous shipped model (the paper's generic-ULS forest, from git)
on the same clouds in the same run ("before"). Each classification goes through
`quakescan classify` (`quakescan.assessment.run.classify`) and reports its describe and total seconds.

Ablation (same run, same test rows): the model's classifier refitted on the training set's
tables without each descriptor group, and the other classifier candidates, scored on the
simulated test pairs and the real no-change pairs. Needs the training set of the shipped
model (`--training-work`, default out/default_model; built when missing).

Writes the tables to stdout, BENCHMARKS.md (section "transfer") and WORK/results.json.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, peak_rss_mb, table, write_section  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
PREVIOUS_MODEL_COMMIT = "14370f2"  # main before the transfer work: the paper's generic-ULS forest
TEST_MIX = {0: 35, 3: 19, 4: 32, 5: 35}
TEST_SEED = 90_001


def real_pairs(work: Path) -> list:
    """(name, pre, post) LAS files of the real no-change pairs, written once."""
    import laspy

    out = []
    for tile in (1, 2):
        src = SHARED / f"ahn3_cropped_{tile}.laz"
        if not src.is_file():
            print(f"skipping {src}: missing", flush=True)
            continue
        las = laspy.read(src)
        n = len(las.points)
        half = np.random.default_rng(5).random(n) < 0.5
        thin = np.random.default_rng(5).random(n) < 0.25
        for name, a, b in ((f"AHN3 tile {tile}: two random halves", half, ~half),
                           (f"AHN3 tile {tile}: tile vs itself thinned to 25 %", np.ones(n, bool), thin)):
            tag = f"ahn{tile}_{'halves' if 'halves' in name else 'thin25'}"
            paths = []
            for role, mask in (("pre", a), ("post", b)):
                p = work / "real" / f"{tag}_{role}.las"
                if not p.is_file():
                    p.parent.mkdir(parents=True, exist_ok=True)
                    sub = laspy.LasData(las.header)
                    sub.points = las.points[mask]
                    sub.write(p.with_name(p.name + ".part.las"))
                    p.with_name(p.name + ".part.las").replace(p)
                paths.append(p)
            out.append((name, tag, *paths))
    return out


def test_city(work: Path, realistic: bool = False) -> tuple:
    """The held-out city's scenes and its preset-acquired clouds: {name: (pre, post)}.
    `realistic`: the same city with roof and facade detail, trees, hedges, cars and street
    furniture (the generator's `typical`), to be labelled through its footprints."""
    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.generator import GenerationSpec, generate

    city = work / ("test_city_realistic" if realistic else "test_city")
    look = {"details": "typical", "streetscape": "typical"} if realistic else {}
    generate(GenerationSpec("region", "mixed", None, TEST_SEED, city, grade_mix=TEST_MIX, force=True, **look))
    work = work / "realistic" if realistic else work
    acq = {"uls": Acquisition("uls", preset("paper")), "dim": Acquisition("dim", preset_dim("paper")),
           "als": Acquisition("als", preset("als"))}
    clouds = {}
    for kind, seed in (("uls", 11), ("dim", 12), ("als", 13)):
        for scene, k in (("pre", 0), ("post", 1)):
            if kind == "als" and scene == "post":
                continue
            p = work / "clouds" / f"{scene}_{kind}.las"
            p.parent.mkdir(parents=True, exist_ok=True)
            acquire(city / scene, acq[kind], p, seed=seed * 10 + k)
            clouds[(scene, kind)] = p
    pairs = {"DIM pair": ("dim", "dim"), "ULS pair": ("uls", "uls"), "ALS-like pre + DIM post": ("als", "dim"),
             "ALS-like pre + ULS post": ("als", "uls")}
    return city, {name: (clouds[("pre", a)], clouds[("post", b)]) for name, (a, b) in pairs.items()}


def previous_model(work: Path) -> Path | None:
    out = work / "previous_model.skops"
    if out.is_file():
        return out
    try:
        blob = subprocess.run(["git", "-C", str(ROOT), "show", f"{PREVIOUS_MODEL_COMMIT}:core/data/default_model.skops"],
                              capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        print("previous model: not available (no git history)", flush=True)
        return None
    out.write_bytes(blob)
    return out


def run_classify(pre, post, out_dir, model, footprints=None):
    from quakescan.assessment.run import classify

    t0 = time.perf_counter()
    summary = classify(pre, post, out_dir, model_path=model, footprints_path=footprints, write_las=False,
                       force=True)  # timed: never an up-to-date skip
    return summary, time.perf_counter() - t0


def classify_and_evaluate(pre, post, out_dir, model, truth_city, footprints=None) -> tuple:
    """(summary, seconds, Evaluation): the pair classified into `out_dir` (`run_classify`) and
    its buildings.csv scored against the grades of `truth_city`'s post-event scene."""
    from quakescan.results.evaluation import evaluate_files

    summary, secs = run_classify(pre, post, out_dir, model, footprints=footprints)
    return summary, secs, evaluate_files(Path(out_dir) / "buildings.csv", Path(truth_city) / "post")


def flagged(csv_path: Path) -> tuple:
    import csv

    rows = list(csv.DictReader(open(csv_path)))
    ok = [r for r in rows if r["assessable"] == "1"]
    damaged = [r for r in ok if int(r["predicted_grade"]) > 0]
    return len(damaged), len(ok), len(rows)


def main(argv=None) -> int:
    from quakescan.learning.default_model import DEFAULT_MODEL
    from quakescan.learning.model import load_model

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_transfer"))
    p.add_argument("--model", default=str(DEFAULT_MODEL))
    p.add_argument("--training-work", default=str(ROOT / "out" / "default_model"),
                   help="make_default_model's working folder: its training set(s), built when missing")
    p.add_argument("--also", action="append", default=[], metavar="LABEL=MODEL",
                   help="another model to run on the same clouds, reported beside the shipped one (repeatable)")
    p.add_argument("--no-realistic", action="store_true",
                   help="skip the held-out city made realistic (roof detail, trees, cars; labelled by footprints)")
    p.add_argument("--no-ablation", action="store_true", help="skip the ablation (needs the training set)")
    p.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    a = p.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    model_path = Path(a.model)
    model = load_model(model_path)
    models = {"shipped": model_path}
    prev = previous_model(work)
    if prev is not None:
        models["before"] = prev
    for item in a.also:
        label, _, path = item.partition("=")
        if not path or not Path(path).is_file():
            p.error(f"--also {item!r}: expected LABEL=MODEL with an existing model file")
        models[label] = Path(path)
    results = {"model": str(model_path), "provenance": model.provenance, "models": list(models),
               "provenances": {k: load_model(v).provenance.get("dataset", "") for k, v in models.items()},
               "real": [], "simulated": []}

    print("real no-change pairs", flush=True)
    fp = SHARED / "ahn3_footprints_rd.geojson"
    real = real_pairs(work)
    for name, tag, pre, post in real:
        row = {"case": name}
        for label, mp in models.items():
            summary, secs = run_classify(pre, post, work / "results" / label / tag, mp, footprints=fp)
            dmg, ok, n = flagged(work / "results" / label / tag / "buildings.csv")
            row[label] = {"damaged": dmg, "assessable": ok, "buildings": n, "seconds": round(secs, 1),
                          "describe_s": summary["seconds"]["describe"]}
            print(f"  {name} [{label}]: {dmg} of {ok} assessable called damaged ({n} footprints), {secs:.0f} s",
                  flush=True)
        results["real"].append(row)

    print("held-out simulated city", flush=True)
    city, pairs = test_city(work)
    cases = [(name, pre, post, city, None) for name, (pre, post) in pairs.items()]
    if not a.no_realistic:
        from quakescan.learning.trainset import scene_footprints

        real_city, real_city_pairs = test_city(work, realistic=True)
        cases += [(f"realistic city: {name}", pre, post, real_city, scene_footprints(real_city))
                  for name, (pre, post) in real_city_pairs.items()]
    for name, pre, post, truth_city, footprints in cases:
        row = {"case": name}
        for label, mp in models.items():
            tag = name.replace(" ", "_").replace("+", "").replace("-", "").replace(":", "")
            summary, secs, ev = classify_and_evaluate(pre, post, work / "results" / label / tag, mp, truth_city,
                                                      footprints=footprints)
            f1s = ", ".join(f"{g}: {100 * m['f1']:.0f}" for g, m in ev.per_grade.items())
            row[label] = {"overall_accuracy": ev.overall_accuracy, "n": ev.n, "not_assessable": ev.not_assessable,
                          "f1": {str(g): m["f1"] for g, m in ev.per_grade.items()}, "damaged_f1": ev.damaged["f1"],
                          "seconds": round(secs, 1), "describe_s": summary["seconds"]["describe"]}
            print(f"  {name} [{label}]: OA {100 * ev.overall_accuracy:.1f} % on {ev.n} "
                  f"(F1 {f1s}; "
                  f"damaged {100 * ev.damaged['f1']:.1f}), {secs:.0f} s", flush=True)
        results["simulated"].append(row)

    if not a.no_ablation:
        results["ablation"] = ablation(work, model, Path(a.training_work), city, pairs, real)

    results["seconds"] = round(time.perf_counter() - t_start, 1)
    results["peak_mib"] = round(peak_rss_mb())
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    text = report(results, a)
    print(text)
    if not a.no_write:
        write_section("transfer", text)
    return 0


def _pct(v):
    return f"{100 * v:.1f}"


def report(res: dict, args) -> str:
    prov = res["provenance"]
    lines = ["## Transfer to data QuakeScan did not make (`bench/bench_transfer.py`)", "",
             f"Machine: {machine()}. Command: `.venv/bin/python bench/bench_transfer.py`; "
             f"{res['seconds'] / 60:.1f} min from nothing but the shipped model's training set, peak "
             f"{res['peak_mib']:,} MiB. Model: {prov.get('dataset', '?')}; classifier "
             f"{prov.get('classifier_selection', {}).get('chosen', '?')}. \"before\" = the previous shipped "
             f"model (commit {PREVIOUS_MODEL_COMMIT}, the paper's generic-ULS forest) on the same clouds.", ""]
    for label in res.get("models", []):
        if label not in ("shipped", "before"):
            lines += [f"\"{label}\": {res['provenances'].get(label, '')}", ""]
    rows = []
    for r in res["real"]:
        cells = [r["case"], "<= 1 %"]
        for label in res["models"]:
            m = r.get(label)
            cells.append("—" if m is None else f"{_pct(m['damaged'] / max(m['assessable'], 1))} % "
                         f"({m['damaged']}/{m['assessable']})")
        m = r["shipped"]
        cells.append(f"{m['describe_s']:.1f} / {m['seconds']:.1f}")
        rows.append(cells)
    lines += ["Real no-change pairs (real footprints): share of assessable buildings called damaged.", "",
              table(["case", "target", *res["models"], "describe / classify s (shipped)"], rows), ""]
    targets = {"DIM pair": "OA >= 85 %, every F1 >= 80, damaged F1 >= 95", "ULS pair": "OA >= 90 %",
               "ALS-like pre + DIM post": "OA >= 80 %", "ALS-like pre + ULS post": "—"}
    rows = []
    for r in res["simulated"]:
        for label in res["models"]:
            m = r.get(label)
            if m is None:
                continue
            rows.append([r["case"] if label == "shipped" else "", label, targets.get(r["case"].removeprefix(
                "realistic city: "), "") if label == "shipped"
                         else "", f"{_pct(m['overall_accuracy'])}", *(f"{100 * m['f1'][g]:.0f}" for g in ("0", "3", "4", "5")),
                         f"{100 * m['damaged_f1']:.1f}", f"{m['n']} ({m['not_assessable']})",
                         f"{m['describe_s']:.1f} / {m['seconds']:.1f}"])
    lines += [f"Held-out simulated region-specific city (seed {TEST_SEED}, 121 buildings, the paper's mix "
              "35/19/32/35), preset sensors (paper ULS, paper DIM, `als` preset): overall accuracy %, F1 % per "
              "grade, damaged vs undamaged F1 %. \"realistic city\": the same city with the generator's typical "
              "roof and facade detail, trees, hedges, cars and street furniture, its buildings labelled through "
              "its footprints as real clouds are.", "",
              table(["pair", "model", "target", "OA", "F1 0", "F1 3", "F1 4", "F1 5", "F1 damaged",
                     "assessed (not)", "describe / classify s"], rows), ""]
    lines += [f"Shipped model on its own held-out set (cross-validation holding out whole cities, pooled "
              f"out-of-fold predictions): overall accuracy {_pct(prov.get('test_overall_accuracy', float('nan')))} %.",
              ""]
    sel = prov.get("classifier_selection", {})
    if sel.get("table"):
        lines += ["Classifier candidates on the training set (the same cross-validation):", "", sel["table"], ""]
    ab = res.get("ablation")
    if ab:
        lines += [ab["text"], ""]
    return "\n".join(lines)


# Ablation -----------------------------------------------------------------------------

GROUPS = {
    "2.5-D lowering (s_lowered_*, s_volume_*, s_height_ratio_*)": lambda n: n.startswith(("s_lowered", "s_volume",
                                                                                           "s_height_ratio")),
    "raised share (s_raised)": lambda n: n == "s_raised",
    "debris ring (s_debris_*)": lambda n: n.startswith("s_debris"),
    "post-event gaps (s_post_gap)": lambda n: n == "s_post_gap",
    "seen through the roof (s_see_through)": lambda n: n == "s_see_through",
    "interior seen through openings (s_interior_seen)": lambda n: n == "s_interior_seen",
    "M3C2 shares (m_changed, m_lost, m_roof/wall_changed)": lambda n: n in ("m_changed", "m_lost", "m_roof_changed",
                                                                             "m_wall_changed"),
    "upper/lower storeys (m_upper_changed, m_lower_changed)": lambda n: n in ("m_upper_changed", "m_lower_changed"),
    "direction (m_inward, m_outward)": lambda n: n in ("m_inward", "m_outward"),
    "coherence (m_coherent, m_largest_patch)": lambda n: n in ("m_coherent", "m_largest_patch"),
    "M3C2 distances and LoD (m_distance_*, m_lod_median)": lambda n: n.startswith(("m_distance", "m_lod")),
}


def _describe_rows(pre, post, settings, footprints=None, limits=None):
    """Assessable rows of a pair; `limits`: the shipped model's pipeline settings, whose
    density and coverage limits decide what is assessable (as classify does)."""
    from quakescan.change.pipeline import describe_pair, quality_gate
    from quakescan.formats.pair import load_pair

    data = load_pair(pre, post, footprints)
    rows = describe_pair(data.pre, data.post, settings)
    if limits is not None:
        rows = [quality_gate(r, limits) for r in rows]
    return [r for r in rows if r.assessable]


def plan_size(provenance: dict) -> str:
    """The training plan's size a model was made with ("full" for files older than the key,
    read from the plan's name "default-SIZE+..." where it is there)."""
    if provenance.get("size"):
        return str(provenance["size"])
    m = re.match(r"transfer training set 'default-(\w+)", str(provenance.get("dataset", "")))
    return m.group(1) if m else "full"


def training_variants(tab) -> dict:
    """Masks of the training rows without one source of variety each (the shipped model's
    configuration is refitted on each): what every part of the training set buys."""
    from quakescan.learning.trainset import PHYSICS_TWINS

    city = tab.pair_city.astype(str)
    twin = np.char.endswith(city, "-physics")
    first_twins = np.isin(city, [f"{n}-physics" for n in PHYSICS_TWINS["full"]])
    variants = {}
    if (twin & ~first_twins).any():
        variants["without the physics twins of the added cities (" + ", ".join(
            sorted({c.removesuffix("-physics") for c in city[twin & ~first_twins]})) + ")"] = ~(twin & ~first_twins)
    if twin.any():
        variants["without any physics twin"] = ~twin
    real = np.char.endswith(city, "-real")
    if real.any():
        variants["without the realistic scenes"] = ~real
    rotterdam = np.char.startswith(city, "rotterdam")
    if rotterdam.any():
        variants["without the Rotterdam buildings"] = ~rotterdam
    paper = np.array([re.search(r"_p\d", c) is not None for c in city], dtype=bool)
    if paper.any():
        variants["without the paper-design cities"] = ~paper
    return variants


def ablation(work: Path, model, training_work: Path, city: Path, pairs: dict, real: list) -> dict:
    """Refit the shipped classifier without each descriptor group (and the other candidates)
    on the training set; score all on the same test rows."""
    from quakescan.change.pipeline import descriptor_matrix
    from quakescan.learning.prediction import model_settings
    from quakescan.learning.default_model import CANDIDATES, TABLE_SETTINGS, cv_groups, training_rows, transfer_training_table
    from quakescan.learning.model import fit_classifier
    from quakescan.results.evaluation import evaluate_grades, read_truth

    print("ablation: training set and test descriptor tables", flush=True)
    t0 = time.perf_counter()
    # the rows the shipped model was fitted on: damage its acquisition did not see left out
    tab = training_rows(transfer_training_table(training_work, seed=model.provenance.get("seed", 0) or 0,
                                                size=plan_size(model.provenance),
                                                scenes=model.provenance.get("scenes", "clean"),
                                                damage=model.provenance.get("damage", "patterns"),
                                                small=model.provenance.get("small_buildings", False))[1])
    names = tab.names
    truth = read_truth(city / "post")
    limits = model_settings(model)
    tests = {}
    for name, (pre, post) in pairs.items():
        rows = [r for r in _describe_rows(pre, post, TABLE_SETTINGS, limits=limits) if r.building_id in truth]
        tests[name] = (descriptor_matrix(rows, names), np.array([truth[r.building_id] for r in rows]))
    fp = SHARED / "ahn3_footprints_rd.geojson"
    for name, tag, pre, post in real:
        rows = _describe_rows(pre, post, TABLE_SETTINGS, fp, limits=limits)
        tests[name] = (descriptor_matrix(rows, names), None)
    chosen = model.provenance.get("classifier_selection", {}).get("chosen")
    config = next((c for c in CANDIDATES if c["name"] == chosen), CANDIDATES[0])

    def fit_score(cfg, cols):
        args = {k: v for k, v in cfg.items() if k not in ("name", "rule")}
        t = time.perf_counter()
        est = fit_classifier(tab.x[:, cols], tab.y, seed=0, groups=cv_groups(tab) if args.get("calibration") else None,
                             **args)
        fit_s = time.perf_counter() - t
        out = {"fit_s": round(fit_s, 1)}
        for name, (x, y) in tests.items():
            pred = est.predict(x[:, cols])
            if y is None:
                out[name] = float(np.mean(pred > 0)) if len(pred) else float("nan")
            else:
                ev = evaluate_grades(y, pred)
                out[name] = {"oa": ev.overall_accuracy, "f1_3": ev.per_grade[3]["f1"], "damaged_f1": ev.damaged["f1"]}
        return out

    used = [n for n in model.feature_names if n in names]
    base = [names.index(n) for n in used]
    runs = {f"shipped ({config['name']}, its {len(base)} descriptors)": fit_score(config, base)}
    for group, test in GROUPS.items():
        if any(test(n) for n in used):
            runs[f"without {group}"] = fit_score(config, [i for i in base if not test(names[i])])
        else:
            runs[f"with {group}"] = fit_score(config, base + [i for i, n in enumerate(names) if test(n)])
    for cand in CANDIDATES:
        if cand["name"] != config["name"]:
            runs[f"classifier: {cand['name']}"] = fit_score(cand, base)
    full_tab = tab
    for variant, keep in training_variants(tab).items():
        tab = full_tab.subset(keep)
        runs[f"training data: {variant} ({len(tab.y):,} rows)"] = fit_score(config, base)
    tab = full_tab
    sim = list(pairs)
    real_names = [r[0] for r in real]
    head = ["variant", "fit s"] + [f"{n} OA / F1 3" for n in sim] + [f"{n.split(':')[0]}{' halves' if 'halves' in n else ' thin'} dmg %"
                                                                  for n in real_names]
    rows = []
    for variant, r in runs.items():
        rows.append([variant, r["fit_s"]] + [f"{100 * r[n]['oa']:.1f} / {100 * r[n]['f1_3']:.0f}" for n in sim]
                    + [f"{100 * r[n]:.1f}" for n in real_names])
    text = ("Ablation on the same rows (each descriptor group left out, the other classifier candidates, and the "
            "shipped configuration on the training set without one source of variety, refitted "
            f"on the {len(tab.y):,} training rows it was fitted on; {time.perf_counter() - t0:.0f} s; the test rows "
            "assessable within the shipped model's limits): overall accuracy % / heavy F1 % on the simulated pairs, "
            "share called damaged on the real no-change pairs. The shipped row refits the shipped configuration "
            "(the file's calibration folds may differ), so it can differ by a building from the table above."
            "\n\n" + table(head, rows))
    return {"runs": runs, "text": text}


if __name__ == "__main__":
    sys.exit(main())
