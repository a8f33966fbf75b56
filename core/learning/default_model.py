"""The model QuakeScan ships: the transfer training set, a classifier chosen by measurement,
the data it can judge, and where it all came from.

1. **Descriptors** (`TRANSFER_SETTINGS`): the density-invariant surface descriptors of
   `quakescan.change.surface` only, without the distances and LoD of the significant core points
   (`MODEL_DESCRIPTORS`). The paper's point-feature descriptors are left out of the shipped
   model: several of them count points (densities, neighbours) and the rest are statistics
   over a split whose gate depends on the sensor's noise; `bench/bench_transfer.py` measures
   both with and without them on the same rows.
2. **Training set** (`quakescan.learning.trainset.default_plan`): thousands of buildings, every
   acquisition randomised, cross-source pairs; rows labelled damaged whose acquisition saw
   no change at all are left out (`visible_damage`).
3. **Classifier** (`select_classifier`): random forest and gradient boosting, with and
   without calibrated probabilities, compared by cross-validation that holds out whole
   *cities* (a building's rows, and its neighbours', never on both sides); the best macro
   F1 over the four grades wins (ties: the earlier, simpler candidate). It is fitted on
   every row and asked about every assessable building (no "no change" rule: an undamaged
   building with changed points is exactly what it learned).
4. **What it can judge**: the sparsest roof density (1st percentile) and the smallest
   post-event coverage (0.1th percentile) among its training rows (physics twins, which
   repeat their cities' acquisitions, counted once: `without_twins`) become the pipeline's
   `min_density_pts_m2` and `min_coverage`: a building below them is "not assessable" with
   the reason, not guessed. A size limit (`min_cells`, raster cells of the footprint) is
   recorded per row and available, but not set (see CELLS_QUANTILE).
5. **Provenance**: plan, counts, the comparison table, the choice and its scores, the
   command and date go into the model file.
"""
from __future__ import annotations

import datetime
import math
import time
from pathlib import Path

import numpy as np

from ..change.descriptors import DESCRIPTOR_VERSION
from ..change.settings import PipelineSettings
from ..change.surface import NOISE_FREE_DESCRIPTORS, SurfaceSettings
from ..runtime.progress import stage_log
from .model import ModelError
from .model_selection import MIN_CITIES_TO_GROUP, cv_groups

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "data" / "default_model.skops"


def default_model_path() -> Path:
    """The shipped model's file (the one `classify` applies unless given another)."""
    if not DEFAULT_MODEL.is_file():
        raise ModelError(f"{DEFAULT_MODEL}: the shipped default model is missing; rebuild it with "
                         "`python blender_scripts/make_default_model.py` or pass --model")
    return DEFAULT_MODEL


# The training set's tables hold every surface descriptor (so that an ablation can put any of
# them back); the model uses those whose meaning does not depend on the sensor's noise: the
# signed distances and the level of detection of the significant core points are left out
# (on an unchanged real roof the few "significant" core points are noise, and their
# distances and LoD describe the sensor, not the building; bench_transfer measures them).
TABLE_SETTINGS = PipelineSettings(surface=SurfaceSettings(), paper_descriptors=False)
# The openings per return (`o_*`, quakescan.change.openings) are read by the model since
# openings version 4: earlier definitions found heavy damage in real points but called undamaged
# buildings damaged across sensors, on walls a photo flight reconstructs and a laser barely
# samples and through real city models' open shells (docs/results.md).
MODEL_DESCRIPTORS = NOISE_FREE_DESCRIPTORS
TRANSFER_SETTINGS = PipelineSettings(surface=SurfaceSettings(), paper_descriptors=False,
                                     surface_descriptors=MODEL_DESCRIPTORS)
