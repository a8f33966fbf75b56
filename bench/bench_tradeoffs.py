"""Speed versus accuracy: what each knob of the damage pipeline costs in time and gives in accuracy.

    .venv/bin/python bench/bench_tradeoffs.py          # ≤ 25 min on 2 cores; rewrites its section of BENCHMARKS.md
    .venv/bin/python bench/bench_tradeoffs.py --quick  # smoke run (small city, two values per knob), prints only

Data (generated once into out/bench_tradeoffs/scenes, reused when present): training set
= the generic dataset of 40 buildings (generate_scenes.py --set generic --dataset paper
--seed 11): pre-event and every building heavy, extreme and destroyed; the undamaged class
is the pre-event scene acquired a second time with another seed, as `quakescan.studies.experiment`
does. Test city = a region-specific mixed city (--seed 12) of 12 undamaged, 8 heavy,
10 extreme and 12 destroyed buildings; truth from its scene.json.

Baseline: the paper's ULS survey (300 kHz at 100 m) with the single-ray beam, features at
1.5 m from every pre-event building point, a forest of 100 trees of depth 5, trained on
ULS and tested on the test city scanned with the same survey. Each row changes one knob
from the baseline and is one full train + classify; clouds, descriptor tables and forests
that a row shares with the baseline are the baseline's (same seeds, same bytes), and their
seconds are the baseline's. Every cloud is acquired again on each run (its time is
measured), written as *.part.las and renamed.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._report import machine, peak_rss_mb, table, write_section

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "out" / "bench_tradeoffs"

FULL = {"train_buildings": 40, "test_mix": {0: 20, 3: 16, 4: 16, 5: 20}, "work": WORK,
        "beam": ("single", "adaptive", "full"),
        "survey": (("300 kHz, 100 m", 300_000.0, 100.0), ("150 kHz, 100 m", 150_000.0, 100.0),
                   ("300 kHz, 150 m", 300_000.0, 150.0)),
        "radius": (1.0, 1.5, 2.5), "step": (1, 4, 16), "trees": (10, 100, 500),
        "source": ("ULS", "DIM", "ULS+DIM")}
QUICK = {"train_buildings": 12, "test_mix": {0: 4, 3: 2, 4: 3, 5: 3}, "work": WORK / "quick",
         "beam": ("single", "adaptive"),
         "survey": (("300 kHz, 100 m", 300_000.0, 100.0), ("150 kHz, 100 m", 150_000.0, 100.0)),
         "radius": (1.0, 1.5), "step": (1, 4), "trees": (10, 100), "source": ("ULS", "DIM")}
BASE = {"beam": "single", "survey": "300 kHz, 100 m", "radius": 1.5, "step": 1, "trees": 100, "source": "ULS"}
TRAIN_SEED, TEST_SEED = 11, 12
# (cloud name, scene folder, seed); the training pairs are (pre, name) with the grade
TRAIN_CLOUDS = (("pre", "pre", 101), ("pre_rescan", "pre", 102), ("post_heavy", "post_heavy", 103),
                ("post_extreme", "post_extreme", 104), ("post_destruction", "post_destruction", 105))
TRAIN_PAIRS = (("pre_rescan", 0), ("post_heavy", 3), ("post_extreme", 4), ("post_destruction", 5))
TEST_CLOUDS = (("pre", "pre", 190), ("post", "post", 191))
MAX_DEPTH = 5
KNOB_NAMES = {"beam": "beam model", "survey": "pulse rate, altitude", "radius": "feature radius (m)",
              "step": "core point step (1 = exact)", "trees": "trees", "source": "training source (DIM test)"}
STAGE = {"beam": "acquire", "survey": "acquire", "radius": "describe", "step": "describe", "trees": "fit",
         "source": "acquire"}


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# ------------------------------------------------------------------ data
def ensure_scenes(cfg: dict) -> tuple[Path, Path]:
    """The training and test scene bundles, generated once (into *.part, then renamed); the
    folder names carry what made them, so a changed size or mix is generated anew."""
    from quakescan.generator import GenerationSpec, generate

    scenes = cfg["work"] / "scenes"
    mix = "_".join(f"{g}x{n}" for g, n in sorted(cfg["test_mix"].items()))
    train = scenes / f"train_generic_{cfg['train_buildings']}_seed{TRAIN_SEED}"
    test = scenes / f"test_region_{mix}_seed{TEST_SEED}"
    jobs = ((train, ("pre", "post_heavy", "post_extreme", "post_destruction"),
             lambda out: generate(GenerationSpec("generic", "paper", cfg["train_buildings"], TRAIN_SEED, out))),
            (test, ("pre", "post"),
             lambda out: generate(GenerationSpec("region", "mixed", None, TEST_SEED, out, grade_mix=cfg["test_mix"]))))
    for folder, needed, make in jobs:
        if all((folder / s / "scene.json").is_file() for s in needed):
            continue
        part = folder.with_name(folder.name + ".part")
        shutil.rmtree(part, ignore_errors=True)
        say(f"generating {folder}")
        make(part)
        shutil.rmtree(folder, ignore_errors=True)
        os.replace(part, folder)
    return train, test


@dataclass
class Acquisition:
    """The clouds of one acquisition setting: path, seconds and points per cloud name."""

    paths: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    cpu: dict = field(default_factory=dict)  # CPU seconds of this process, all threads
    points: dict = field(default_factory=dict)

    def time_of(self, names, cpu: bool = False) -> float:
        return sum((self.cpu if cpu else self.seconds)[n] for n in names)


class Study:
    def __init__(self, cfg: dict, workers: int = -1):
        self.cfg, self.workers = cfg, workers
        self.train_dir, self.test_dir = ensure_scenes(cfg)
        from quakescan.results.evaluation import read_truth

        self.truth = read_truth(self.test_dir / "post")
        self.clouds = cfg["work"] / "clouds"
        self._acq: dict = {}
        self._desc: dict = {}
        self._scenes: dict = {}

    # acquisition ------------------------------------------------------------
    def _scene(self, folder: Path):
        from quakescan.formats.scene import read_scene

        if folder not in self._scenes:
            self._scenes[folder] = read_scene(folder)
        return self._scenes[folder]

    def acquisition(self, tag: str, part: str) -> Acquisition:
        """Clouds `part` ('train' or 'test') of the acquisition `tag` ('dim' or a survey label)."""
        key = (tag, part)
        if key in self._acq:
            return self._acq[key]
        from quakescan.acquisition.dim import simulate_dim
        from quakescan.acquisition.dim_settings import preset_dim
        from quakescan.acquisition.scan import scan

        folder, clouds = (self.train_dir, TRAIN_CLOUDS) if part == "train" else (self.test_dir, TEST_CLOUDS)
        out = self.clouds / _slug(tag)
        out.mkdir(parents=True, exist_ok=True)
        acq = Acquisition()
        for name, scene, seed in clouds:
            path = out / f"{part}_{name}.las"
            tmp = path.with_name(f"{part}_{name}.part.las")  # the writer wants a .las suffix
            sc = self._scene(folder / scene)
            t, c = time.perf_counter(), time.process_time()
            if tag == "dim":
                summary = simulate_dim(sc, preset_dim("paper"), tmp, seed=seed, source=str(folder / scene))
            else:
                summary = scan(sc, self.survey(tag), tmp, seed=seed, source=str(folder / scene))
            acq.seconds[name] = time.perf_counter() - t
            acq.cpu[name] = time.process_time() - c
            os.replace(tmp, path)
            acq.paths[name], acq.points[name] = path, int(summary.points)
        say(f"acquired {part} clouds '{tag}': {acq.time_of(acq.seconds):.1f} s, "
            f"{sum(acq.points.values()):,} points")
        self._acq[key] = acq
        return acq

    @staticmethod
    def survey(tag: str):
        """'beam single' / 'beam full' / a survey label of cfg['survey'] → a Survey."""
        from quakescan.acquisition.survey import preset

        if tag.startswith("beam "):
            return preset("paper").replace(beam=tag.split()[1])
        for label, rate, alt in FULL["survey"]:
            if label == tag:
                return preset("paper").replace(pulse_rate_hz=rate, altitude_agl_m=alt)
        raise KeyError(tag)

    # describing ----------------------------------------------------------------
    def describe(self, tag: str, part: str, radius: float, step: int) -> dict:
        """Descriptor rows of the training pairs (x, y) or the test pair (rows), with seconds."""
        key = (tag, part, radius, step)
        if key in self._desc:
            return self._desc[key]
        from quakescan.change.pipeline import describe_pair, descriptor_matrix
        from quakescan.change.settings import PipelineSettings
        from quakescan.formats.pair import load_pair

        settings = PipelineSettings(radius_m=radius, core_point_step=step)
        acq = self.acquisition(tag, part)
        t, c = time.perf_counter(), time.process_time()
        if part == "train":
            xs, ys = [], []
            for name, grade in TRAIN_PAIRS:
                pair = load_pair(acq.paths["pre"], acq.paths[name])
                rows = [r for r in describe_pair(pair.pre, pair.post, settings, workers=self.workers)
                        if r.assessable]
                xs.append(descriptor_matrix(rows, settings.descriptor_names()))
                ys += [grade] * len(rows)
            res = {"x": np.vstack(xs), "y": np.array(ys)}
        else:
            pair = load_pair(acq.paths["pre"], acq.paths["post"])
            res = {"rows": describe_pair(pair.pre, pair.post, settings, workers=self.workers)}
        res["seconds"] = time.perf_counter() - t
        res["cpu"] = time.process_time() - c
        res["settings"] = settings
        say(f"described {part} '{tag}' r {radius} m, step {step}: {res['seconds']:.1f} s")
        self._desc[key] = res
        return res

    # one row -------------------------------------------------------------------
    def row(self, knob: str, value, *, train_tags=("beam single",), test_tag="beam single", radius=1.5,
            step=1, trees=100) -> dict:
        from quakescan.learning.prediction import predict_rows
        from quakescan.learning.model import DamageModel, train_damage_forest
        from quakescan.results.evaluation import evaluate_grades

        tables = [self.describe(t, "train", radius, step) for t in train_tags]
        test = self.describe(test_tag, "test", radius, step)
        acquire_s = sum(self.acquisition(t, "train").time_of(n for n, _, _ in TRAIN_CLOUDS) for t in train_tags)
        test_acq = self.acquisition(test_tag, "test")
        acquire_s += test_acq.time_of(n for n, _, _ in TEST_CLOUDS)
        describe_s = sum(t["seconds"] for t in tables) + test["seconds"]
        cpu = {"acquire": sum(self.acquisition(t, "train").time_of((n for n, _, _ in TRAIN_CLOUDS), cpu=True)
                              for t in train_tags) + test_acq.time_of((n for n, _, _ in TEST_CLOUDS), cpu=True),
               "describe": sum(t["cpu"] for t in tables) + test["cpu"]}
        settings = test["settings"]
        t, c = time.perf_counter(), time.process_time()
        x = np.vstack([t_["x"] for t_ in tables])
        y = np.concatenate([t_["y"] for t_ in tables])
        est = train_damage_forest(x, y, settings.descriptor_names(), n_estimators=trees, max_depth=MAX_DEPTH, seed=0,
                                  n_jobs=self.workers)
        model = DamageModel(est, settings.descriptor_names(), settings.radius_m, split=settings.to_json(),
                            provenance={"bench": "tradeoffs", "knob": knob, "value": str(value)})
        pred = predict_rows(test["rows"], model)
        fit_s = time.perf_counter() - t
        cpu["fit"] = time.process_time() - c
        assessed = [r for r in pred if r.assessable and r.building_id in self.truth]
        ev = evaluate_grades(np.array([self.truth[r.building_id] for r in assessed]),
                             np.array([r.grade for r in assessed]))
        seconds = {"acquire": acquire_s, "describe": describe_s, "fit": fit_s}
        r = {"knob": knob, "value": value, "stage_s": seconds[STAGE[knob]], "stage": STAGE[knob],
             "total_s": sum(seconds.values()), "seconds": seconds, "test_points": test_acq.points["pre"],
             "stage_cpu": cpu[STAGE[knob]], "total_cpu": sum(cpu.values()), "cpu": cpu,
             "assessed": len(assessed), "buildings": len(self.truth), "training_rows": len(y),
             "oa": ev.overall_accuracy, "f1_damaged": ev.damaged["f1"], "f1_0": ev.per_grade[0]["f1"],
             "f1_5": ev.per_grade[5]["f1"]}
        say(f"{KNOB_NAMES[knob]} = {value}: stage {r['stage_s']:.1f} s, total {r['total_s']:.1f} s, "
            f"OA {100 * r['oa']:.1f} %, F1 damaged {100 * r['f1_damaged']:.1f} %")
        return r


def _slug(tag: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in tag).strip("_")


def warm_up(folder: Path, workers: int = -1) -> None:
    """Every compiled kernel the study times (three beams, DIM, features at every radius and
    step, the forest) run once on a 2 × 2 box city, so no row pays for loading or compiling."""
    from quakescan.acquisition.dim import simulate_dim
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.change.pipeline import describe_pair
    from quakescan.change.settings import PipelineSettings
    from quakescan.formats.pointcloud import read_epoch
    from quakescan.formats.synthetic import box_city
    from quakescan.learning.model import train_forest

    folder.mkdir(parents=True, exist_ok=True)
    pre, post = box_city(rows=2, cols=2), box_city(rows=2, cols=2, height=(9.0, 3.0), epoch="post")
    for beam in ("single", "adaptive", "full"):
        s = preset("paper").replace(pulse_rate_hz=50_000.0, beam=beam)
        scan(pre, s, folder / "pre.las", seed=1)
        scan(post, s, folder / "post.las", seed=2)
    simulate_dim(pre, preset_dim("paper"), folder / "dim.las", seed=1)
    a = read_epoch(folder / "pre.las")
    b = read_epoch(folder / "post.las", origin=a.origin)
    for radius in FULL["radius"]:
        for step in FULL["step"][:2]:
            describe_pair(a, b, PipelineSettings(radius_m=radius, core_point_step=step), workers=workers)
    train_forest(np.random.default_rng(0).normal(size=(40, 3)), np.arange(40) % 4, n_estimators=10, n_jobs=workers)
    shutil.rmtree(folder, ignore_errors=True)


def run(cfg: dict, workers: int = -1) -> list[dict]:
    study = Study(cfg, workers)
    t = time.perf_counter()
    warm_up(cfg["work"] / "warm_up", workers)
    say(f"warm-up (kernels loaded or compiled, not timed in any row): {time.perf_counter() - t:.1f} s")
    rows, baseline = [], None

    def add(knob, value, **kw):
        nonlocal baseline
        if value == BASE[knob] and knob != "source":
            if baseline is None:
                baseline = study.row(knob, value)
            r = dict(baseline, knob=knob, value=value, stage=STAGE[knob],
                     stage_s=baseline["seconds"][STAGE[knob]], stage_cpu=baseline["cpu"][STAGE[knob]],
                     baseline=True)
        else:
            r = study.row(knob, value, **kw)
        rows.append(r)

    for beam in cfg["beam"]:
        add("beam", beam, train_tags=(f"beam {beam}",), test_tag=f"beam {beam}")
    for label, _, _ in cfg["survey"]:
        add("survey", label, train_tags=(label,), test_tag=label)
    for radius in cfg["radius"]:
        add("radius", radius, radius=radius)
    for step in cfg["step"]:
        add("step", step, step=step)
    for trees in cfg["trees"]:
        add("trees", trees, trees=trees)
    sources = {"ULS": ("beam single",), "DIM": ("dim",), "ULS+DIM": ("beam single", "dim")}
    for source in cfg["source"]:
        add("source", source, train_tags=sources[source], test_tag="dim")
    return rows


# ------------------------------------------------------------------ report
def _value(r: dict) -> str:
    v = r["value"]
    text = f"{v:g}" if isinstance(v, float) else str(v)
    return text + (" (baseline)" if r.get("baseline") else "")


def report_table(rows: list[dict]) -> str:
    out, last = [], None
    for r in rows:
        knob = KNOB_NAMES[r["knob"]] if r["knob"] != last else ""
        last = r["knob"]
        out.append((knob, _value(r), f"{r['stage']} {r['stage_s']:.1f}", f"{r['stage_cpu']:.1f}",
                    f"{r['total_s']:.0f}", f"{r['total_cpu']:.0f}",
                    f"{r['test_points']:,}", f"{r['assessed']}/{r['buildings']}", f"{100 * r['oa']:.1f}",
                    f"{100 * r['f1_damaged']:.1f}", f"{100 * r['f1_0']:.1f}", f"{100 * r['f1_5']:.1f}"))
    return table(["knob", "value", "stage s (knob's)", "stage CPU s", "end-to-end s", "end-to-end CPU s",
                  "test pre points", "assessed",
                  "OA %", "F1 damaged %", "F1 no damage %", "F1 destruction %"], out)


def reading(rows: list[dict]) -> str:
    """Plain sentences computed from the numbers: per knob, time and accuracy against the baseline."""
    base = next(r for r in rows if r.get("baseline"))
    n = base["buildings"]
    parts = []
    for knob in dict.fromkeys(r["knob"] for r in rows):
        group = [r for r in rows if r["knob"] == knob]
        ref = next((r for r in group if r.get("baseline")), group[0])
        bits = []
        for r in group:
            if r is ref:
                continue
            dt = r["total_s"] / ref["total_s"] if ref["total_s"] else float("nan")
            ds = r["stage_s"] / ref["stage_s"] if ref["stage_s"] else float("nan")
            dc = r["total_cpu"] / ref["total_cpu"] if ref["total_cpu"] else float("nan")
            bits.append(f"{_value(r)}: {r['stage']} ×{ds:.2f}, end to end ×{dt:.2f} (CPU ×{dc:.2f}), "
                        f"OA {100 * (r['oa'] - ref['oa']):+.1f} points, "
                        f"F1 damaged {100 * (r['f1_damaged'] - ref['f1_damaged']):+.1f}")
        parts.append(f"*{KNOB_NAMES[knob]}* (against {_value(ref)}): " + "; ".join(bits) + ".")
    others = [r for r in rows if not r.get("baseline") and r["knob"] != "source"]
    faster = [r for r in others if r["total_cpu"] < base["total_cpu"]]
    noise = 100 / n if n else float("nan")
    lines = [("Reading (computed from the table; one test building is "
             f"{noise:.1f} OA points, so differences of a few points are one or two buildings):"), ""]
    lines += [f"- {p}" for p in parts]
    if faster:
        # the fastest row that stays within one test building of the baseline's accuracy
        kept = [r for r in faster if 100 * (base["oa"] - r["oa"]) <= noise + 1e-9]
        cheap = min(kept or faster, key=lambda r: r["total_cpu"])
        lines.append(f"- {'Cheapest speed-up' if kept else 'No speed-up keeps the accuracy; the fastest'}: "
                     f"{KNOB_NAMES[cheap['knob']]} = {_value(cheap)} "
                     f"({base['total_cpu']:.0f} → {cheap['total_cpu']:.0f} CPU s end to end, "
                     f"OA {100 * base['oa']:.1f} → {100 * cheap['oa']:.1f} %).")
    worst = min(others, key=lambda r: r["oa"]) if others else None
    if worst is not None:
        lines.append(f"- Largest accuracy cost: {KNOB_NAMES[worst['knob']]} = {_value(worst)} "
                     f"(OA {100 * worst['oa']:.1f} % against the baseline's {100 * base['oa']:.1f} %).")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small city, two values per knob; prints only")
    ap.add_argument("--write", action="store_true", help="with --quick: rewrite BENCHMARKS.md all the same")
    args = ap.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    t0 = time.perf_counter()
    load_before = os.getloadavg()[0]
    rows = run(cfg)
    total = time.perf_counter() - t0
    load_after = os.getloadavg()
    test_pre = rows[0]["test_points"]
    training = rows[0]["training_rows"]
    command = "`.venv/bin/python bench/bench_tradeoffs.py" + (" --quick" if args.quick else "") + "`"
    mix = ", ".join(f"{n} × grade {g}" for g, n in sorted(cfg["test_mix"].items()))
    text = "\n\n".join([
        "## Speed versus accuracy (`bench/bench_tradeoffs.py`)" + (" — quick mode" if args.quick else ""),
        (f"Machine: {machine()}; both cores (scanner threads, `workers=-1`, forest `n_jobs=-1`). "
        f"Command: {command}; the whole run took {total / 60:.1f} min, peak memory {peak_rss_mb():,.0f} MiB; "
         f"load average {load_before:.1f} at the start, {load_after[0]:.1f} / {load_after[1]:.1f} / "
         f"{load_after[2]:.1f} (1 / 5 / 15 min) at the end (above 2: other jobs shared the cores)."),
        (f"Data: training = the generic dataset of {cfg['train_buildings']} buildings (seed {TRAIN_SEED}; "
        "pre-event, heavy, extreme, destroyed; no damage = the pre-event scene acquired again with another "
        f"seed), {training} training rows at the baseline; test = a region-specific mixed city (seed {TEST_SEED}) "
        f"with {mix}, {test_pre:,} points in its baseline pre-event cloud. Metrics over the assessed test "
        "buildings: overall accuracy over the four classes (0/3/4/5), F1 of damaged vs undamaged, F1 of no "
        "damage and of destruction."),
        ("Baseline: paper ULS survey (300 kHz at 100 m), single-ray beam, radius 1.5 m, every pre-event point "
        "(core point step 1), 100 trees of depth 5 fitted as the shipped model is (buildings with changed "
        "points, balanced classes), the split's default levels of detection in every row (the DIM rows too; "
        "`quakescan experiment` measures DIM's), trained on ULS, tested on the same survey's scans. Each row "
        "changes one knob and is one train + classify. Rows that do not change the acquisition reuse the "
        "baseline's clouds (their acquisition seconds are the baseline's), rows that do not change the "
        "features reuse its descriptor tables; the baseline row appears once per knob with the same numbers. "
        "The training-source rows test on the city acquired as DIM (`preset_dim(\"paper\")`); their ULS row "
        "uses the baseline's ULS training tables. \"Stage s\" is the time of the stage the knob acts on "
        "(acquire: every cloud the row uses, training and test; describe: descriptor rows of the four "
        "training pairs and the test pair, reading included; fit: forest training + prediction); "
        "end-to-end = acquire + describe + fit. CPU s = CPU time of this process, all threads; close to "
        "the wall seconds means the process had about one core on average, and on this shared VM both grow "
        "alike with the other jobs' load: compare the seconds of rows run under similar load only (the load "
        "average above says how shared the run was)."),
        report_table(rows),
        reading(rows),
    ])
    print("\n" + text)
    results = cfg["work"] / "results.json"
    tmp = results.with_name(results.name + ".part")
    tmp.write_text(json.dumps({"minutes": total / 60, "rows": rows}, indent=1, default=str))
    os.replace(tmp, results)
    if not args.quick or args.write:
        write_section("tradeoffs", text)


if __name__ == "__main__":
    main()
