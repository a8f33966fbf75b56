"""Training a damage model from labelled pairs of epochs (`quakescan train`).

A training pair is a pre- and a post-event point cloud whose buildings carry grades: the
post epoch's `grade` dimension (simulated data; the most frequent grade among a building's
post-event points) or a truth CSV (`building_id,grade`). EMS-98 grades 1–2 are trained as
"no damage" (docs/DESIGN.md: not visible at UAV resolution). Rows are split 70/30 grouped by
building: the same building of one pre-event city never appears on both sides, even when
it occurs in several pairs (heavy, extreme, destruction of one city).
"""
from __future__ import annotations

import datetime
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..change.pipeline import describe_pair, descriptor_matrix
from ..change.settings import PipelineSettings
from ..errors import QuakeScanError
from ..formats.pointcloud import GRADE_UNKNOWN, Epoch
from ..results.evaluation import Evaluation, evaluate_grades, read_grade_csv, to_target_grade
from ..runtime.progress import ProgressCallback, in_stage
from ..formats.pair import load_pair
from .model import DamageModel, grouped_split, predict_grades, train_damage_forest

log = logging.getLogger(__name__)


class TrainingError(QuakeScanError):
    """Training data are missing, unlabelled or inconsistent."""


@dataclass
class TrainingPair:
    pre: str
    post: str
    truth: str | None = None
    footprints: str | None = None


def read_truth_csv(path: str | os.PathLike) -> dict[int, int]:
    """{building_id: grade} from a CSV with columns building_id, grade (0–5), one row per
    building (`quakescan.results.evaluation.read_grade_csv`, the one truth reader)."""
    return read_grade_csv(path, TrainingError)


def grades_from_epoch(epoch: Epoch) -> dict[int, int]:
    """{building_id: grade}: the most frequent known grade of each building's points."""
    if epoch.grade is None or epoch.building_id is None:
        raise TrainingError(f"{epoch.source}: no grade/building_id dimensions; give a truth CSV")
    known = (epoch.grade != GRADE_UNKNOWN) & (epoch.building_id > 0)
    ids, grades = epoch.building_id[known], epoch.grade[known].astype(np.int64)
    if len(ids) == 0:
        raise TrainingError(f"{epoch.source}: no building point has a known grade; give a truth CSV")
    key = ids * 8 + grades
    uk, counts = np.unique(key, return_counts=True)
    best: dict[int, tuple[int, int]] = {}
    for k, c in zip(uk.tolist(), counts.tolist()):
        bid, g = divmod(k, 8)
        if bid not in best or c > best[bid][1]:
            best[bid] = (g, c)
    return {b: g for b, (g, _) in best.items()}


@dataclass
class TrainingTable:
    x: np.ndarray        # (n, d) descriptors
    y: np.ndarray        # (n,) target grade 0/3/4/5
    groups: np.ndarray   # (n,) building group: pre-event file + building ID
    names: list
    building_ids: np.ndarray
    pair_of_row: np.ndarray


def training_table(pairs: Sequence[TrainingPair], settings: PipelineSettings, *, workers: int = -1,
                   progress: ProgressCallback | None = None) -> TrainingTable:
    """The described rows of every pair. `progress` counts each pair's buildings as a stage
    named after its post-event file."""
    names = settings.descriptor_names()
    xs, ys, groups, bids, pair_of = [], [], [], [], []
    group_codes: dict[tuple, int] = {}
    for k, pair in enumerate(pairs):
        data = load_pair(pair.pre, pair.post, pair.footprints)
        pre, post = data.pre, data.post
        truth = read_truth_csv(pair.truth) if pair.truth else grades_from_epoch(post)
        rows = [r for r in describe_pair(pre, post, settings, workers=workers,
                                         progress=in_stage(progress, Path(pair.post).name))
                if r.assessable and r.building_id in truth]
        if not rows:
            raise TrainingError(f"{pair.post}: no assessable building has a grade")
        xs.append(descriptor_matrix(rows, names))
        ys += [truth[r.building_id] for r in rows]
        pre_key = os.path.realpath(pair.pre)
        for r in rows:
            groups.append(group_codes.setdefault((pre_key, r.building_id), len(group_codes)))
            bids.append(r.building_id)
            pair_of.append(k)
        log.info("%s: %d buildings", pair.post, len(rows))
    return TrainingTable(np.vstack(xs), to_target_grade(np.array(ys)), np.array(groups), names,
                         np.array(bids), np.array(pair_of))


def train(pairs: Sequence[TrainingPair], settings: PipelineSettings, *, n_estimators: int = 100,
          max_depth: int | None = 5, test_size: float = 0.3, seed: int = 0, workers: int = -1,
          progress: ProgressCallback | None = None, command: str = "", rule: bool = True, classifier: dict | None = None
          ) -> tuple[DamageModel, Evaluation | None, TrainingTable]:
    """Fit the forest on the training 70 % (grouped by building) and evaluate it on the rest.

    With test_size 0 the forest sees every row and no evaluation is returned. rule: fit on
    buildings with changed points and decide the others by rule (the paper's way), or
    (False) fit on every row and ask the model about every building; the model file records
    which. classifier: further `quakescan.learning.model.fit_classifier` arguments (kind, calibration, ...);
    calibration folds are grouped by building."""
    t0 = time.perf_counter()
    table = training_table(pairs, settings, workers=workers, progress=progress)
    if len(np.unique(table.y)) < 2:
        raise TrainingError(f"all {len(table.y)} training buildings have grade {table.y[0]}: "
                            "a classifier needs at least two grades")
    if test_size > 0:
        if len(np.unique(table.groups)) < 4:
            raise TrainingError(f"{len(np.unique(table.groups))} buildings are too few for a "
                                "train/test split; use --test-size 0")
        tr, te = grouped_split(table.groups, test_size=test_size, seed=seed)
    else:
        tr, te = np.arange(len(table.y)), np.zeros(0, np.int64)
    fit_args = {"max_depth": max_depth, "seed": seed, **(classifier or {})}
    if "max_iter" not in fit_args:  # boosting rounds given as such: n_estimators would say them twice
        fit_args.setdefault("n_estimators", n_estimators)
    if fit_args.get("calibration"):
        fit_args.setdefault("groups", table.groups[tr])
    est = train_damage_forest(table.x[tr], table.y[tr], table.names, rule=rule, **fit_args)
    ev = (evaluate_grades(table.y[te], predict_grades(est, table.x[te], table.names, rule=rule))
          if len(te) else None)
    provenance = {
        "created": datetime.date.today().isoformat(),
        "command": command,
        "pairs": [{"pre": os.path.basename(p.pre), "post": os.path.basename(p.post),
                   "truth": os.path.basename(p.truth) if p.truth else "grade dimension"} for p in pairs],
        "n_rows": int(len(table.y)), "n_train": int(len(tr)), "n_test": int(len(te)),
        "grades_train": {str(g): int(c) for g, c in zip(*np.unique(table.y[tr], return_counts=True))},
        "n_estimators": n_estimators, "max_depth": max_depth, "seed": seed, "test_size": test_size,
        "test_overall_accuracy": None if ev is None else round(float(ev.overall_accuracy), 4),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    model = DamageModel(est, list(table.names), settings.radius_m, split=settings.to_json(),
                        provenance=provenance, no_change_rule=rule)
    return model, ev, table