CANDIDATES = (
    {"name": "rf (paper: 100 trees, depth 5)", "kind": "rf", "n_estimators": 100, "max_depth": 5},
    {"name": "rf 300 deep", "kind": "rf", "n_estimators": 300, "max_depth": None, "min_samples_leaf": 2},
    {"name": "hgb", "kind": "hgb", "max_depth": None},
    {"name": "rf 300 deep + sigmoid", "kind": "rf", "n_estimators": 300, "max_depth": None, "min_samples_leaf": 2,
     "calibration": "sigmoid"},
    {"name": "hgb + sigmoid", "kind": "hgb", "max_depth": None, "calibration": "sigmoid"},
)
DENSITY_QUANTILE = 0.01
# No size limit in the shipped model: its training footprints span 32 cells and more (1st
# percentile 46), while half of the AHN3 Delft buildings in a 25 % thinning span fewer than
# 38 (row houses, sheds at ~2 pts/m²). A limit at the 1st percentile made 61 of 90 of them
# "not assessable" — an answer withheld for most of a real district, for a training set that
# lacks small buildings at airborne densities. `size_limit(table, q)` sets one where wanted.
CELLS_QUANTILE = None
# Coverage is lowest where it matters most: the rubble of a collapse between tall neighbours is
# partly hidden from the air (1 % of the destroyed training buildings have < 74 % coverage),
# so the limit is the rarest coverage seen, not a percentile of all rows.
COVERAGE_QUANTILE = 0.001


# Descriptors that show a change at all: a row labelled damaged where every one of them is
# zero is damage the acquisition did not see (half the heavy buildings of an ALS-like pair at
# 2-30 pts/m²: roof holes smaller than its cells). Teaching the classifier that such a building
# is damaged teaches it to guess from the faintest noise; they are left out of training, and
# on real data such a building can only be "no visible damage" anyway.
EVIDENCE = ("s_lowered_1m", "s_volume_loss", "s_raised", "s_debris_ring", "s_see_through", "s_interior_seen",
            "m_changed", "m_holes", "m_largest_patch", "o_fallen_excess")


def visible_damage(table) -> np.ndarray:
    """Rows to train on: undamaged ones, and damaged ones where some change was seen."""
    cols = [table.names.index(n) for n in EVIDENCE if n in table.names]
    if not cols:
        return np.ones(len(table.y), bool)
    seen = np.any(table.x[:, cols] > 0, axis=1)
    return (table.y == 0) | seen


def training_rows(table):
    """The table without damaged rows whose damage the acquisition did not see (`visible_damage`)."""
    return table.subset(visible_damage(table))


def data_limits(table) -> tuple[float, float]:
    """(minimum density pts/m², minimum coverage) the model is made for: the 1st percentile of
    its training rows' sparser-epoch roof density and the 0.1th of their post-event coverage,
    rounded down."""
    dens = np.nanmin(table.density, axis=1)
    dens = dens[np.isfinite(dens)]
    d = float(np.quantile(dens, DENSITY_QUANTILE)) if len(dens) else 0.0
    cov = 1.0 - table.x[:, table.names.index("s_post_gap")] if "s_post_gap" in table.names else np.ones(1)
    c = float(np.quantile(cov, COVERAGE_QUANTILE))
    return math.floor(d * 10) / 10, math.floor(c * 100) / 100


def without_twins(table):
    """The rows of the table's own acquisitions: a physics twin repeats its city's buildings
    and acquisitions (quakescan.learning.trainset.PHYSICS_TWINS), so counting its rows in the data limits
    would weigh four cities' sensors twice (it moved the density limit from 1.8 to 1.9 pts/m²,
    and a quarter of a real district thinned to 1.8 pts/m² out of what the model answers)."""
    twin = np.array([c.endswith("-physics") for c in table.pair_city], dtype=bool)
    return table.subset(~twin) if twin.any() else table


def size_limit(table, quantile: float | None = CELLS_QUANTILE) -> int:
    """Fewest raster cells of a footprint the model is made for: the `quantile` of its
    training rows' cell counts; 0 (no limit) when `quantile` is None or the table predates
    cell counts."""
    if quantile is None or table.cells is None or not len(table.cells):
        return 0
    return int(np.quantile(table.cells, quantile))


