"""Evaluation as in Zahs et al.: per grade one-vs-rest OA / precision / recall / F1, damaged
vs undamaged, confusion matrix.

Result CSV (written by `classify`): one row per building with at least `building_id`,
`predicted_grade` and `assessable` (1/0). Truth CSV: `building_id`, `grade`. Buildings
that are not assessable are left out of the metrics and counted; EMS-98 grades 1–2 are
geometrically "no damage" at UAV resolution (docs/DESIGN.md) and count as undamaged.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..grades import short_name

TARGET_GRADES = (0, 3, 4, 5)
TARGET_SHORT_NAMES = {g: short_name(g) for g in TARGET_GRADES}  # tables and plots: the paper's short names
NOT_AVAILABLE = "n/a"


class EvaluationError(QuakeScanError):
    """Result and truth tables cannot be compared."""


def binary_metrics(truth: np.ndarray, pred: np.ndarray) -> dict:
    """OA, precision, recall, F1 of boolean predictions; 0 where a ratio has no cases, and
    those metrics named in `undefined` (reports print them "n/a", see `metric_text`)."""
    truth, pred = np.asarray(truth, bool), np.asarray(pred, bool)
    tp = int(np.sum(truth & pred))
    tn = int(np.sum(~truth & ~pred))
    fp = int(np.sum(~truth & pred))
    fn = int(np.sum(truth & ~pred))
    n = tp + tn + fp + fn
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    undefined = [k for k, ok in (("oa", n), ("precision", tp + fp), ("recall", tp + fn),
                                 ("f1", tp + fp and tp + fn)) if not ok]
    return {"oa": (tp + tn) / n if n else 0.0, "precision": precision, "recall": recall, "f1": f1,
            "tp": tp, "tn": tn, "fp": fp, "fn": fn, "undefined": undefined}


def metric_defined(m: dict, key: str) -> bool:
    """False for a ratio without cases: recall and F1 of a class absent from the truth,
    precision of a class never predicted (dicts written before `undefined` existed are read
    from their counts)."""
    if "undefined" in m:
        return key not in m["undefined"]
    tp, fp, fn, tn = (int(m.get(k, 0)) for k in ("tp", "fp", "fn", "tn"))
    return bool({"oa": tp + fp + fn + tn, "precision": tp + fp, "recall": tp + fn,
                 "f1": (tp + fp) and (tp + fn)}.get(key, 1))


def metric_text(m: dict, key: str, digits: int = 1, unit: str = " %") -> str:
    """A metric in percent for reports, "n/a" where it has no cases (never a 0 % that reads
    as a failure)."""
    return f"{100 * m[key]:.{digits}f}{unit}" if metric_defined(m, key) else NOT_AVAILABLE


def to_target_grade(g: np.ndarray) -> np.ndarray:
    """EMS-98 grade → the paper's classes: 1–2 become 0 (no visible damage)."""
    g = np.asarray(g, dtype=np.int64)
    return np.where(g <= 2, 0, g)


@dataclass
class Evaluation:
    per_grade: dict  # grade → binary metrics (one vs rest)
    damaged: dict  # any damage (3–5) vs none
    confusion: np.ndarray  # rows truth, columns prediction, over TARGET_GRADES
    n: int
    not_assessable: int = 0
    missing: list = field(default_factory=list)

    @property
    def overall_accuracy(self) -> float:
        """Share of buildings whose grade (0/3/4/5) is right, over all classes at once."""
        return float(np.trace(self.confusion) / self.n) if self.n else 0.0

    def to_json(self) -> dict:
        return {"n": self.n, "overall_accuracy": self.overall_accuracy,
                "per_grade": {str(g): m for g, m in self.per_grade.items()}, "damaged_vs_undamaged": self.damaged,
                "confusion": {"grades": list(TARGET_GRADES), "rows_truth_columns_prediction": self.confusion.tolist()},
                "not_assessable": self.not_assessable, "missing": list(self.missing)}

    def table(self) -> str:
        rows = ["| class | OA | precision | recall | F1 |", "|---|---|---|---|---|"]
        named = [(TARGET_SHORT_NAMES[g], self.per_grade[g]) for g in TARGET_GRADES]
        for name, m in named + [("damaged vs undamaged", self.damaged)]:
            rows.append(f"| {name} | " + " | ".join(metric_text(m, k) for k in ("oa", "precision", "recall", "f1"))
                        + " |")
        return "\n".join(rows)


def evaluate_grades(truth: np.ndarray, pred: np.ndarray) -> Evaluation:
    t, p = to_target_grade(truth), to_target_grade(pred)
    per = {g: binary_metrics(t == g, p == g) for g in TARGET_GRADES}
    dmg = binary_metrics(t > 0, p > 0)
    conf = np.zeros((len(TARGET_GRADES), len(TARGET_GRADES)), np.int64)
    index = {g: i for i, g in enumerate(TARGET_GRADES)}
    for a, b in zip(t, p):
        conf[index[int(a)], index[int(b)]] += 1
    return Evaluation(per, dmg, conf, len(t))


