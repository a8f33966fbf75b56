#!/usr/bin/env python3
"""Damage in real points: the shipped model on AHN3 tile 1 with damage injected by `quakescan inject`.

    .venv/bin/python bench/bench_real_damage.py [--work out/bench_real_damage] [--model MODEL.skops]

AHN3 tile 1 (`../shared/data/ahn3_cropped_1.laz`, real footprints) is reserved for
evaluation: nothing is trained or tuned on it. Each case splits it into two random halves
(numpy `default_rng(SPLIT).random(n) < 0.5`: one half pre, the other post, ~4 pts/m² each,
both real) and injects damage into the post half (`quakescan.injection.inject`, its own
seed, among the buildings with at least 200 points in that half; the other buildings stay as
they were). The cases vary what the injector does: the grade mix, the seed (which buildings,
which patterns), the split, patterns or rigid-body collapses for grades 4-5.

Per case: the confusion matrix (truth rows, predicted columns, "n/a" = not assessable), recall
and F1 per grade, damaged vs undamaged, the share of undamaged buildings called damaged, the
damaged buildings reported "no damage" at a confidence of 0.8 or more (in brackets those
whose injected damage moved no return: nothing in the data shows it, and their grade 0 comes
with `walls_resolved` 0 where it lay in walls), and the expected
calibration error of the predicted grade's probability (10 equal bins of confidence over
the assessable buildings: sum of |accuracy - mean confidence| weighted by the bin's share).
Each case is classified three times: with the probabilities counting the damage each
building's data could not show (`quakescan.learning.unseen_damage`, the default), with the
model's own, which assume any damage shows (`unseen_damage=False`), and counting it with the
case's own mix of grades as the prior (`prior=`; the truth's shares, so what a perfect
estimate of the mix would give at best).

No change across sensors on real shapes: the Rotterdam LoD2 buildings (`rotterdam_subset.json`,
its densest cluster as the training set takes it, and every building once per quarter turn
packed on a grid, `rotated_copies`: each alone, no neighbour hiding a gap of its shell) and the
Zurich LoD2 model packed into a city
(`bench_zurich.packed_cityjson`; reserved for evaluation, measured here only), every building
undamaged, acquired before by one of QuakeScan's preset sensors and after by another (ULS →
DIM, DIM → ULS, ALS-like → DIM): the share of assessable buildings called damaged (target
≤ 2 %).

A real archive before, a simulated drone after: the tile's half DRONE_SPLIT before; after,
the paper's ULS and DIM presets flown over the 2.5D surface of the other half
(`quakescan.injection.surface_model`), once as flown (no change: the share called damaged) and
once with DRONE_MIX injected into the drone's returns (the score above).

Low buildings: a city of the generator's small set (garden sheds, garages, Dutch row houses,
small detached houses; seed LOW_SEED, no training city's) with LOW_MIX, acquired by the paper's
ULS and DIM presets: heavy damage F1 there (target ≥ 0.85), where openings in a low roof
lower a large share of a one- or two-storey building.

Writes the tables to stdout, BENCHMARKS.md (section "real_damage") and WORK/results.json.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, peak_rss_mb, table, write_section  # noqa: E402
from bench_zurich import _renumber  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
TILE = SHARED / "ahn3_cropped_1.laz"
FOOTPRINTS = SHARED / "ahn3_footprints_rd.geojson"
GRADES = (0, 3, 4, 5)
# (name, split seed, inject seed, grade mix, damage)
CASES = [
    ("15/15/15, patterns", 5, 101, {3: 15, 4: 15, 5: 15}, "patterns"),
    ("15/15/15, other seeds", 6, 202, {3: 15, 4: 15, 5: 15}, "patterns"),
    ("25 heavy / 10 / 10", 7, 303, {3: 25, 4: 10, 5: 10}, "patterns"),
    ("15/15/15, collapses by physics", 8, 404, {3: 15, 4: 15, 5: 15}, "both"),
]
CONFIDENT = 0.8
# the catalogue's heavy patterns that change the roof, which an airborne sensor sees from above
ROOF_PATTERNS = {"roof_holes", "chimney_loss", "parapet_loss"}
LOW_SEED = 98_001
LOW_MIX = {0: 20, 3: 20, 4: 20, 5: 20}
CROSS_PAIRS = {"ULS → DIM": ("uls", "dim"), "DIM → ULS": ("dim", "uls"), "ALS-like → DIM": ("als", "dim")}
CROSS_SEEDS = {"uls": 31, "dim": 32, "als": 33}
# Rotterdam's buildings once per quarter turn, packed on a grid with streets between them:
# each stands alone, so no neighbour in the file hides what a sensor sees of it
ROTATIONS = (0, 1, 2, 3)
ECE_BINS = 10
# a real archive before, a simulated drone after: tile 1's half DRONE_SPLIT before, a drone
# flown over the 2.5D surface of the other half (`injection.surface_model`), damage injected
# into the drone's returns
DRONE_SPLIT, DRONE_SEED = 9, 909
DRONE_MIX = {3: 15, 4: 15, 5: 15}
DRONE_SENSORS = ("ULS", "DIM")


def halves(work: Path, split: int) -> tuple[Path, Path]:
    import laspy

    pre, post = work / "real" / f"tile1_split{split}_pre.las", work / "real" / f"tile1_split{split}_post.las"
    if not (pre.is_file() and post.is_file()):
        las = laspy.read(TILE)
        half = np.random.default_rng(split).random(len(las.points)) < 0.5
        for path, mask in ((pre, half), (post, ~half)):
            path.parent.mkdir(parents=True, exist_ok=True)
            sub = laspy.LasData(las.header)
            sub.points = las.points[mask]
            tmp = path.with_name(path.name + ".part.las")
            sub.write(tmp)
            tmp.replace(path)
    return pre, post


def score(result_csv: Path, truth_csv: Path, every_building: bool = False) -> dict:
    from quakescan.results.evaluation import to_target_grade

    truth = {int(r["building_id"]): int(to_target_grade(np.array([int(r["grade"])]))[0])
             for r in csv.DictReader(open(truth_csv))}
    rows = list(csv.DictReader(open(result_csv)))
    injected_or_big = set(truth) if every_building else {
        int(r["building_id"]) for r in csv.DictReader(open(truth_csv)) if int(r["injected"]) or int(r["n_points"]) >= 200}
    cols = list(GRADES) + ["n/a"]
    confusion = {g: {c: 0 for c in cols} for g in GRADES}
    # quiet misses whose damage moved no return at all: the data hold no trace of it
    conf, correct, quiet_misses, unseen_misses = [], [], [], []
    # heavy damage that shows on the roof (an airborne sensor can see it) and on walls only
    truth_rows = {int(r["building_id"]): r for r in csv.DictReader(open(truth_csv))}
    heavy_seen = {"roof": [0, 0], "walls only": [0, 0]}  # [graded damaged, of]
    heavy_graded_heavy = {"roof": 0, "walls only": 0}
    for r in rows:
        b = int(r["building_id"])
        if b not in injected_or_big:  # small buildings the injector never draws: not part of the test
            continue
        t = truth.get(b, 0)
        if r["assessable"] != "1":
            confusion[t]["n/a"] += 1
            continue
        g = int(r["predicted_grade"])
        confusion[t][g if g in GRADES else 0] += 1
        if t == 3 and "patterns" in truth_rows.get(b, {}):
            kind = "walls only" if not set(truth_rows[b]["patterns"].split()) & ROOF_PATTERNS else "roof"
            heavy_seen[kind][0] += g > 0
            heavy_seen[kind][1] += 1
            heavy_graded_heavy[kind] += g == 3
        c = float(r["confidence"]) if r.get("confidence") else 1.0
        conf.append(c)
        correct.append(g == t)
        if t > 0 and g == 0 and c >= CONFIDENT:
            quiet_misses.append(b)
            if int(truth_rows.get(b, {}).get("moved") or 0) == 0:
                unseen_misses.append(b)
    per_grade = {}
    for g in GRADES:
        tp = confusion[g][g]
        n_true = sum(confusion[g][c] for c in GRADES)
        n_pred = sum(confusion[t][g] for t in GRADES)
        rec = tp / n_true if n_true else float("nan")
        prec = tp / n_pred if n_pred else float("nan")
        f1 = 2 * tp / (n_true + n_pred) if n_true + n_pred else float("nan")
        per_grade[g] = {"recall": rec, "precision": prec, "f1": f1, "n": n_true}
    undamaged = sum(confusion[0][c] for c in GRADES)
    false_alarms = sum(confusion[0][c] for c in GRADES if c > 0)
    damaged_true = sum(confusion[t][c] for t in GRADES if t > 0 for c in GRADES)
    damaged_found = sum(confusion[t][c] for t in GRADES if t > 0 for c in GRADES if c > 0)
    return {"confusion": {str(g): {str(c): n for c, n in row.items()} for g, row in confusion.items()},
            "per_grade": {str(g): v for g, v in per_grade.items()},
            "undamaged_called_damaged": false_alarms / undamaged if undamaged else float("nan"),
            "damaged_found": damaged_found / damaged_true if damaged_true else float("nan"),
            "quiet_misses": quiet_misses, "quiet_misses_no_return_moved": unseen_misses, "ece": expected_calibration_error(np.array(conf), np.array(correct)),
            "heavy_seen": heavy_seen, "heavy_graded_heavy": heavy_graded_heavy}


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = ECE_BINS) -> float:
    from quakescan.learning.reliability import calibration_error

    return calibration_error(confidence, correct, bins)


def real_shape_scenes(work: Path) -> dict:
    """{name: scene bundle folder} of the undamaged real-shape cities."""
    from bench_zurich import ZURICH, packed_cityjson
    from quakescan.formats.cityjson import IMPORT_VERSION, import_cityjson
    from quakescan.formats.scene import write_scene
    from quakescan.learning.trainset import densest_cluster

    out = {}
    rotterdam, zurich = SHARED / "rotterdam_subset.json", ZURICH
    if rotterdam.is_file():
        folder = work / "shapes" / f"rotterdam_v{IMPORT_VERSION}"  # another importer, another scene
        if not (folder / "scene.json").is_file():
            write_scene(densest_cluster(import_cityjson(rotterdam)), folder)
        out["Rotterdam"] = folder
        folder = work / "shapes" / f"rotterdam_packed_v{IMPORT_VERSION}"
        if not (folder / "scene.json").is_file():
            rotated = work / "shapes" / "rotterdam_rotated.city.json"
            rotated_copies(rotterdam, rotated)
            packed_cityjson(rotated, work / "shapes" / "rotterdam_packed.city.json")
            write_scene(import_cityjson(work / "shapes" / "rotterdam_packed.city.json"), folder)
        out["Rotterdam packed"] = folder
    if zurich.is_file():
        folder = work / "shapes" / f"zurich_v{IMPORT_VERSION}"
        if not (folder / "scene.json").is_file():
            packed_cityjson(zurich, work / "shapes" / "zurich_packed.city.json")
            write_scene(import_cityjson(work / "shapes" / "zurich_packed.city.json"), folder)
        out["Zurich"] = folder
    return out


def rotated_copies(src: Path, dst: Path, turns=ROTATIONS) -> int:
    """The CityJSON `src` with every city object copied once per quarter turn in `turns`
    (integer vertices rotated about the origin: exact), IDs suffixed "-r<turn>"; written to
    `dst` for `bench_zurich.packed_cityjson`. Returns the number of objects."""
    doc = json.loads(src.read_text())
    verts = np.asarray(doc["vertices"], dtype=np.int64)
    objs = doc["CityObjects"]
    new_verts, new_objs = [], {}
    for turn in turns:
        v = verts.copy()
        for _ in range(turn):
            v = np.column_stack([-v[:, 1], v[:, 0], v[:, 2]])
        base = len(new_verts)
        new_verts += v.tolist()
        for k, o in objs.items():
            o = json.loads(json.dumps(o))
            for g in o.get("geometry", []):
                g["boundaries"] = _renumber(g["boundaries"], lambda i, base=base: i + base)
            for key in ("parents", "children"):
                if key in o:
                    o[key] = [f"{c}-r{turn}" for c in o[key]]
            o.pop("geographicalExtent", None)
            new_objs[f"{k}-r{turn}"] = o
    doc["vertices"], doc["CityObjects"] = new_verts, new_objs
    doc["transform"]["translate"] = [0.0, 0.0, doc["transform"]["translate"][2]]
    doc.pop("metadata", None)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(doc))
    return len(new_objs)


def no_change_across_sensors(work: Path, model: str) -> list:
    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.assessment.run import classify

    acq = {"uls": Acquisition("uls", preset("paper")), "dim": Acquisition("dim", preset_dim("paper")),
           "als": Acquisition("als", preset("als"))}
    rows = []
    for city, scene in real_shape_scenes(work).items():
        for name, (a, b) in CROSS_PAIRS.items():
            clouds = []
            for role, kind in (("pre", a), ("post", b)):
                path = work / "shapes" / "clouds" / f"{city}_{role}_{kind}.las"
                path.parent.mkdir(parents=True, exist_ok=True)
                acquire(scene, acq[kind], path, seed=CROSS_SEEDS[kind] * 10 + (role == "post"))
                clouds.append(path)
            out = work / "shapes" / "results" / f"{city}_{a}_{b}"
            classify(*clouds, out, model_path=model, write_las=False, force=True)
            res = list(csv.DictReader(open(out / "buildings.csv")))
            ok = [r for r in res if r["assessable"] == "1"]
            flagged = [r for r in ok if int(r["predicted_grade"]) > 0]
            rows.append({"city": city, "pair": name, "damaged": len(flagged), "assessable": len(ok),
                         "buildings": len(res), "grades": sorted(int(r["predicted_grade"]) for r in flagged)})
            print(f"{city} {name}: {len(flagged)} of {len(ok)} assessable called damaged", flush=True)
    return rows


def low_buildings(work: Path, model: str) -> list:
    """Per preset pair of the small-building city: the confusion and F1 per grade."""
    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.generator import GenerationSpec, generate
    from quakescan.assessment.run import classify
    from quakescan.learning.trainset import scene_footprints

    city = work / "low" / "city"
    generate(GenerationSpec("small", "mixed", None, LOW_SEED, city, grade_mix=LOW_MIX))
    rows = []
    for kind, acq in (("ULS", Acquisition("uls", preset("paper"))), ("DIM", Acquisition("dim", preset_dim("paper")))):
        clouds = []
        for k, scene in enumerate(("pre", "post")):
            path = work / "low" / "clouds" / f"{scene}_{kind.lower()}.las"
            path.parent.mkdir(parents=True, exist_ok=True)
            acquire(city / scene, acq, path, seed=41 + 10 * k + (kind == "DIM"))
            clouds.append(path)
        out = work / "low" / "results" / kind
        classify(*clouds, out, model_path=model, footprints_path=scene_footprints(city), write_las=False, force=True)
        truth = work / "low" / "truth.csv"
        from quakescan.formats.scene import read_scene

        truth.write_text("building_id,grade\n" + "".join(f"{b.id},{b.grade}\n" for b in read_scene(city / "post").buildings))
        s = score(out / "buildings.csv", truth, every_building=True)
        s["pair"] = f"{kind} pair"
        rows.append(s)
        print(f"low buildings, {kind} pair: F1 " + ", ".join(f"{g}: {100 * v['f1']:.0f}" for g, v in s["per_grade"].items()),
              flush=True)
    return rows


def drone_after_archive(work: Path, model: str, sensors=DRONE_SENSORS) -> list:
    """Per drone sensor: the real half before, the drone after with no damage (the share of
    buildings called damaged) and with DRONE_MIX injected (`score`)."""
    import laspy

    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.formats.footprints import read_footprints
    from quakescan.injection.inject import InjectSettings, inject
    from quakescan.injection.surface_model import surface_scene
    from quakescan.assessment.run import classify

    pre, other = halves(work, DRONE_SPLIT)
    las = laspy.read(other)
    xyz = np.c_[las.x, las.y, las.z]
    origin = np.r_[np.floor(xyz[:, :2].min(axis=0)), 0.0]
    t0 = time.perf_counter()
    scene = surface_scene(xyz, np.asarray(las.classification), read_footprints(FOOTPRINTS), origin, crs="EPSG:28992")
    t_scene = time.perf_counter() - t0
    acq = {"ULS": Acquisition("uls", preset("paper")), "DIM": Acquisition("dim", preset_dim("paper"))}
    rows = []
    for k, kind in enumerate(sensors):
        flown = work / "drone" / f"after_{kind.lower()}.las"
        flown.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        acquire(scene, acq[kind], flown, seed=DRONE_SEED + k)
        t_fly = time.perf_counter() - t0
        quiet = work / "drone" / "results" / f"{kind.lower()}_no_change"
        classify(pre, flown, quiet, model_path=model, footprints_path=FOOTPRINTS, write_las=False, force=True)
        graded = [r for r in csv.DictReader(open(quiet / "buildings.csv")) if r["assessable"] == "1"]
        flagged = sorted(int(r["predicted_grade"]) for r in graded if int(r["predicted_grade"]) > 0)
        inj = inject(flown, FOOTPRINTS, work / "drone" / "inject" / kind.lower(),
                     InjectSettings(seed=DRONE_SEED, grade_mix=DRONE_MIX))
        out = work / "drone" / "results" / kind.lower()
        classify(pre, inj.post, out, model_path=model, footprints_path=FOOTPRINTS, write_las=False, force=True)
        s = score(out / "buildings.csv", inj.truth)
        s.update({"pair": f"real half → {kind} over its other half", "no_change_damaged": len(flagged),
                  "no_change_assessable": len(graded), "no_change_grades": flagged, "moved": inj.counts["moved"],
                  "points_after": int(laspy.open(flown).header.point_count), "scene_s": round(t_scene, 1),
                  "fly_s": round(t_fly, 1), "scene_faces": int(len(scene.faces))})
        rows.append(s)
        f1 = ", ".join(f"{g}: {100 * v['f1']:.0f}" for g, v in s["per_grade"].items())
        print(f"drone after archive, {kind}: no change {len(flagged)} of {len(graded)} called damaged; "
              f"damage F1 {f1}; ECE {s['ece']:.3f}", flush=True)
    return rows


def main(argv=None) -> int:
    from quakescan.injection.inject import InjectSettings, inject
    from quakescan.assessment.run import classify
    from quakescan.learning.default_model import DEFAULT_MODEL

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_real_damage"))
    p.add_argument("--model", default=str(DEFAULT_MODEL))
    p.add_argument("--cases", default=None, help="comma-separated case numbers (1-based) to run (default all)")
    p.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    p.add_argument("--no-shapes", action="store_true", help="skip the no-change rows across sensors on real shapes")
    p.add_argument("--no-low", action="store_true", help="skip the small-building city")
    p.add_argument("--no-drone", action="store_true", help="skip the real archive before, simulated drone after")
    a = p.parse_args(argv)
    if not TILE.is_file():
        print(f"skipping: {TILE} is missing", file=sys.stderr)
        return 0
    work = Path(a.work)
    t_start = time.perf_counter()
    chosen = [CASES[int(k) - 1] for k in a.cases.split(",")] if a.cases else CASES
    results = {"model": str(a.model), "machine": machine(), "cases": []}
    for name, split, seed, mix, damage in chosen:
        pre, post = halves(work, split)
        tag = f"split{split}_seed{seed}"
        t0 = time.perf_counter()
        inj = inject(post, FOOTPRINTS, work / "inject" / tag,
                     InjectSettings(seed=seed, grade_mix=mix, damage=damage))
        t_inject = time.perf_counter() - t0
        t0 = time.perf_counter()
        classify(pre, inj.post, work / "results" / tag, model_path=a.model, footprints_path=FOOTPRINTS,
                 write_las=False, force=True)
        t_classify = time.perf_counter() - t0
        s = score(work / "results" / tag / "buildings.csv", inj.truth)
        # the knob both ways: the model's own probabilities, which assume any damage shows
        classify(pre, inj.post, work / "results" / f"{tag}_assumed_visible", model_path=a.model,
                 footprints_path=FOOTPRINTS, write_las=False, force=True, unseen_damage=False)
        s["assumed_visible"] = score(work / "results" / f"{tag}_assumed_visible" / "buildings.csv", inj.truth)
        # and with the case's own mix of grades as the prior: what a responder's perfect estimate
        # of it would give (`--prior`), an upper bound of what the knob buys
        oracle = {int(g): max(sum(row.values()), 1) for g, row in s["confusion"].items()}
        classify(pre, inj.post, work / "results" / f"{tag}_own_prior", model_path=a.model,
                 footprints_path=FOOTPRINTS, write_las=False, force=True, prior=oracle)
        s["own_prior"] = score(work / "results" / f"{tag}_own_prior" / "buildings.csv", inj.truth)
        s["own_prior"]["prior"] = {str(g): n for g, n in oracle.items()}
        s.update({"case": name, "split": split, "seed": seed, "mix": {str(g): n for g, n in mix.items()},
                  "damage": damage, "inject_s": round(t_inject, 1), "classify_s": round(t_classify, 1),
                  "moved": inj.counts["moved"]})
        results["cases"].append(s)
        f1 = ", ".join(f"{g}: {100 * v['f1']:.0f}" for g, v in s["per_grade"].items())
        print(f"{name}: F1 {f1}; heavy recall {100 * s['per_grade']['3']['recall']:.0f} %; undamaged called damaged "
              f"{100 * s['undamaged_called_damaged']:.1f} %; quiet misses {len(s['quiet_misses'])}; "
              f"ECE {s['ece']:.3f} (inject {t_inject:.0f} s, classify {t_classify:.0f} s)", flush=True)
    if not a.no_shapes:
        results["across_sensors"] = no_change_across_sensors(work, a.model)
    if not a.no_low:
        results["low"] = low_buildings(work, a.model)
    if not a.no_drone:
        results["drone"] = drone_after_archive(work, a.model)
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    results["peak_mib"] = round(peak_rss_mb())
    work.mkdir(parents=True, exist_ok=True)
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    text = report(results)
    print(text)
    if not a.no_write:
        write_section("real_damage", text)
    return 0


def _pct(v) -> str:
    return "–" if v != v else f"{100 * v:.0f}"


def report(res: dict) -> str:
    lines = ["## bench_real_damage: damage injected into real points (AHN3 tile 1, evaluation only)", "",
             f"{res['machine']}; model `{Path(res['model']).name}`; {res['seconds']:.0f} s, peak {res['peak_mib']} MiB. "
             "Both epochs real (the tile's random halves, ~4 pts/m² each), damage injected into the post half by "
             "`quakescan inject` among buildings with ≥ 200 points; buildings scored: those injected and the "
             "undamaged ones with ≥ 200 points. `bench/bench_real_damage.py`.", ""]
    head = ["case", "F1 0", "F1 3", "F1 4", "F1 5", "heavy recall", "damaged found", "undamaged called damaged",
            "damaged reported 0 at ≥ 0.8 (no return moved)", "ECE", "heavy graded damaged: roof / walls only",
            "heavy graded heavy: roof / walls only"]
    rows = []
    for s in res["cases"]:
        g = s["per_grade"]
        rows.append([s["case"], _pct(g["0"]["f1"]), _pct(g["3"]["f1"]), _pct(g["4"]["f1"]), _pct(g["5"]["f1"]),
                     _pct(g["3"]["recall"]), _pct(s["damaged_found"]), f"{100 * s['undamaged_called_damaged']:.1f} %",
                     f"{len(s['quiet_misses'])} ({len(s.get('quiet_misses_no_return_moved', []))})",
                     f"{s['ece']:.3f}",
                     " / ".join(f"{a} of {n}" for a, n in s["heavy_seen"].values()),
                     " / ".join(f"{s['heavy_graded_heavy'][k]} of {n}" for k, (_, n) in s["heavy_seen"].items())
                     if "heavy_graded_heavy" in s else "—"])
    lines += [table(head, rows), ""]
    both = [s for s in res["cases"] if "assumed_visible" in s]
    if both:
        lines += ["Counting the damage the data could not show (`quakescan.learning.unseen_damage`, the default) "
                  "against the model's own probabilities, which assume any damage shows (`--assume-damage-visible`), "
                  "and with the case's own mix of grades given as the prior (`--prior`; the truth's shares, so an "
                  "upper bound of what a responder's estimate buys): the same descriptors and model, one run. "
                  "Grades are the model's in all three; only the probabilities differ.", ""]
        knob = []
        for s in both:
            for how, v in (("counted (default)", s), ("assumed visible", s["assumed_visible"]),
                           ("counted, the case's own mix as prior", s.get("own_prior"))):
                if v is None:
                    continue
                g = v["per_grade"]
                knob.append([s["case"], how, _pct(g["3"]["f1"]), _pct(g["4"]["f1"]), _pct(g["3"]["recall"]),
                             f"{100 * v['undamaged_called_damaged']:.1f} %",
                             f"{len(v['quiet_misses'])} ({len(v.get('quiet_misses_no_return_moved', []))})",
                             f"{v['ece']:.3f}"])
        lines += [table(["case", "unseen damage", "F1 3", "F1 4", "heavy recall", "undamaged called damaged",
                         "damaged reported 0 at ≥ 0.8 (no return moved)", "ECE"], knob), ""]
    if res.get("low"):
        lines += [f"Low buildings (the generator's small set: sheds, garages, row houses; seed {LOW_SEED}, mix "
                  + "/".join(str(LOW_MIX[g]) for g in GRADES) + ", paper presets, labelled through footprints): F1 % "
                  "per grade (target heavy ≥ 85).", ""]
        lines += [table(["pair", "F1 0", "F1 3", "F1 4", "F1 5", "heavy recall", "n/a"],
                        [[r["pair"], *[_pct(r["per_grade"][str(g)]["f1"]) for g in GRADES],
                          _pct(r["per_grade"]["3"]["recall"]),
                          sum(r["confusion"][str(g)]["n/a"] for g in GRADES)] for r in res["low"]]), ""]
    if res.get("drone"):
        lines += [f"A real archive before, a simulated drone after (tile 1 split {DRONE_SPLIT}: one real half before; "
                  "after, QuakeScan's paper ULS / DIM preset flown over the 2.5D surface of the other half, "
                  "`injection.surface_model`; then once as flown, no damage, and once with "
                  + "/".join(str(DRONE_MIX[g]) for g in (3, 4, 5)) + f" buildings at grades 3/4/5 injected, seed "
                  f"{DRONE_SEED}). F1 %; no change: assessable buildings called damaged (target ≤ 2 %).", ""]
        lines += [table(["pair", "points after", "no change: called damaged", "F1 0", "F1 3", "F1 4", "F1 5",
                         "heavy recall", "undamaged called damaged", "damaged reported 0 at ≥ 0.8", "ECE"],
                        [[r["pair"], f"{r['points_after']:,}",
                          f"{100 * r['no_change_damaged'] / max(r['no_change_assessable'], 1):.1f} % "
                          f"({r['no_change_damaged']}/{r['no_change_assessable']})",
                          *[_pct(r["per_grade"][str(g)]["f1"]) for g in GRADES], _pct(r["per_grade"]["3"]["recall"]),
                          f"{100 * r['undamaged_called_damaged']:.1f} %", len(r["quiet_misses"]), f"{r['ece']:.3f}"]
                         for r in res["drone"]]), ""]
        for r in res["drone"]:
            cols = [str(c) for c in GRADES] + ["n/a"]
            lines += [f"**{r['pair']}**: truth → predicted", "",
                      table(["truth"] + cols, [[t] + [r["confusion"][t][c] for c in cols] for t in r["confusion"]]), ""]
    if res.get("across_sensors"):
        lines += ["No change across sensors on real shapes (every building undamaged; QuakeScan's preset sensors, "
                  "one before, another after): assessable buildings called damaged (target ≤ 2 %).", ""]
        lines += [table(["city", "pair", "called damaged", "grades given"],
                        [[r["city"], r["pair"], f"{100 * r['damaged'] / max(r['assessable'], 1):.1f} % "
                          f"({r['damaged']}/{r['assessable']})", ", ".join(map(str, r["grades"])) or "–"]
                         for r in res["across_sensors"]]), ""]
    for s in res["cases"]:
        lines += [f"**{s['case']}** (split {s['split']}, inject seed {s['seed']}, {s['damage']}; "
                  f"{s['moved']:,} returns moved): truth → predicted", ""]
        cols = [str(c) for c in GRADES] + ["n/a"]
        lines += [table(["truth"] + cols, [[t] + [s["confusion"][t][c] for c in cols] for t in s["confusion"]]), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