def model_columns(table, names=MODEL_DESCRIPTORS):
    """The table restricted to the descriptor columns `names` (a copy with x and names replaced)."""
    import dataclasses

    missing = [n for n in names if n not in table.names]
    if missing:
        raise ValueError(f"the training table lacks descriptors {missing}")
    cols = [table.names.index(n) for n in names]
    return dataclasses.replace(table, x=table.x[:, cols], names=list(names))


def select_classifier(table, candidates=CANDIDATES, *, seed: int = 0, n_splits: int = 5):
    """Scores of every candidate under city-held-out cross-validation, and the winner's config."""
    from .model_selection import compare_classifiers

    groups = cv_groups(table)
    scores = compare_classifiers(table.x, table.y, groups, table.names, list(candidates), seed=seed,
                                 n_splits=min(n_splits, len(set(groups.tolist()))))
    best = max(range(len(scores)), key=lambda i: (round(scores[i].macro_f1, 3), -i))
    return scores, dict(candidates[best])


def fit_default_model(table, plan, config: dict, scores, *, seed: int = 0, command: str = "",
                      seconds_building: float | None = None):
    """The chosen classifier fitted on every row, with its settings and provenance."""
    from .model import DamageModel, fit_classifier
    from .model_selection import comparison_table

    fit_args = {k: v for k, v in config.items() if k not in ("name", "rule")}
    t0 = time.perf_counter()
    est = fit_classifier(table.x, table.y, seed=seed, groups=cv_groups(table) if fit_args.get("calibration") else None,
                         **fit_args)
    min_density, min_coverage = data_limits(without_twins(table))
    min_cells = size_limit(table)
    settings = PipelineSettings.from_json({**TRANSFER_SETTINGS.to_json(), "min_density_pts_m2": min_density,
                                           "min_coverage": min_coverage, "min_cells": min_cells})
    chosen = next(s for s in scores if s.name == config["name"])
    sensors = {}
    for p in table.pair:
        sensors[table.sensors[p]] = sensors.get(table.sensors[p], 0) + 1
    provenance = {
        "created": datetime.date.today().isoformat(),
        "command": command,
        # "quakescan.trainset": the training set's module (quakescan.learning.trainset) as the
        # shipped model's files and their reports name it, kept byte for byte
        "dataset": (f"transfer training set '{plan.name}' (seed {plan.seed}): {len(plan.cities)} cities, "
                    f"{len(plan.pairs)} pairs, {len(table.y)} building rows; random acquisitions, "
                    "cross-source pairs, mixed post-event cities (quakescan.trainset)"),
        "cities": [c.name for c in plan.cities],
        "rows_per_sensor_pair": sensors,
        "grades_train": {str(g): int(n) for g, n in zip(*np.unique(table.y, return_counts=True))},
        "n_rows": int(len(table.y)), "n_train": int(len(table.y)), "n_test": 0,
        "classifier_selection": {"criterion": "macro F1, cross-validation holding out whole cities"
                                              if len(set(table.city.tolist())) >= MIN_CITIES_TO_GROUP
                                              else "macro F1, cross-validation holding out buildings",
                                 "chosen": config["name"], "table": comparison_table(scores),
                                 "scores": [s.to_json() for s in scores]},
        "test_overall_accuracy": round(float(chosen.accuracy), 4),
        "test_note": "held-out scores: pooled out-of-fold predictions, cities held out",
        "limits": {"min_density_pts_m2": min_density, "min_coverage": min_coverage, "min_cells": min_cells,
                   "rule": f"density: {DENSITY_QUANTILE:.1%} quantile of the training rows' sparser epoch; "
                           f"coverage: {COVERAGE_QUANTILE:.1%} quantile; raster cells of the footprint: "
                           + ("none" if CELLS_QUANTILE is None else f"{CELLS_QUANTILE:.1%} quantile")},
        "seed": seed,
        "descriptor_version": DESCRIPTOR_VERSION,
        "seconds": {"fit": round(time.perf_counter() - t0, 1), "training_set": seconds_building},
    }
    return DamageModel(est, list(table.names), settings.radius_m, split=settings.to_json(), provenance=provenance,
                       no_change_rule=False)


