"""The paper's experiment (`quakescan experiment paper`): four classifiers, one held-out test.

Zahs et al. train four random forests and evaluate each on real DIM clouds of L'Aquila
(35 no damage, 19 heavy, 32 extreme, 35 destruction). No real labelled DIM clouds exist
here, so the "real-world DIM" of the paper is stood in for by simulated DIM clouds of the
region-specific (L'Aquila-like) set:

  generic ULS               generic city, virtual laser scanning          (the shipped model)
  region ULS                region-specific city, laser scanning
  generic ULS + region DIM  both of the above training sets, the region's as DIM
  region DIM                region-specific city, photogrammetry (DIM)

Each training set is the paper's dataset design: N buildings pre-event and, in three
post-event scenes, every building heavy, extreme or destroyed; the undamaged class comes
from the pre-event scene acquired a second time (new noise). With `training="paper+mixed"`
(the default) each set also holds a mixed city of N buildings, a quarter per grade, where
undamaged buildings stand beside damaged ones: the paper's design never shows the
classifier an undamaged building next to a collapse (debris on its walls, a neighbour's
newly exposed party wall), and the test city is full of them. The test city is a separate
region-specific mixed city with the paper's exact class mix, acquired as DIM.

Levels of detection of the changed/unchanged split (`quakescan.change.lod`): by default measured on
the region-specific pre-event scene acquired twice as DIM (the source the classifiers are
applied to) and used for every training table and the test alike; explicit values
override. Descriptor tables are computed once per dataset and split settings and shared
between classifiers; every step reuses an output only when the fingerprint stored with it is
the one the step would store now (`quakescan.runtime.fingerprint`: resumable, never stale) and
everything is seeded (reproducible).
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..learning.model import train_damage_forest, train_forest
from ..results.evaluation import (
    TARGET_GRADES,
    TARGET_SHORT_NAMES,
    Evaluation,
    evaluate_grades,
    metric_text,
    plot_confusion,
    read_truth,
)
from ..runtime import fingerprint
from ..runtime.atomic import open_replacing, write_text
from ..runtime.progress import ProgressCallback, stage_log

log = logging.getLogger(__name__)

# Table of Zahs et al.: per classifier, per column (damaged vs undamaged, grades 0/3/4/5),
# (overall accuracy, precision, recall, F1) in %.
PAPER_TABLE = {
    "generic ULS": {"damaged": (95.12, 100.0, 84.62, 91.67), 0: (95.12, 84.62, 100.0, 91.67),
                    3: (92.80, 72.73, 84.21, 78.05), 4: (92.00, 78.13, 89.29, 83.33), 5: (93.60, 91.43, 86.49, 88.89)},
    "region ULS": {"damaged": (94.40, 82.05, 100.0, 90.14), 0: (92.00, 84.21, 69.57, 76.19),
                   3: (92.00, 69.57, 84.21, 76.91), 4: (92.00, 78.13, 89.29, 83.33), 5: (92.00, 82.05, 91.43, 86.49)},
    "generic ULS + region DIM": {"damaged": (94.40, 82.05, 100.0, 90.14), 0: (94.40, 100.0, 82.05, 90.14),
                                 3: (91.20, 68.18, 78.95, 73.17), 4: (92.00, 81.25, 86.67, 83.87),
                                 5: (92.00, 83.78, 88.57, 86.11)},
    "region DIM": {"damaged": (96.80, 100.0, 89.74, 94.59), 0: (96.80, 89.74, 100.0, 94.59),
                   3: (93.60, 78.95, 78.95, 78.95), 4: (92.00, 81.25, 86.67, 83.87), 5: (93.60, 84.62, 94.29, 89.19)},
}
CLASSIFIERS = {
    "generic ULS": (("generic", "uls"),),
    "region ULS": (("region", "uls"),),
    "generic ULS + region DIM": (("generic", "uls"), ("region", "dim")),
    "region DIM": (("region", "dim"),),
}
PAPER_TEST_MIX = {0: 35, 3: 19, 4: 32, 5: 35}
TRAINING_SCENES = (("pre_rescan", "pre", 0), ("post_heavy", "post_heavy", 3), ("post_extreme", "post_extreme", 4),
                   ("post_destruction", "post_destruction", 5))
TRAINING_LAYOUTS = ("paper", "paper+mixed")


@dataclass
class ExperimentSettings:
    buildings: int = 112
    test_mix: dict = None
    seed: int = 0
    n_estimators: int = 100
    max_depth: int = 5
    lod_height_m: float | None = None  # None: calibrated on the DIM rescan (quakescan.change.lod)
    lod_curvature: float | None = None
    training: str = "paper+mixed"

    def __post_init__(self):
        from ..errors import QuakeScanError

        if self.test_mix is None:
            self.test_mix = dict(PAPER_TEST_MIX)
        if self.training not in TRAINING_LAYOUTS:
            raise QuakeScanError(f"training layout must be one of {TRAINING_LAYOUTS}, got {self.training!r}")
        if self.buildings < 4:
            raise QuakeScanError(f"buildings per training dataset must be >= 4, got {self.buildings}")

    @property
    def mixed_training_mix(self) -> dict:
        """Grades of each training set's mixed city: a quarter of the buildings per grade."""
        return {g: self.buildings // 4 for g in TARGET_GRADES}


def _acquire(kind: str, scene_dir: Path, stem: Path, seed: int) -> Path:
    """stem.seedN.las acquired from scene_dir with the default settings of sensor `kind`
    (`quakescan.acquisition.sensors`); reused only when its acquisition record says the same scene, settings
    and seed (`quakescan.acquisition.acquire`)."""
    from ..acquisition import sensors
    from ..acquisition.acquire import Acquisition, acquire

    out = _acquired_path(stem, seed)
    t0 = time.perf_counter()
    got = acquire(scene_dir, Acquisition(kind, sensors.get(kind).default()), out, seed=seed)
    if not got.resumed:
        stage_log.info(f"  {out.name}: {kind.upper()} in {time.perf_counter() - t0:.0f} s")
    return out


def _acquired_path(stem: Path, seed: int) -> Path:
    return stem.with_name(f"{stem.name}.seed{seed}.las")


def _table(pre: Path, posts: list, cache: Path, settings, workers) -> dict:
    """Descriptor rows {X, y, ids} of the training pairs (pre, post), cached.

    `posts`: (post cloud, grade) where grade is one grade for every building or a
    {building ID: grade} truth (a mixed city)."""
    from ..change.descriptors import DESCRIPTOR_VERSION
    from ..change.pipeline import describe_pair, descriptor_matrix
    from ..formats.pair import load_pair

    inputs = json.dumps([settings.to_json(), Path(pre).name, [Path(p).name for p, _ in posts]], sort_keys=True)
    cache = cache.with_name(f"{cache.name}_{hashlib.sha256(inputs.encode()).hexdigest()[:10]}.npz")
    clouds = {"pre": fingerprint.stat(pre), "posts": [[fingerprint.stat(p), _grade_json(g)] for p, g in posts]}
    fp = fingerprint.make("descriptor-table", inputs=clouds, settings=settings.to_json(),
                          code={"descriptors": DESCRIPTOR_VERSION})
    found = fingerprint.state(cache, fp)
    if found == "changed":
        _discard(cache, "cut or replaced since it was written")
    elif found == "current":
        try:
            with np.load(cache) as d:
                return {"x": d["x"], "y": d["y"], "ids": d["ids"]}
        except Exception as e:  # foreign: recomputed, never a traceback on every rerun
            _discard(cache, e)
    fingerprint.forget(cache)
    names = settings.descriptor_names()
    xs, ys, ids = [], [], []
    for post, grade in posts:
        t0 = time.perf_counter()
        data = load_pair(pre, post)
        rows = [r for r in describe_pair(data.pre, data.post, settings, workers=workers) if r.assessable]
        stage_log.info(f"  {Path(post).name} against {Path(pre).name}: {len(rows)} buildings in "
                       f"{time.perf_counter() - t0:.0f} s")
        if isinstance(grade, dict):
            rows = [r for r in rows if r.building_id in grade]
        xs.append(descriptor_matrix(rows, names))
        ys += [grade[r.building_id] if isinstance(grade, dict) else grade for r in rows]
        ids += [r.building_id for r in rows]
    out = {"x": np.vstack(xs), "y": np.array(ys), "ids": np.array(ids)}
    with open_replacing(cache, "wb") as f:
        np.savez(f, **out)
    fingerprint.record(cache, fp)
    return out


def _grade_json(grade):
    """A pair's grade for a fingerprint: one grade, or the {building ID: grade} truth."""
    return {str(k): int(v) for k, v in grade.items()} if isinstance(grade, dict) else int(grade)


def _discard(cache: Path, why) -> None:
    """Remove an unreadable cache file, saying so (`why`: the error or a reason): its step is
    recomputed."""
    log.warning("%s: unreadable cache (%s), discarded: recomputing it", cache, why)
    cache.unlink(missing_ok=True)


def _levels_of_detection(s: ExperimentSettings, pre: Path, rescan: Path, cache: Path, workers):
    """The split's LoDs: explicit ones, or measured on the DIM rescan (cached as JSON)."""
    from ..change.lod import LevelsOfDetection, calibrate
    from ..formats.pointcloud import read_epoch

    lod = None
    fp = fingerprint.make("levels-of-detection", inputs={"pre": fingerprint.stat(pre),
                                                         "rescan": fingerprint.stat(rescan)},
                          settings={"seed": s.seed})
    found = fingerprint.state(cache, fp)
    if found == "changed":
        _discard(cache, "cut or edited since it was written")
    elif found == "current":
        try:
            lod = LevelsOfDetection(**json.loads(cache.read_text()))
        except Exception as e:  # edited to the same size: measured again
            _discard(cache, e)
    if lod is None:
        fingerprint.forget(cache)
        a = read_epoch(pre)
        lod = calibrate(a, read_epoch(rescan, origin=a.origin), seed=s.seed, workers=workers)
        write_text(cache, json.dumps(lod.to_json(), indent=1))
        fingerprint.record(cache, fp)
    if s.lod_height_m is not None:
        lod.lod_height_m = s.lod_height_m
    if s.lod_curvature is not None:
        lod.lod_curvature = s.lod_curvature
    return lod


def run_paper_experiment(out_dir, settings: ExperimentSettings | None = None, *, workers: int = -1,
                         progress: ProgressCallback | None = None, client=None) -> dict:
    """Run everything and write the report to out_dir; returns {classifier: Evaluation}.

    `progress(done, total)` counts steps: cities generated, clouds acquired, the levels of
    detection, descriptor tables, the test city described, the classifiers trained (a cached
    step counts as done).

    `client` (a dask.distributed Client): every step but the training as a Dask task on its
    cluster (a city per task, a cloud per task after its city, the levels of detection, a
    descriptor table per dataset and the test city after their clouds; single-threaded tasks,
    each worker its own ray-casting scene); every worker must reach out_dir. The same files,
    caches and numbers as one process makes: either run resumes the other's."""
    from ..change.settings import PipelineSettings
    from ..generator import GenerationSpec, generate
    from ..learning.prediction import predict_rows
    from ..learning.model import DamageModel

    s = settings or ExperimentSettings()
    mixed = s.training == "paper+mixed"
    out = Path(out_dir)
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timings = {}

    def step(label):
        timings[label] = round(time.perf_counter() - t0 - sum(timings.values()), 1)

    n_cities = 5 if mixed else 3
    n_clouds = 3 * (1 + len(TRAINING_SCENES) + (2 if mixed else 0)) + 2
    total = n_cities + n_clouds + 1 + 3 * (2 if mixed else 1) + 2
    done = [0]

    def advance(result=None):
        done[0] += 1
        if progress:
            progress(done[0], total)
        return result

    run = _InProcess(advance, workers) if client is None else _OnDask(client, advance)
    stage_log.info(f"experiment 1/5: generating the generic and region-specific datasets ({s.buildings} buildings "
                   "each" + (f", and a mixed city {s.mixed_training_mix} each" if mixed else "")
                   + f") and the test city {s.test_mix}" + ("" if client is None else " (Dask tasks from here on)"))
    # the data folder is the experiment's own cache: bundles of another generator are made again
    made = {"generic": run("generate-generic", generate, GenerationSpec("generic", "paper", s.buildings, s.seed,
                                                                        data / "generic", force=True)),
            "region": run("generate-region", generate, GenerationSpec("region", "paper", s.buildings, s.seed + 1,
                                                                      data / "region", force=True)),
            "test": run("generate-test", generate, GenerationSpec("region", "mixed", None, s.seed + 2, data / "test",
                                                                  grade_mix=s.test_mix, force=True))}
    if mixed:
        made["generic_mixed"] = run("generate-generic-mixed", generate, GenerationSpec(
            "generic", "mixed", None, s.seed + 3, data / "generic_mixed", grade_mix=s.mixed_training_mix, force=True))
        made["region_mixed"] = run("generate-region-mixed", generate, GenerationSpec(
            "region", "mixed", None, s.seed + 4, data / "region_mixed", grade_mix=s.mixed_training_mix, force=True))
    step("generate")

    stage_log.info("experiment 2/5: acquiring the clouds (ULS: paper survey; DIM: paper photo flight)")
    clouds: dict[tuple, dict] = {}
    paths = {}  # a cloud's step -> the cloud's path (a Dask step's value is there once it has run)

    def acquire(kind, city, scene, stem, seed):
        cloud = run(f"acquire-{stem}", _acquire, kind, data / city / scene, data / stem, seed, after=made[city])
        paths[cloud] = _acquired_path(data / stem, seed)
        return cloud

    # every cloud its own seed, the same whatever the training layout
    for k, (dataset, kind) in enumerate((("generic", "uls"), ("region", "uls"), ("region", "dim"))):
        c = {}
        for j, (name, scene, _) in enumerate((("pre", "pre", None), *TRAINING_SCENES)):
            c[name] = acquire(kind, dataset, scene, f"{dataset}_{kind}_{name}", s.seed * 100 + 5 * k + j + 1)
        if mixed:
            for j, ep in enumerate(("pre", "post")):
                c[f"mixed_{ep}"] = acquire(kind, f"{dataset}_mixed", ep, f"{dataset}_mixed_{kind}_{ep}",
                                           s.seed * 100 + 60 + 2 * k + j)
        clouds[(dataset, kind)] = c
    test_pre = acquire("dim", "test", "pre", "test_dim_pre", s.seed * 100 + 90)
    test_post = acquire("dim", "test", "post", "test_dim_post", s.seed * 100 + 91)
    step("acquire")

    dim = clouds[("region", "dim")]
    lod = run("levels-of-detection", _levels_of_detection, s, dim["pre"], dim["pre_rescan"],
              data / f"lod_{paths[dim['pre_rescan']].stem}.json", run.workers)
    if client is None:
        stage_log.info(f"experiment 3/5: change descriptors of every training pair (levels of detection "
                       f"{lod.lod_height_m:.2f} m, {lod.lod_curvature:.2f} 1/m; one table per dataset, shared)")
    tables = {}  # cached under a hash of the settings and the input clouds' names (seeds included)
    for key in sorted(clouds):
        c = clouds[key]
        paper = run(f"table-{key[0]}-{key[1]}", _table_after_lod, c["pre"],
                    [(c[name], g) for name, _, g in TRAINING_SCENES], data / f"table_{key[0]}_{key[1]}", lod,
                    run.workers)
        mixed_table = None
        if mixed:  # its truth is read once the city is made
            mixed_table = run(f"table-{key[0]}-mixed-{key[1]}", _table_after_lod, c["mixed_pre"],
                              [(c["mixed_post"], data / f"{key[0]}_mixed" / "post")],
                              data / f"table_{key[0]}_mixed_{key[1]}", lod, run.workers)
        tables[key] = {"paper": paper, "mixed": mixed_table}
    step("describe training")

    if client is None:
        stage_log.info("experiment 4/5: training the four classifiers and classifying the held-out DIM test city")
    test_rows = run("describe-test", _describe_after_lod, test_pre, test_post, lod, run.workers)
    shipped = run("shipped-default", shipped_default, test_pre, test_post, data / "test" / "post", run.workers,
                  count=False)
    if client is not None:  # every task above runs now; progress as they finish
        lod, tables, test_rows, shipped = run.wait((lod, tables, test_rows, shipped))
        timings = {"generate, acquire, describe (Dask tasks)": round(time.perf_counter() - t0, 1)}
        stage_log.info(f"experiment 3-4/5: levels of detection {lod.lod_height_m:.2f} m, {lod.lod_curvature:.2f} "
                       "1/m; training the four classifiers and classifying the held-out DIM test city")
    pipe = PipelineSettings(split=lod.split())
    truth = read_truth(data / "test" / "post")
    names = pipe.descriptor_names()

    def evaluate(parts, layouts, forest_rows) -> Evaluation:
        x = np.vstack([tables[p][lay]["x"] for p in parts for lay in layouts])
        y = np.concatenate([tables[p][lay]["y"] for p in parts for lay in layouts])
        if forest_rows == "changed, balanced":
            est = train_damage_forest(x, y, names, n_estimators=s.n_estimators, max_depth=s.max_depth, seed=s.seed)
        else:  # the plain forest on every row, as a check of what the two measures buy
            est = train_forest(x, y, n_estimators=s.n_estimators, max_depth=s.max_depth, seed=s.seed,
                               class_weight=None)
        model = DamageModel(est, names, pipe.radius_m, split=pipe.to_json(), provenance={"rows": len(y)})
        pred = predict_rows(test_rows, model)
        assessed = [r for r in pred if r.assessable and r.building_id in truth]
        ev = evaluate_grades(np.array([truth[r.building_id] for r in assessed]), np.array([r.grade for r in assessed]))
        ev.not_assessable = sum(not r.assessable for r in pred)
        return ev

    layouts = ("paper", "mixed") if mixed else ("paper",)
    results = {name: evaluate(parts, layouts, "changed, balanced") for name, parts in CLASSIFIERS.items()}
    # What each measure against the undamaged failure buys, on the same tables and test rows.
    ablation = {}
    for lay in ((("paper",), ("paper", "mixed")) if mixed else (("paper",),)):
        for rows in ("all, unweighted", "changed, balanced"):
            ablation[("+".join(lay), rows)] = {name: evaluate(parts, lay, rows) for name, parts in CLASSIFIERS.items()}
    advance()
    step("train + classify")

    stage_log.info(f"experiment 5/5: report -> {out}")
    write_report(out, results, s, lod, timings, time.perf_counter() - t0, ablation, shipped,
                 dask_workers=None if client is None else _worker_count(client))
    return results


class _InProcess:
    """Runs each step of the experiment when it is asked for, in this process, with `workers`
    threads; a step's result is its value."""

    def __init__(self, advance, workers):
        self.advance, self.workers = advance, workers

    def __call__(self, key, fn, *args, after=None, count=True, **kwargs):
        result = fn(*args, **kwargs)
        return self.advance(result) if count else result


class _OnDask:
    """Submits each step as a Dask task (single-threaded: `workers` 1) whose inputs are the
    futures of the steps it needs, and `after` those it must follow; `wait` counts them as they
    finish and gathers the values asked for."""

    workers = 1

    def __init__(self, client, advance):
        import uuid

        self.client, self.advance = client, advance
        # keys new in every run: a key of a run interrupted a moment ago may still be cancelling
        self.run = uuid.uuid4().hex[:8]
        self.futures, self.counted = [], set()

    def __call__(self, key, fn, *args, after=None, count=True, **kwargs):
        f = self.client.submit(_after, fn, after, *args, key=f"experiment-{key}-{self.run}", pure=False, **kwargs)
        self.futures.append(f)
        if count:
            self.counted.add(f.key)
        return f

    def wait(self, values):
        from dask.distributed import as_completed

        try:
            for f in as_completed(self.futures):
                f.result()  # a task's error is raised here, with the task's traceback
                if f.key in self.counted:
                    self.advance()
            return self.client.gather(values)
        finally:
            self.client.cancel([f for f in self.futures if not f.done()])


def _after(fn, after, *args, **kwargs):
    """Dask task: fn(*args, **kwargs), once `after` (a future's result) is there; every numba
    kernel on one thread (the worker processes are the parallelism)."""
    from ..runtime.workers import kernel_threads

    with kernel_threads(1):
        return fn(*args, **kwargs)


def _worker_count(client) -> int:
    return len(client.scheduler_info().get("workers", {}))


def _table_after_lod(pre: Path, posts: list, cache: Path, lod, workers) -> dict:
    """`_table` with the split of the measured levels of detection; a post-event cloud's grade
    may be a scene folder whose truth holds the grades (a mixed city, read once it is made)."""
    from ..change.settings import PipelineSettings

    posts = [(post, read_truth(grade) if isinstance(grade, Path) else grade) for post, grade in posts]
    return _table(pre, posts, cache, PipelineSettings(split=lod.split()), workers)


def _describe_after_lod(pre: Path, post: Path, lod, workers) -> list:
    """The test pair's building rows with the split of the measured levels of detection."""
    from ..change.pipeline import describe_pair
    from ..change.settings import PipelineSettings
    from ..formats.pair import load_pair

    pair = load_pair(pre, post)
    return describe_pair(pair.pre, pair.post, PipelineSettings(split=lod.split()), workers=workers)


def shipped_default(pre: Path, post: Path, truth_dir: Path, workers) -> Evaluation | None:
    """The shipped default model (trained on the transfer training set, not on this experiment's
    data) applied as it is to the test pair: what a user gets without training anything."""
    from ..change.pipeline import describe_pair
    from ..formats.pair import load_pair
    from ..learning.default_model import default_model_path
    from ..learning.prediction import model_settings, predict_rows
    from ..learning.model import ModelError, load_model

    try:
        path = default_model_path()
        model = load_model(path)
    except ModelError:
        return None
    pair, truth = load_pair(pre, post), read_truth(truth_dir)
    rows = describe_pair(pair.pre, pair.post, model_settings(model, str(path)), workers=workers)
    pred = [r for r in predict_rows(rows, model) if r.building_id in truth]
    assessed = [r for r in pred if r.assessable]
    ev = evaluate_grades(np.array([truth[r.building_id] for r in assessed]), np.array([r.grade for r in assessed]))
    ev.not_assessable = sum(not r.assessable for r in pred)
    return ev


def _cell(m: dict) -> tuple:
    """The four metrics as report text ("n/a" where a metric has no cases)."""
    return tuple(metric_text(m, k, unit="") for k in ("oa", "precision", "recall", "f1"))


def comparison_table(results: dict) -> str:
    cols = [("damaged", "damaged vs undamaged")] + [(g, TARGET_SHORT_NAMES[g]) for g in TARGET_GRADES]
    lines = ["| classifier | metric | " + " | ".join(c for _, c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for name, ev in results.items():
        ours = {"damaged": _cell(ev.damaged), **{g: _cell(ev.per_grade[g]) for g in TARGET_GRADES}}
        paper = PAPER_TABLE[name]
        for i, metric in enumerate(("OA", "precision", "recall", "F1")):
            cells = [f"{ours[c][i]} ({paper[c][i]:.1f})" for c, _ in cols]
            lines.append(f"| {name if i == 0 else ''} | {metric} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _command(out: Path, s: ExperimentSettings) -> str:
    defaults = ExperimentSettings()
    args = [f"quakescan experiment paper -o {out}"]
    for flag, value, default in (("--buildings", s.buildings, defaults.buildings), ("--seed", s.seed, defaults.seed),
                                 ("--trees", s.n_estimators, defaults.n_estimators),
                                 ("--training", s.training, defaults.training),
                                 ("--lod-height", s.lod_height_m, None), ("--lod-curvature", s.lod_curvature, None)):
        if value != default:
            args.append(f"{flag} {value}")
    if s.test_mix != PAPER_TEST_MIX:
        args.append("--test-mix " + ",".join(f"{g}:{n}" for g, n in sorted(s.test_mix.items())))
    return " ".join(args)


def ablation_table(ablation: dict) -> str:
    """Overall accuracy and undamaged buildings recognised per training layout and forest rows."""
    if not ablation:
        return ""
    names = list(next(iter(ablation.values())))
    lines = ["| training sets | forest fitted on | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for (layout, rows), res in ablation.items():
        cells = []
        for n in names:
            ev = res[n]
            cells.append(f"{100 * ev.overall_accuracy:.1f} % ({int(ev.confusion[0, 0])}/{int(ev.confusion[0].sum())})")
        lines.append(f"| {layout} | {rows} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def shipped_text(ev: Evaluation | None) -> str:
    if ev is None:
        return "The shipped default model was not found; no comparison with it."
    f1 = ", ".join(f"{TARGET_SHORT_NAMES[g]} {metric_text(ev.per_grade[g], 'f1', unit='')}" for g in TARGET_GRADES)
    # "quakescan.trainset": the training set's module as the reports of record and the shipped
    # model's provenance name it, so the report's text stays the same bytes
    return (f"The shipped default model (`core/data/default_model.skops`: the transfer training set of "
            f"`quakescan.trainset`, nothing of this experiment's data), applied as it is to the same test pair: "
            f"overall accuracy {100 * ev.overall_accuracy:.1f} % on {ev.n} buildings ({ev.not_assessable} not "
            f"assessable); F1 {f1}; damaged vs undamaged F1 {metric_text(ev.damaged, 'f1')}.")


def write_report(out: Path, results: dict, s: ExperimentSettings, lod, timings: dict, total_s: float,
                 ablation: dict | None = None, shipped: Evaluation | None = None,
                 dask_workers: int | None = None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, ev in results.items():
        slug = name.lower().replace(" + ", "_plus_").replace(" ", "_")
        plot_confusion(ev, out / f"confusion_{slug}.png", title=f"{name} → region DIM test city")
    doc = {"settings": {"buildings": s.buildings, "test_mix": {str(g): n for g, n in s.test_mix.items()},
                        "seed": s.seed, "n_estimators": s.n_estimators, "max_depth": s.max_depth,
                        "training": s.training, "lod_height_m": s.lod_height_m, "lod_curvature": s.lod_curvature},
           "levels_of_detection": lod.to_json(),
           "seconds": {**timings, "total": round(total_s, 1)},
           "results": {name: ev.to_json() for name, ev in results.items()},
           "ablation": [{"training": lay, "forest_rows": rows, "results": {n: ev.to_json() for n, ev in res.items()}}
                        for (lay, rows), res in (ablation or {}).items()],
           "paper": {name: {str(k): v for k, v in t.items()} for name, t in PAPER_TABLE.items()},
           "shipped_default": None if shipped is None else shipped.to_json()}
    write_text(out / "results.json", json.dumps(doc, indent=1))
    n = next(iter(results.values())).n if results else 0
    measured = s.lod_height_m is None or s.lod_curvature is None
    how = (f", measured on the region-specific pre-event scene acquired twice as DIM ({lod.points} points; "
           f"99.9th percentiles {lod.height_at_quantile_m:.3f} m and {lod.curvature_at_quantile:.3f} 1/m, "
           "floors 0.30 m and 0.20 1/m)") if measured else ""
    lod_text = (f"levels of detection of the split {lod.lod_height_m:.2f} m (height) and {lod.lod_curvature:.2f} 1/m "
                f"(curvature){how}")
    grades = ", ".join(f"{v} × grade {k}" for k, v in s.mixed_training_mix.items())
    mixed = (f" Each set also holds a mixed city ({grades}), where undamaged buildings stand beside damaged ones."
             if s.training == "paper+mixed" else "")
    where = "" if dask_workers is None else f", as Dask tasks on {dask_workers} workers"
    text = f"""# The paper's experiment, simulated

Command: `{_command(out, s)}`; {total_s / 60:.1f} min on this machine{where}
(stages: {", ".join(f"{k} {v} s" for k, v in timings.items())}).

Training sets: the generic and the region-specific (L'Aquila-like) dataset, {s.buildings} buildings each,
pre-event acquired twice (no damage) and every building heavy, extreme and destroyed.{mixed} Test: a separate
region-specific city with {", ".join(f"{v} × grade {k}" for k, v in sorted(s.test_mix.items()))}, acquired
as simulated DIM ({n} assessable buildings). The paper's "real-world DIM" is simulated DIM here.
Random forests of {s.n_estimators} trees, depth {s.max_depth}; {lod_text}.

Each cell: ours (the paper's), in %.

{comparison_table(results)}

Overall accuracy over all four classes at once: {", ".join(f"{k} {100 * v.overall_accuracy:.1f} %"
                                                        for k, v in results.items())}.

{shipped_text(shipped)}

What the measures against misreading undamaged buildings buy (same descriptor tables, same test rows;
overall accuracy, in brackets undamaged buildings recognised of those assessed). "all, unweighted" is the
paper's plain forest fitted on every training row; "changed, balanced" fits it only on buildings with
changed points (the others are "no damage" by rule) with class weights inverse to class frequency:

{ablation_table(ablation or {})}

Confusion matrices: `confusion_*.png`; all numbers: `results.json`.
"""
    write_text(out / "README.md", text)


__all__ = ["CLASSIFIERS", "PAPER_TABLE", "Evaluation", "ExperimentSettings", "comparison_table",
           "run_paper_experiment"]
