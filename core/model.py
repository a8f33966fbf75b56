"""Random-forest damage model: training, persistence, prediction.

A model file (skops format) holds the fitted scikit-learn forest and everything needed to
apply it again: feature names, neighbourhood radius, split settings, class labels,
training provenance and the versions that made it. Loading never executes code from the
file: skops rebuilds only the types on an allow-list, and a file asking for anything
else is refused.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .errors import QuakeScanError

FORMAT = "quakescan-model"
VERSION = 1
GRADE_LABELS = {0: "no damage", 1: "negligible", 2: "moderate", 3: "heavy", 4: "extreme", 5: "destruction"}
# Everything a forest needs beyond skops' built-in safe types.
TRUSTED_TYPES = ["sklearn.tree._tree.Tree"]


class ModelError(QuakeScanError):
    """A model file is missing, tampered with, or does not fit the data."""


@dataclass
class DamageModel:
    estimator: object  # fitted sklearn RandomForestClassifier
    feature_names: list
    radius_m: float
    split: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)

    @property
    def classes(self) -> list:
        """Grades the forest can answer."""
        return [int(c) for c in self.estimator.classes_]

    @property
    def grades(self) -> list:
        """Grades a classification can give: the forest's and "no damage", which a building
        without changed points gets by rule even when the forest never saw one."""
        return sorted(set(self.classes) | {0})

    def predict_proba(self, table: dict) -> np.ndarray:
        """(n, n_classes) probabilities from a table {feature name: (n,) values}."""
        missing = [f for f in self.feature_names if f not in table]
        if missing:
            raise ModelError(f"the model needs features {missing} that the data lacks "
                             f"(model features: {self.feature_names})")
        x = np.column_stack([np.asarray(table[f], dtype=np.float64) for f in self.feature_names])
        return self.estimator.predict_proba(x)

    def predict(self, table: dict) -> np.ndarray:
        p = self.predict_proba(table)
        return np.asarray(self.classes)[p.argmax(axis=1)]


SHARE_CHANGED = "share_changed"


def decided_by_rule(x: np.ndarray, names) -> np.ndarray:
    """Rows a classification decides without the forest: no changed point, so no damage
    (Zahs et al.: "buildings with no changed points would directly be considered as
    undamaged")."""
    names = list(names)
    if SHARE_CHANGED not in names:
        return np.zeros(len(x), bool)
    return np.asarray(x)[:, names.index(SHARE_CHANGED)] == 0


def train_forest(x: np.ndarray, y: np.ndarray, n_estimators: int = 100, max_depth: int | None = 5,
                 seed: int = 0, n_jobs: int | None = None, class_weight: str | None = "balanced"):
    """The paper's classifier: a random forest (100 trees, depth 5 by default), seeded.

    Classes weighted inversely to their frequency by default: the grade the field needs
    most, an undamaged building that nevertheless shows changed points (a neighbour's
    debris, DIM noise), is the rarest row of a simulated training set."""
    from sklearn.ensemble import RandomForestClassifier

    return RandomForestClassifier(n_estimators=n_estimators, max_depth=max_depth, random_state=seed,
                                  n_jobs=n_jobs, class_weight=class_weight).fit(x, y)


def train_damage_forest(x: np.ndarray, y: np.ndarray, names, **kw):
    """A forest fitted on the rows it will be asked about: buildings with changed points.

    Rows without changed points are decided by rule (`decided_by_rule`) when classifying;
    fitting on them too would spend the forest on all-zero rows and, with them labelled
    "no damage" by the hundred, leave the few undamaged buildings *with* changes outvoted."""
    ask = ~decided_by_rule(x, names)
    if not ask.any():
        raise ModelError(f"none of the {len(ask)} training buildings has changed points: nothing for the "
                         "forest to learn (every building would be 'no damage' by rule anyway)")
    return train_forest(np.asarray(x)[ask], np.asarray(y)[ask], **kw)


def predict_grades(estimator, x: np.ndarray, names) -> np.ndarray:
    """Grades of descriptor rows: by rule where nothing changed, by the forest elsewhere."""
    out = np.zeros(len(x), np.int64)
    ask = ~decided_by_rule(x, names)
    if ask.any():
        out[ask] = estimator.predict(np.asarray(x)[ask])
    return out


def grouped_split(groups: np.ndarray, test_size: float = 0.3, seed: int = 0):
    """Train/test row indices with all rows of a group (a building) on one side."""
    from sklearn.model_selection import GroupShuffleSplit

    gss = GroupShuffleSplit(n_splits=1, test_size=test_size, random_state=seed)
    return next(gss.split(np.zeros(len(groups)), groups=groups))


def save_model(model: DamageModel, path: str | os.PathLike) -> None:
    import sklearn
    import skops.io as sio

    meta = {
        "format": FORMAT, "version": VERSION, "quakescan": __version__, "sklearn": sklearn.__version__,
        "feature_names": list(model.feature_names), "radius_m": float(model.radius_m),
        "split": dict(model.split), "provenance": dict(model.provenance),
        "created": model.provenance.get("created") or datetime.date.today().isoformat(),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    sio.dump({"meta": meta, "estimator": model.estimator}, tmp)
    os.replace(tmp, path)


def load_model(path: str | os.PathLike) -> DamageModel:
    import skops.io as sio

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: model file does not exist")
    try:
        untrusted = sio.get_untrusted_types(file=path)
    except Exception as e:
        raise ModelError(f"{path}: not a QuakeScan model file ({e})") from None
    unexpected = sorted(set(untrusted) - set(TRUSTED_TYPES))
    if unexpected:
        raise ModelError(f"{path}: refused: the file asks to build types {unexpected} that a damage model "
                         "never contains (tampered or foreign file); nothing was executed")
    try:
        obj = sio.load(path, trusted=TRUSTED_TYPES)
    except Exception as e:
        raise ModelError(f"{path}: cannot load the model ({e})") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("meta"), dict):
        raise ModelError(f"{path}: not a QuakeScan model file (no metadata)")
    meta = obj["meta"]
    if meta.get("format") != FORMAT:
        raise ModelError(f"{path}: format {meta.get('format')!r} is not {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise ModelError(f"{path}: model format version {meta.get('version')!r} is not supported "
                         f"(this QuakeScan reads version {VERSION}); retrain with `quakescan train`")
    est = obj.get("estimator")
    names = meta.get("feature_names")
    if est is None or not hasattr(est, "predict_proba") or not isinstance(names, list):
        raise ModelError(f"{path}: incomplete model (estimator or feature names missing)")
    if getattr(est, "n_features_in_", len(names)) != len(names):
        raise ModelError(f"{path}: the forest expects {est.n_features_in_} features but the file names "
                         f"{len(names)}")
    return DamageModel(est, names, float(meta.get("radius_m", 0.0)), meta.get("split", {}),
                       dict(meta.get("provenance", {}), versions={"quakescan": meta.get("quakescan"),
                                                                   "sklearn": meta.get("sklearn")}))