def transfer_training_table(work: Path, *, seed: int = 0, size: str = "full", scenes: str = "both",
                            damage: str = "patterns", small: bool = False, workers: int = -1,
                            keep_clouds: bool = True):
    """The plan and the descriptor table of the training set under `work`: `scenes` clean (the
    generator's bare scenes, under work/trainset), realistic (the same cities with roof detail,
    trees and cars, labelled through footprints, under work/trainset_realistic) or both;
    `damage` "both" adds the clean plan's physics twins, `small` the small-building cities
    (`quakescan.learning.trainset.default_plan`); `keep_clouds` False removes each cloud once
    its pairs are described (`quakescan.learning.trainset.build`)."""
    from .trainset import TrainingPlan, build, combine_tables, default_plan

    if scenes not in ("clean", "realistic", "both"):
        raise ValueError(f"scenes must be clean, realistic or both, got {scenes!r}")
    work = Path(work)
    parts = {}
    for kind in (("clean", "realistic") if scenes == "both" else (scenes,)):
        plan = default_plan(seed, size, kind, damage, small)
        folder = work / ("trainset" if kind == "clean" else "trainset_realistic")
        parts[kind] = (plan, build(folder, plan, TABLE_SETTINGS, workers=workers, keep_clouds=keep_clouds))
    if scenes != "both":
        return parts[scenes]
    (clean_plan, clean), (real_plan, real) = parts["clean"], parts["realistic"]
    plan = TrainingPlan(clean_plan.cities + real_plan.cities, clean_plan.pairs + real_plan.pairs, seed,
                        f"{clean_plan.name}+realistic", labels="simulator")
    return plan, combine_tables(clean, real)


def calibrate_on_real_points(model, table, full, config: dict, real_pairs, *, seed: int = 0) -> dict:
    """Set `model.temperature` from the real-point rows' out-of-fold probabilities
    (`quakescan.learning.real_calibration`) and record how in its provenance."""
    from .real_calibration import real_calibration

    stage_log.info(f"calibrating on real points: {len(real_pairs)} fits, each without one real pair")
    record = real_calibration(table, full, config, real_pairs, seed=seed)
    model.temperature = record["temperature"]
    model.provenance["real_calibration"] = record
    stage_log.info(f"temperature {record['temperature']}: real rows' log-loss {record['log_loss_before']} -> "
                   f"{record['log_loss_after']}, ECE {record['ece_before']} -> {record['ece_after']}")
    return record


def default_tables(work: Path, *, seed: int = 0, size: str = "full", scenes: str = "both", damage: str = "both",
                   small: bool = False, workers: int = -1, keep_clouds: bool = False, real_data: Path | None = None):
    """(plan, training rows, every row, real pair names) of the shipped model's recipe under
    `work` (built where missing, read where cached): the simulated transfer table, the real
    pairs appended (`real_data`), the model's columns, the unseen damage left out of training."""
    plan, table = transfer_training_table(work, seed=seed, size=size, scenes=scenes, damage=damage, small=small,
                                          workers=workers, keep_clouds=keep_clouds)
    real_pairs = []
    if real_data is not None:
        from .realset import REAL_PLAN, REAL_REPEAT, append_tables, real_table

        stage_log.info(f"real points: {len(REAL_PLAN)} pairs with damage injected (quakescan.learning.realset)")
        table = append_tables(table, real_table(Path(work) / "realset", Path(real_data), TABLE_SETTINGS,
                                                workers=workers, repeat=REAL_REPEAT))
        real_pairs = [p.name for p in REAL_PLAN]
    full = model_columns(table)
    return plan, training_rows(full), full, real_pairs