def _read_csv(path: Path, needed: tuple) -> list[dict]:
    from .csv_table import read_csv_rows

    _, rows = read_csv_rows(path, EvaluationError)
    if not rows:
        raise EvaluationError(f"{path}: no rows")
    missing = [c for c in needed if c not in rows[0]]
    if missing:
        raise EvaluationError(f"{path}: missing columns {missing} (has {list(rows[0])})")
    return rows


def read_truth(path: str | os.PathLike) -> dict[int, int]:
    """{building_id: grade} from a truth CSV (building_id, grade) or a post-event scene bundle
    folder (the grades in its scene.json)."""
    path = Path(path)
    if path.is_dir():
        import json

        manifest = path / "scene.json"
        try:
            doc = json.loads(manifest.read_bytes())  # bytes: UTF-8 whatever the locale
            grades = {int(b["id"]): int(b["grade"]) for b in doc["buildings"]}
        except FileNotFoundError:
            raise EvaluationError(f"{manifest}: a truth folder must be a scene bundle with scene.json") from None
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
            raise EvaluationError(f"{manifest}: cannot read building grades ({e!r})") from None
        bad = {b: g for b, g in grades.items() if not 0 <= g <= 5}
        if bad:
            raise EvaluationError(f"{manifest}: grades {bad} are not EMS-98 grades 0–5")
        return grades
    return read_grade_csv(path, EvaluationError)


def read_grade_csv(path, error=EvaluationError) -> dict[int, int]:
    """{building_id: grade} from a truth CSV (columns building_id, grade 0–5); `error`: the
    caller's error class. A building listed twice is refused (which row is the truth?)."""
    from .csv_table import read_csv_rows

    path = Path(path)
    _, rows = read_csv_rows(path, error, "truth file")
    if not rows or not {"building_id", "grade"} <= set(rows[0]):
        raise error(f"{path}: needs columns building_id and grade")
    out, line_of = {}, {}
    for k, r in enumerate(rows, start=2):
        try:
            bid, g = int(r["building_id"]), int(r["grade"])
        except (TypeError, ValueError):
            raise error(f"{path}: line {k}: building_id and grade must be integers, got "
                        f"{r['building_id']!r}, {r['grade']!r}") from None
        if not 0 <= g <= 5:
            raise error(f"{path}: line {k}: grade {g} is not an EMS-98 grade 0–5")
        if bid in out:
            raise error(f"{path}: line {k}: building {bid} is listed twice (also line {line_of[bid]}); "
                        "keep one row per building")
        out[bid], line_of[bid] = g, k
    return out


def evaluate_files(result_csv: str | os.PathLike, truth_csv: str | os.PathLike) -> Evaluation:
    """Join result and truth by building_id and evaluate the assessable buildings."""
    result_csv, truth_csv = Path(result_csv), Path(truth_csv)
    res = _read_csv(result_csv, ("building_id", "predicted_grade"))
    truth = read_truth(truth_csv)
    t, p, not_assessable, seen = [], [], 0, set()
    for line, r in enumerate(res, start=2):
        try:
            bid = int(r["building_id"])
            assessable = str(r.get("assessable", "1")).strip() not in ("0", "false", "False")
            grade = int(r["predicted_grade"]) if assessable else None
        except (TypeError, ValueError):
            raise EvaluationError(f"{result_csv}: line {line}: building_id and, for an assessable building, "
                                  f"predicted_grade must be integers, got {r.get('building_id')!r}, "
                                  f"{r.get('predicted_grade')!r}") from None
        if bid in seen:
            raise EvaluationError(f"{result_csv}: line {line}: building {bid} is listed twice")
        seen.add(bid)
        if bid not in truth:
            continue
        if not assessable:
            not_assessable += 1
            continue
        if grade not in (0, 1, 2, 3, 4, 5):
            raise EvaluationError(f"{result_csv}: line {line}: predicted grade {grade} is not an EMS-98 grade 0–5")
        t.append(truth[bid])
        p.append(grade)
    if not t:
        raise EvaluationError(f"{result_csv}: no assessable building shares an ID with {truth_csv}")
    ev = evaluate_grades(np.array(t), np.array(p))
    ev.not_assessable = not_assessable
    ev.missing = sorted(set(truth) - seen)
    return ev


def plot_confusion(ev: Evaluation, path: str | os.PathLike, title: str = "Damage grades") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [TARGET_SHORT_NAMES[g] for g in TARGET_GRADES]
    fig, ax = plt.subplots(figsize=(4.8, 4.2), dpi=120)
    ax.imshow(ev.confusion, cmap="Blues")
    for i in range(len(names)):
        for j in range(len(names)):
            v = ev.confusion[i, j]
            ax.text(j, i, str(v), ha="center", va="center",
                    color="white" if v > ev.confusion.max() / 2 else "black")
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("predicted")
    ax.set_ylabel("reference")
    ax.set_title(title)
    fig.tight_layout()
    from ..runtime.atomic import open_replacing

    try:
        with open_replacing(path, "wb") as f:
            fig.savefig(f, format="png")
    finally:
        plt.close(fig)
