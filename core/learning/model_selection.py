"""Which classifier to ship, by measurement: grouped cross-validation of candidate
configurations on one descriptor table.

A candidate is a dict of `quakescan.learning.model.fit_classifier` arguments (kind, calibration, n_estimators,
...) plus two optional keys: `rule` (True: fitted on buildings with changed points and the
others decided by the no-change rule, as `train_damage_forest`/`predict_grades` do; default
False: fitted on and asked about every row) and `name` (for the table). Every candidate is
fitted and scored on the same folds: `StratifiedGroupKFold`, shuffled with the seed, so all
rows of a building (one group) fall in one fold and the grades spread evenly over the folds.
Scores are computed once on the pooled out-of-fold predictions (every row predicted by the
model that did not see its building), except `fold_accuracy`, which shows the spread.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from ..results.evaluation import TARGET_SHORT_NAMES, binary_metrics, to_target_grade
from .model import ModelError, decided_by_rule, native_threads, train_damage_forest

PROBABILITY_FLOOR = 1e-15  # log-loss of a probability 0 given to the true grade: log(1e-15) ≈ -34.5
_NOT_FIT_ARGUMENTS = ("name", "rule")


@dataclass
class CandidateScore:
    """How one candidate did over all folds (see the module docstring)."""

    name: str
    config: dict
    accuracy: float  # overall accuracy: share of rows whose grade is right
    macro_f1: float  # mean of the per-grade F1 over the grades in the data
    f1_per_grade: dict  # grade → one-vs-rest F1 (quakescan.results.evaluation.binary_metrics)
    damaged_f1: float  # F1 of "damaged" (grade 3–5) against "undamaged" (0–2)
    log_loss: float  # mean −ln p(true grade), p floored at PROBABILITY_FLOOR; 0 is perfect
    brier: float  # mean over rows of Σ_k (p_k − [grade = k])²: 0 perfect, 2 worst
    fit_seconds: float  # wall time of all the candidate's fits (folds summed)
    fold_accuracy: list = field(default_factory=list)  # overall accuracy of each fold

    def to_json(self) -> dict:
        d = asdict(self)
        d["f1_per_grade"] = {str(g): v for g, v in self.f1_per_grade.items()}
        return d


def candidate_name(config: dict) -> str:
    """`config["name"]`, else e.g. "rf", "hgb+sigmoid", "rf+rule"."""
    if config.get("name"):
        return str(config["name"])
    parts = [str(config.get("kind", "rf"))]
    if config.get("calibration"):
        parts.append(str(config["calibration"]))
    if config.get("rule"):
        parts.append("rule")
    return "+".join(parts)


def grouped_folds(y: np.ndarray, groups: np.ndarray, n_splits: int = 5, seed: int = 0) -> list:
    """(train, test) row indices of `n_splits` folds with every group in one test fold,
    grades stratified, shuffled with `seed` (the same seed, the same folds)."""
    from sklearn.model_selection import StratifiedGroupKFold

    n_groups = len(np.unique(groups))
    if n_groups < n_splits:
        raise ModelError(f"{n_groups} groups (buildings) are too few for {n_splits}-fold grouped "
                         "cross-validation; use fewer folds or more buildings")
    cv = StratifiedGroupKFold(n_splits=n_splits, shuffle=True, random_state=seed)
    return list(cv.split(np.zeros((len(y), 1)), y, groups))


def compare_classifiers(x: np.ndarray, y: np.ndarray, groups: np.ndarray, names: Sequence[str],
                        candidates: Sequence[dict], *, seed: int = 0, n_splits: int = 5) -> list[CandidateScore]:
    """A CandidateScore per candidate, in the candidates' order.

    x: (n, d) descriptors with columns `names` (the rule reads `share_changed`); y: (n,)
    grades; groups: (n,) one code per building. `seed` fixes the folds and is every
    candidate's fit seed unless the candidate gives its own. Calibrated candidates get
    calibration folds grouped the same way, inside each training fold. A candidate's
    `n_jobs` limits its native threads for fitting and predicting (`native_threads`): give
    1 for small tables on a busy machine."""
    x, y, groups = np.asarray(x, dtype=np.float64), np.asarray(y), np.asarray(groups)
    if not len(x) == len(y) == len(groups):
        raise ModelError(f"x has {len(x)} rows, y {len(y)} and groups {len(groups)}: give one of each per row")
    if len(np.unique(y)) < 2:
        raise ModelError(f"all {len(y)} rows have grade {y[0] if len(y) else None}: nothing to compare")
    folds = grouped_folds(y, groups, n_splits, seed)
    return [_score(x, y, groups, list(names), dict(c), folds, seed) for c in candidates]


def _score(x, y, groups, names, config, folds, seed) -> CandidateScore:
    rule = bool(config.get("rule", False))
    args = {k: v for k, v in config.items() if k not in _NOT_FIT_ARGUMENTS}
    if "groups" in args or isinstance(args.get("cv"), (list, tuple)):
        raise ModelError(f"candidate {candidate_name(config)}: groups and calibration splits given as rows "
                         "cannot follow the cross-validation folds; give cv as a number of folds (the "
                         "comparison groups them by building)")
    args.setdefault("seed", seed)
    grades = np.array(sorted(set(np.unique(y).tolist()) | ({0} if rule else set())))
    proba = np.zeros((len(y), len(grades)))
    seconds, fold_accuracy = 0.0, []
    for tr, te in folds:
        fold_args = dict(args)
        if fold_args.get("calibration"):
            fold_args["groups"] = groups[tr]  # calibration folds grouped by building, too
        with native_threads(args.get("n_jobs")):
            t0 = time.perf_counter()
            est = train_damage_forest(x[tr], y[tr], names, rule=rule, **fold_args)
            seconds += time.perf_counter() - t0
            proba[te] = _fold_probabilities(est, x[te], names, rule, grades)
        fold_accuracy.append(float(np.mean(grades[proba[te].argmax(axis=1)] == y[te])))
    pred = grades[proba.argmax(axis=1)]
    present = np.unique(y)
    per_grade = {int(g): binary_metrics(y == g, pred == g)["f1"] for g in present}
    truth_onehot = (y[:, None] == grades[None, :]).astype(np.float64)
    p_true = proba[truth_onehot.astype(bool)]
    return CandidateScore(
        name=candidate_name(config), config=config,
        accuracy=float(np.mean(pred == y)),
        macro_f1=float(np.mean(list(per_grade.values()))),
        f1_per_grade=per_grade,
        damaged_f1=binary_metrics(to_target_grade(y) > 0, to_target_grade(pred) > 0)["f1"],
        log_loss=float(-np.mean(np.log(np.clip(p_true, PROBABILITY_FLOOR, 1.0)))),
        brier=float(np.mean(np.sum((proba - truth_onehot) ** 2, axis=1))),
        fit_seconds=round(seconds, 3), fold_accuracy=fold_accuracy)


def _fold_probabilities(est, x, names, rule, grades) -> np.ndarray:
    """(n, len(grades)) probabilities: the estimator's in the columns of its classes (a
    grade its fold never saw gets 0), and p(0) = 1 for rows the rule decides."""
    out = np.zeros((len(x), len(grades)))
    ask = ~decided_by_rule(x, names) if rule else np.ones(len(x), bool)
    if ask.any():
        cols = np.searchsorted(grades, np.asarray(est.classes_))
        out[np.ix_(np.flatnonzero(ask), cols)] = est.predict_proba(x[ask])
    out[~ask, np.searchsorted(grades, 0)] = 1.0
    return out


def comparison_table(scores: Sequence[CandidateScore]) -> str:
    """A markdown table, one line per candidate: overall accuracy (lowest–highest fold),
    macro F1, F1 per grade, damaged-vs-undamaged F1, log-loss, Brier score, fit seconds."""
    grades = sorted({g for s in scores for g in s.f1_per_grade})
    head = (["candidate", "OA (folds)", "macro F1"] + [f"F1 {TARGET_SHORT_NAMES.get(g, f'grade {g}')}" for g in grades]
            + ["damaged F1", "log-loss", "Brier", "fit s"])
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in scores:
        folds = f" ({100 * min(s.fold_accuracy):.1f}–{100 * max(s.fold_accuracy):.1f})" if s.fold_accuracy else ""
        cells = ([s.name, f"{100 * s.accuracy:.1f} %{folds}", f"{100 * s.macro_f1:.1f} %"]
                 + [f"{100 * s.f1_per_grade[g]:.1f} %" if g in s.f1_per_grade else "" for g in grades]
                 + [f"{100 * s.damaged_f1:.1f} %", f"{s.log_loss:.3f}", f"{s.brier:.3f}", f"{s.fit_seconds:.2f}"])
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)



MIN_CITIES_TO_GROUP = 6


def cv_groups(table) -> np.ndarray:
    """Groups of the cross-validation: whole cities (a building and its neighbours, whose debris
    and acquisitions it shares, never on both sides), or single buildings for a training set of
    fewer than MIN_CITIES_TO_GROUP cities, where city folds would leave calibration folds
    without a second city."""
    if len(set(table.city.tolist())) >= MIN_CITIES_TO_GROUP:
        return np.asarray(table.city)
    return table.groups


__all__ = ["MIN_CITIES_TO_GROUP", "CandidateScore", "candidate_name", "compare_classifiers", "comparison_table", "cv_groups",
           "grouped_folds"]