def recalibrate_default_model(model_path: Path, work: Path, output: Path, *, seed: int = 0, note: str = "",
                              **recipe) -> dict:
    """Refit only the real-point temperature of the model at `model_path` with the recipe's
    out-of-fold calibration (`calibrate_on_real_points`: each real pair predicted by the
    model's classifier configuration fitted on the recipe's table without that pair) and write
    it to `output`. The estimator is left as it is, so every grade it gives stays the same;
    the out-of-fold fits depend on the table and the configuration, not on the estimator.
    `recipe`: `default_tables`' arguments (real_data required). Returns the calibration record."""
    from .model import load_model, save_model

    if recipe.get("real_data") is None:
        raise ValueError("recalibrating needs the real archives (real_data): the temperature is fitted on them")
    model = load_model(model_path)
    chosen = model.provenance.get("classifier_selection", {}).get("chosen")
    config = next((c for c in CANDIDATES if c["name"] == chosen), None)
    if config is None:
        raise ValueError(f"{model_path}: its classifier {chosen!r} is none of the recipe's candidates "
                         f"{[c['name'] for c in CANDIDATES]}")
    _, table, full, real_pairs = default_tables(work, seed=seed, **recipe)
    before = model.temperature
    record = calibrate_on_real_points(model, table, full, config, real_pairs, seed=seed)
    record["refit"] = (f"temperature refitted on a table of {len(table.y)} training rows, estimator kept "
                       f"(before: T {before:g}){'; ' + note if note else ''}")
    save_model(model, output)
    return record


def make_default_model(work: Path, output: Path, *, seed: int = 0, size: str = "full", scenes: str = "both",
                       damage: str = "both", small: bool = False, workers: int = -1,
                       command: str = "", keep_clouds: bool = False, real_data: Path | None = None):
    """Build the training set under `work`, choose and fit the classifier, write `output`.
    The training clouds are removed once described unless `keep_clouds` (the tables are what
    the model is made from; the large plan's clouds fill 27 GB). `real_data`: the folder of
    the real archives of `quakescan.learning.realset` (damage injected into their points, rows
    repeated `REAL_REPEAT` times); None: simulated rows only."""
    from .model import save_model

    t0 = time.perf_counter()
    plan, table, full, real_pairs = default_tables(work, seed=seed, size=size, scenes=scenes, damage=damage,
                                                   small=small, workers=workers, keep_clouds=keep_clouds,
                                                   real_data=real_data)
    stage_log.info(f"{len(full.y) - len(table.y)} of {len(full.y)} rows left out: damage their acquisition did not see")
    t_build = round(time.perf_counter() - t0, 1)
    stage_log.info(f"comparing {len(CANDIDATES)} classifiers (cross-validation holding out whole cities)")
    scores, config = select_classifier(table, seed=seed)
    from .model_selection import comparison_table

    stage_log.info(comparison_table(scores))
    stage_log.info(f"chosen: {config['name']}")
    model = fit_default_model(table, plan, config, scores, seed=seed, command=command, seconds_building=t_build)
    model.provenance["size"] = size
    model.provenance["scenes"] = scenes
    model.provenance["damage"] = damage
    model.provenance["small_buildings"] = small
    if real_pairs:
        from .realset import REAL_REPEAT

        model.provenance["real_points"] = {"pairs": real_pairs, "repeat": REAL_REPEAT,
                                           "rows": int(sum(c in real_pairs for c in table.pair_city)),
                                           "how": "damage injected into real archives by quakescan inject "
                                                  "(quakescan.learning.realset); AHN3 tile 1 never"}
    model.provenance["rows_left_out"] = {"count": int(len(full.y) - len(table.y)), "of": int(len(full.y)),
                                         "why": "labelled damaged, but no change seen in any of " + ", ".join(EVIDENCE)}
    if real_pairs:
        calibrate_on_real_points(model, table, full, config, real_pairs, seed=seed)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    save_model(model, output)
    stage_log.info(f"model -> {output} (limits: {model.provenance['limits']}); {time.perf_counter() - t0:.0f} s in all")
    return model, scores, table
