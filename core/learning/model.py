"""Damage model: training, persistence, prediction.

A model file (skops format) holds the fitted scikit-learn classifier and everything needed
to apply it again: feature names, neighbourhood radius, split settings, class labels, the
kind of classifier (random forest or gradient boosting, calibrated or not), whether
buildings without changed points are decided by rule, training provenance and the versions
that made it. Which classifier ships is decided by measurement (`quakescan.learning.model_selection`);
the choice lives in the file, so nothing downstream branches on it. Loading never executes
code from the file: skops rebuilds only the types on an allow-list, and a file asking for
anything else is refused. A model that passed is kept in the user's model cache
(`model_cache`) and loads from there, three times as fast, while the file's bytes stay
the same.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import QuakeScanError
from ..grades import GRADE_SHORT_NAMES

FORMAT = "quakescan-model"
VERSION = 1
# Version 2: a model trained on every row (`no_change_rule` False). A QuakeScan that reads
# only version 1 would decide the unchanged buildings by rule without asking the model,
# i.e. misread the file; the version makes it refuse it instead. Everything else is
# written as version 1, so that a reader of version 1 alone reads it right.
VERSION_ALL_ROWS = 2
SUPPORTED_VERSIONS = (VERSION, VERSION_ALL_ROWS)
GRADE_LABELS = GRADE_SHORT_NAMES  # buildings.csv `label`: the paper's short names (quakescan.grades)
# Everything the classifier kinds need beyond skops' built-in safe types, as
# `skops.io.get_untrusted_types` reports them for saved files of each kind
# (tests/test_model.py checks that this list is exactly their union).
TRUSTED_TYPES = [
    "sklearn.tree._tree.Tree",  # the random forest's trees
    "sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor",  # gradient boosting's trees
    "sklearn.calibration._CalibratedClassifier",  # one fold of a calibrated classifier (any method)
    "sklearn.calibration._SigmoidCalibration",  # the sigmoid (Platt) calibration map
]
CLASSIFIER_KINDS = ("rf", "hgb")
CALIBRATIONS = (None, "sigmoid", "isotonic")
CALIBRATION_FOLDS = 3
FOREST_TREES = 100
# Gradient boosting where a caller does not say otherwise. 200 rounds at learning rate 0.1
# of small trees (15 leaves, depth at most `max_depth`) fit a few hundred buildings with a
# few dozen descriptors without chasing single rows; leaves of at least 10 rows (sklearn: 20)
# because the rarest grade of a training set may have only tens of rows; a little L2 on the
# leaf values. Early stopping off: it holds back a random validation share and stops at a
# data-dependent round (and sklearn switches it on by itself above 10 000 rows), so the
# model would depend on more than the rows and the seed.
HGB_DEFAULTS = {"max_iter": 200, "learning_rate": 0.1, "max_leaf_nodes": 15, "min_samples_leaf": 10,
                "l2_regularization": 0.1, "early_stopping": False}


class ModelError(QuakeScanError):
    """A model file is missing, tampered with, or does not fit the data."""


@dataclass
class DamageModel:
    estimator: object  # fitted sklearn classifier (`fit_classifier`): forest, boosting, calibrated
    feature_names: list
    radius_m: float
    split: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    # True: a building without changed points is "no damage" without asking the estimator
    # (the paper's rule; the estimator was fitted on changed buildings only). False: the
    # estimator was fitted on every row and is asked about every assessable building.
    no_change_rule: bool = True
    # Probabilities p^(1/T), renormalised: the temperature fitted on real-point rows
    # (`quakescan.learning.real_calibration`); 1: the estimator's own. Grades do not depend on it.
    temperature: float = 1.0

    @property
    def classes(self) -> list:
        """Grades the estimator can answer."""
        return [int(c) for c in self.estimator.classes_]

    @property
    def grades(self) -> list:
        """Grades a classification can give: the estimator's, and "no damage" when the rule
        gives it to a building without changed points even if the estimator never saw one."""
        return sorted(set(self.classes) | ({0} if self.no_change_rule else set()))

    @property
    def classifier(self) -> dict:
        """{"kind": "rf"|"hgb", "calibration": None|"sigmoid"|"isotonic", "params": {...}},
        read from the estimator itself (`describe_classifier`)."""
        return describe_classifier(self.estimator)

    def predict_proba(self, table: dict) -> np.ndarray:
        """(n, n_classes) probabilities from a table {feature name: (n,) values}."""
        missing = [f for f in self.feature_names if f not in table]
        if missing:
            raise ModelError(f"the model needs features {missing} that the data lacks "
                             f"(model features: {self.feature_names})")
        return self.predict_proba_matrix(np.column_stack([np.asarray(table[f], dtype=np.float64)
                                                          for f in self.feature_names]))

    def predict_proba_matrix(self, x: np.ndarray) -> np.ndarray:
        """(n, n_classes) probabilities from an (n, len(feature_names)) matrix in `feature_names`'
        order (`quakescan.change.pipeline.descriptor_matrix` of the rows)."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != len(self.feature_names):
            raise ModelError(f"the model reads {len(self.feature_names)} features a row, got a matrix of shape {x.shape}")
        proba = self.estimator.predict_proba(x)
        if self.temperature != 1.0:
            from .reliability import temper

            proba = temper(proba, self.temperature)
        return proba

    def predict(self, table: dict) -> np.ndarray:
        p = self.predict_proba(table)
        return np.asarray(self.classes)[p.argmax(axis=1)]

    @staticmethod
    def confidence(proba) -> np.ndarray:
        """(n,) the probability of each row's predicted class (the row's maximum): how much
        of the model's belief the answer carries; 1/n_classes at worst, 1 when certain."""
        return _probability_rows(proba).max(axis=1)

    @staticmethod
    def margin(proba) -> np.ndarray:
        """(n,) top-1 minus top-2 probability of each row: how far the answer is from its
        runner-up (0 = a tie, 1 = certain); with a single class every row is 1. A small
        margin flags a building worth a second look even when `confidence` looks high
        among many classes."""
        p = _probability_rows(proba)
        if p.shape[1] < 2:
            return np.ones(len(p))
        top = np.sort(p, axis=1)
        return top[:, -1] - top[:, -2]


def _probability_rows(proba) -> np.ndarray:
    p = np.asarray(proba, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] == 0:
        raise ModelError(f"probabilities must be an (n, n_classes) array, got shape {p.shape}")
    return p


SHARE_CHANGED = "share_changed"
# What "nothing changed" is read from, the first a row has: the paper's share of changed
# points, else a surface model's share of changed surface (core points)
CHANGED_SHARE_COLUMNS = (SHARE_CHANGED, "m_changed")


def changed_share_column(names) -> str | None:
    """The column of `names` the no-change rule reads (`CHANGED_SHARE_COLUMNS`), or None."""
    return next((c for c in CHANGED_SHARE_COLUMNS if c in list(names)), None)


def changed_share(descriptors) -> float:
    """A building's changed share by the same column (0 when its row has none)."""
    column = changed_share_column(descriptors)
    return float(descriptors[column]) if column else 0.0


def decided_by_rule(x: np.ndarray, names) -> np.ndarray:
    """Rows a classification decides without the forest: no changed point, so no damage
    (Zahs et al.: "buildings with no changed points would directly be considered as
    undamaged"). The one rule of training (`train_damage_forest`) and classifying
    (`quakescan.learning.prediction.predict_rows`, through `changed_share`)."""
    names = list(names)
    column = changed_share_column(names)
    if column is None:
        return np.zeros(len(x), bool)
    return np.asarray(x)[:, names.index(column)] == 0


def train_forest(x: np.ndarray, y: np.ndarray, n_estimators: int = 100, max_depth: int | None = 5,
                 seed: int = 0, n_jobs: int | None = None, class_weight: str | None = "balanced"):
    """The paper's classifier: a random forest (100 trees, depth 5 by default), seeded.

    Classes weighted inversely to their frequency by default: the grade the field needs
    most, an undamaged building that nevertheless shows changed points (a neighbour's
    debris, DIM noise), is the rarest row of a simulated training set."""
    return fit_classifier(x, y, "rf", n_estimators=n_estimators, max_depth=max_depth, seed=seed,
                          n_jobs=n_jobs, class_weight=class_weight)


def fit_classifier(x: np.ndarray, y: np.ndarray, kind: str = "rf", *, calibration: str | None = None,
                   class_weight: str | None = "balanced", seed: int = 0, n_estimators: int | None = None,
                   max_depth: int | None = 5, n_jobs: int | None = None, cv=None, groups=None, **kw):
    """A fitted scikit-learn classifier of a kind a model file may hold, seeded: the same
    rows and seed give the same predictions.

    kind
        "rf": the paper's random forest (`RandomForestClassifier`), `n_estimators` trees
        (default 100) of depth at most `max_depth`. "hgb": histogram gradient boosting
        (`HistGradientBoostingClassifier`) with `HGB_DEFAULTS`; `n_estimators` is its number
        of boosting rounds (`max_iter`, default 200) and `max_depth` limits every tree as in
        the forest.
    calibration
        None, or "sigmoid" / "isotonic": the classifier is wrapped in `CalibratedClassifierCV`,
        which fits it on `cv` folds and maps each fold's probabilities on the rows it left
        out, so that a building given p = 0.8 is right about 80 % of the time; predictions
        average the folds.
    cv, groups
        The calibration's folds: a number (default 3), a splitter with `split(x, y, groups)`
        or a list of (train, test) row indices. With `groups` (e.g. one code per building)
        a number means `StratifiedGroupKFold`, so no building is on both sides. Splitters
        are turned into their index lists, so a model file holds arrays, not splitter types.
        Both are ignored without calibration.
    class_weight
        "balanced" (classes weighted inversely to their frequency, see `train_forest`) or None.
    n_jobs
        Cores for fitting: the forest's joblib workers, and the native thread pools (OpenMP
        of boosting, BLAS of the sigmoid fit) through `native_threads`; the result does not
        depend on it. None: the libraries' defaults (every core).
    kw
        Further arguments of the estimator (e.g. min_samples_leaf); for "hgb" they override
        `HGB_DEFAULTS`.
    """
    base = _classifier(kind, class_weight=class_weight, seed=seed, n_estimators=n_estimators,
                       max_depth=max_depth, n_jobs=n_jobs, **kw)
    if calibration not in CALIBRATIONS:
        raise ModelError(f"calibration {calibration!r} is not one of {list(CALIBRATIONS)}")
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y)
    if calibration is None:
        est = base
    else:
        from sklearn.calibration import CalibratedClassifierCV

        est = CalibratedClassifierCV(base, method=calibration, cv=calibration_folds(x, y, cv, groups))
    try:
        with native_threads(n_jobs):
            return est.fit(x, y)
    except ValueError as e:  # e.g. a calibration fold without a class: name what was asked
        grades = dict(zip(*(v.tolist() for v in np.unique(y, return_counts=True))))
        raise ModelError(f"cannot fit a {kind} classifier (calibration {calibration}) on {len(y)} rows with "
                         f"grades {grades}: {e}") from None


def _classifier(kind: str, *, class_weight, seed, n_estimators, max_depth, n_jobs, **kw):
    """An unfitted estimator of `kind` (see `fit_classifier`)."""
    try:
        if kind == "rf":
            from sklearn.ensemble import RandomForestClassifier

            return RandomForestClassifier(n_estimators=FOREST_TREES if n_estimators is None else n_estimators,
                                          max_depth=max_depth, random_state=seed, n_jobs=n_jobs,
                                          class_weight=class_weight, **kw)
        if kind == "hgb":
            from sklearn.ensemble import HistGradientBoostingClassifier

            if n_estimators is not None and "max_iter" in kw:
                raise ModelError(f"n_estimators={n_estimators} and max_iter={kw['max_iter']} both give the "
                                 "boosting rounds of an hgb classifier; pass one")
            params = dict(HGB_DEFAULTS, max_depth=max_depth, **kw)
            if n_estimators is not None:
                params["max_iter"] = n_estimators
            return HistGradientBoostingClassifier(random_state=seed, class_weight=class_weight, **params)
    except TypeError as e:  # an argument the estimator does not take
        raise ModelError(f"classifier kind {kind!r}: {e}") from None
    raise ModelError(f"classifier kind {kind!r} is not one of {list(CLASSIFIER_KINDS)}")


def native_threads(n_jobs: int | None):
    """A context limiting OpenMP and BLAS threads to n_jobs (None or < 1: no limit).

    Measured on a 2-core machine shared with other jobs: a boosting or sigmoid-calibration
    fit of a few hundred rows took 10-20x longer with every core's threads than with one,
    the threads waiting for cores longer than the work takes."""
    import contextlib

    if n_jobs is None or n_jobs < 1:
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(n_jobs))


def calibration_folds(x: np.ndarray, y: np.ndarray, cv=None, groups=None):
    """The folds a calibration fits on (see `fit_classifier`): a number of stratified folds
    (sklearn's `StratifiedKFold`, not shuffled, so deterministic), or a list of (train, test)
    row indices; grouped folds (`StratifiedGroupKFold`, not shuffled) when `groups` is given."""
    from sklearn.model_selection import StratifiedGroupKFold

    cv = CALIBRATION_FOLDS if cv is None else cv
    if isinstance(cv, (int, np.integer)):
        if groups is None:
            return int(cv)
        cv = StratifiedGroupKFold(n_splits=int(cv))
    if groups is not None and len(groups) != len(y):
        raise ModelError(f"{len(groups)} groups for {len(y)} rows: give one group per row")
    splits = cv.split(x, y, groups) if hasattr(cv, "split") else cv
    return [(np.asarray(tr, dtype=np.int64), np.asarray(te, dtype=np.int64)) for tr, te in splits]


def describe_classifier(estimator) -> dict:
    """{"kind", "calibration", "params"} of an estimator: "rf" or "hgb" (the class name for
    any other), the calibration method or None, and the (base) estimator's parameters that
    are plain values, plus `calibration_cv` (folds: a number, or "n given splits").
    Read from the estimator, so the record cannot disagree with what predicts."""
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.ensemble import HistGradientBoostingClassifier, RandomForestClassifier

    base, calibration = estimator, None
    if isinstance(estimator, CalibratedClassifierCV):
        base, calibration = estimator.estimator, estimator.method
    kind = ("rf" if isinstance(base, RandomForestClassifier) else
            "hgb" if isinstance(base, HistGradientBoostingClassifier) else type(base).__name__)
    given = base.get_params(deep=False) if hasattr(base, "get_params") else {}
    params = {k: _plain(v) for k, v in given.items() if _plain(v) is not _NOT_PLAIN}
    if calibration is not None:
        folds = estimator.cv
        params["calibration_cv"] = (5 if folds is None else int(folds) if isinstance(folds, (int, np.integer))
                                    else f"{len(folds)} given splits" if isinstance(folds, (list, tuple))
                                    else type(folds).__name__)
    return {"kind": kind, "calibration": calibration, "params": params}


_NOT_PLAIN = object()


def _plain(v):
    """v as a value a metadata dict can hold (None, bool, int, float, str, or a dict of them)."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, dict) and all(_plain(x) is not _NOT_PLAIN for x in v.values()):
        return {str(k): _plain(x) for k, x in v.items()}
    return _NOT_PLAIN


def train_damage_forest(x: np.ndarray, y: np.ndarray, names, *, rule: bool = True, **kw):
    """A classifier fitted on the rows it will be asked about (`fit_classifier` arguments in
    `kw`; by default the paper's random forest).

    rule=True: only buildings with changed points. Rows without changed points are decided
    by rule (`decided_by_rule`) when classifying; fitting on them too would spend the forest
    on all-zero rows and, with them labelled "no damage" by the hundred, leave the few
    undamaged buildings *with* changes outvoted. rule=False: every row, for a model that is
    asked about every building (save it with `DamageModel(no_change_rule=False)`).
    `groups` in `kw` (calibration folds) are kept row for row."""
    x, y = np.asarray(x), np.asarray(y)
    if not rule:
        return fit_classifier(x, y, **kw)
    ask = ~decided_by_rule(x, names)
    if not ask.any():
        raise ModelError(f"none of the {len(ask)} training buildings has changed points: nothing for the "
                         "forest to learn (every building would be 'no damage' by rule anyway)")
    if kw.get("groups") is not None:
        kw["groups"] = np.asarray(kw["groups"])[ask]
    cv = kw.get("cv")
    if cv is not None and not isinstance(cv, (int, np.integer)) and not hasattr(cv, "split") and not ask.all():
        raise ModelError("calibration splits given as row indices cannot follow the rule's removal of "
                         f"{int((~ask).sum())} unchanged rows; pass groups (or a splitter) instead")
    return fit_classifier(x[ask], y[ask], **kw)


def predict_grades(estimator, x: np.ndarray, names, rule: bool = True) -> np.ndarray:
    """Grades of descriptor rows: by rule where nothing changed and by the estimator
    elsewhere, or (rule=False) by the estimator everywhere."""
    x = np.asarray(x)
    if not rule:
        return np.asarray(estimator.predict(x), dtype=np.int64) if len(x) else np.zeros(0, np.int64)
    out = np.zeros(len(x), np.int64)
    ask = ~decided_by_rule(x, names)
    if ask.any():
        out[ask] = estimator.predict(x[ask])
    return out


def grouped_split(groups: np.ndarray, test_size: float = 0.3, seed: int = 0):
    """Train/test row indices with all rows of a group (a building) on one side."""
    from sklearn.model_selection import GroupShuffleSplit

    gss = GroupShuffleSplit(n_splits=1, test_size=test_size, random_state=seed)
    return next(gss.split(np.zeros(len(groups)), groups=groups))


def file_version(model: DamageModel) -> int:
    """The format version a model is written with: `VERSION` (1), which every QuakeScan reads
    as meant, unless older readers would misread it (see `VERSION_ALL_ROWS`)."""
    return VERSION if model.no_change_rule else VERSION_ALL_ROWS


def save_model(model: DamageModel, path: str | os.PathLike) -> None:
    """Write the model (estimator + metadata) to a skops file, atomically.

    Metadata beyond the first files' (all optional on reading): `classifier` ({"kind",
    "calibration", "params"}, `describe_classifier`), `no_change_rule` (bool) and
    `temperature` (written only when not 1; a reader without it gives the same grades with the
    estimator's own probabilities)."""
    import zipfile

    import sklearn
    import skops.io as sio

    meta = {
        "format": FORMAT, "version": file_version(model), "quakescan": __version__,
        "sklearn": sklearn.__version__,
        "feature_names": list(model.feature_names), "radius_m": float(model.radius_m),
        "split": dict(model.split), "provenance": dict(model.provenance),
        "created": model.provenance.get("created") or datetime.date.today().isoformat(),
        "classifier": model.classifier, "no_change_rule": bool(model.no_change_rule),
    }
    if model.temperature != 1.0:
        from .reliability import check_temperature

        meta["temperature"] = check_temperature(model.temperature)
    from ..runtime.atomic import replacing  # a failed write leaves nothing, names the file

    with replacing(path) as tmp:
        # Deflated: a forest's node arrays shrink five-fold (the shipped model 31 → 5.6 MB)
        # and load as fast (0.56 s either way, measured); skops reads either kind.
        sio.dump({"meta": meta, "estimator": model.estimator}, tmp,
                 compression=zipfile.ZIP_DEFLATED, compresslevel=6)


def load_model(path: str | os.PathLike) -> DamageModel:
    """A DamageModel from a file `save_model` wrote (any version in SUPPORTED_VERSIONS).

    A file without `classifier` is a random forest without calibration and one without
    `no_change_rule` decides unchanged buildings by rule: the files written before either
    key existed. A file loaded before with the same bytes comes from the user's model cache
    (`quakescan.learning.model_cache`), without skops."""
    path = Path(path)
    if path.is_dir():
        raise ModelError(f"{path}: is a folder, not a model file")
    if not path.is_file():
        raise ModelError(f"{path}: model file does not exist")
    _check_archive_size(path)
    # Read once: the bytes checked and built below are the bytes the cache is keyed by.
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ModelError(f"{path}: cannot read the model file ({e.strerror or e})") from None
    from . import model_cache

    name = model_cache.entry_name(data)
    model = model_cache.recall(name, DamageModel)
    if model is None:
        model = _build_model(path, data)
        model_cache.remember(name, model)
    return model


def _build_model(path: Path, data: bytes) -> DamageModel:
    """The DamageModel in a model file's bytes, every check of `load_model` passed."""
    import io

    import skops.io as sio
    from skops.io.exceptions import UntrustedTypesFoundException

    # skops audits the whole tree against `trusted` before it builds any object, so one walk
    # both checks and loads: asking get_untrusted_types first walked the tree twice (0.44 s of
    # the shipped model's 1.35 s). It is asked only to name the types of a refused file.
    try:
        obj = sio.load(io.BytesIO(data), trusted=TRUSTED_TYPES)
    except UntrustedTypesFoundException:  # the schema parsed: naming its types reads it again
        unexpected = sorted(set(sio.get_untrusted_types(file=path)) - set(TRUSTED_TYPES))
        raise ModelError(f"{path}: refused: the file asks to build types {unexpected} that a damage model "
                         "never contains (tampered or foreign file); nothing was executed") from None
    except Exception as e:
        raise ModelError(f"{path}: {_load_failure(path, e)}") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("meta"), dict):
        raise ModelError(f"{path}: not a QuakeScan model file (no metadata)")
    meta = obj["meta"]
    if meta.get("format") != FORMAT:
        raise ModelError(f"{path}: format {meta.get('format')!r} is not {FORMAT!r}")
    if meta.get("version") not in SUPPORTED_VERSIONS:
        raise ModelError(f"{path}: model format version {meta.get('version')!r} is not supported "
                         f"(this QuakeScan reads versions {list(SUPPORTED_VERSIONS)}); retrain with "
                         "`quakescan train`")
    est = obj.get("estimator")
    names = meta.get("feature_names")
    if est is None or not hasattr(est, "predict_proba") or not isinstance(names, list):
        raise ModelError(f"{path}: incomplete model (estimator or feature names missing)")
    if getattr(est, "n_features_in_", len(names)) != len(names):
        raise ModelError(f"{path}: the classifier expects {est.n_features_in_} features but the file names "
                         f"{len(names)}")
    rule = meta.get("no_change_rule", True)
    if not isinstance(rule, bool):
        raise ModelError(f"{path}: no_change_rule must be true or false, got {rule!r}")
    _check_classifier_record(path, meta.get("classifier"), est)
    _check_settings(path, meta)
    from .reliability import check_temperature

    try:
        temperature = check_temperature(meta.get("temperature", 1.0))
    except ValueError as e:
        raise ModelError(f"{path}: {e} (edited or foreign file)") from None
    if not isinstance(meta.get("provenance", {}), dict) or not all(isinstance(n, str) for n in names):
        raise ModelError(f"{path}: provenance must be a dict and feature names texts (edited or foreign file)")
    classes = getattr(est, "classes_", None)
    try:
        grades = [int(c) for c in classes] if classes is not None else []
    except (TypeError, ValueError):
        grades = None
    if not grades or not set(grades) <= set(GRADE_LABELS) or len(set(grades)) != len(grades):
        raise ModelError(f"{path}: the classifier's classes {classes!r} are not EMS-98 grades 0–5 (edited or "
                         "foreign file)")
    return DamageModel(est, names, float(meta["radius_m"]), meta.get("split", {}),
                       dict(meta.get("provenance", {}), versions={"quakescan": meta.get("quakescan"),
                                                                   "sklearn": meta.get("sklearn")}),
                       no_change_rule=rule, temperature=temperature)


# A model file is a zip archive; skops inflates every member it reads. The shipped model
# holds 76 MB; a file that would inflate beyond this is refused before anything is read
# (a 2 MB file can declare gigabytes: 7.5 GB of memory before any other check).
MAX_MODEL_UNCOMPRESSED_BYTES = 1 << 30
MAX_MODEL_MEMBERS = 200_000


def _load_failure(path: Path, error: Exception) -> str:
    """Why skops could not load `path`: not a model file at all (no skops schema) or a model
    file it cannot build."""
    import skops.io as sio

    try:
        sio.get_untrusted_types(file=path)
    except Exception as e:
        return f"not a QuakeScan model file ({e})"
    return f"cannot load the model ({error})"


def _check_archive_size(path: Path) -> None:
    """Refuse a model archive whose members would inflate beyond MAX_MODEL_UNCOMPRESSED_BYTES,
    from the sizes its directory declares (zipfile never reads past a declared size)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise ModelError(f"{path}: not a QuakeScan model file (not a skops archive: {e})") from None
    total = sum(i.file_size for i in infos)
    size = path.stat().st_size
    if size > MAX_MODEL_UNCOMPRESSED_BYTES:  # it is read whole: the bytes checked are the bytes built
        raise ModelError(f"{path}: refused: the file holds {size / 2 ** 20:,.0f} MiB (a damage "
                         f"model holds at most {MAX_MODEL_UNCOMPRESSED_BYTES / 2 ** 20:,.0f} MiB); nothing was "
                         "loaded")
    if total > MAX_MODEL_UNCOMPRESSED_BYTES or len(infos) > MAX_MODEL_MEMBERS:
        raise ModelError(f"{path}: refused: the archive would inflate to {total / 2 ** 20:,.0f} MiB in "
                         f"{len(infos):,} members (a damage model holds at most "
                         f"{MAX_MODEL_UNCOMPRESSED_BYTES / 2 ** 20:,.0f} MiB); nothing was loaded")


def _check_settings(path, meta: dict) -> None:
    """Refuse settings no QuakeScan writes: a radius or levels of detection out of range (an
    edited file would classify every building at settings it was never trained on)."""
    from ..change.settings import radius_problem
    from ..change.split import SplitSettings

    problem = radius_problem(meta.get("radius_m"))
    if problem:
        raise ModelError(f"{path}: radius_m {problem} (edited or foreign file)")
    r = meta["radius_m"]
    stored = meta.get("split", {})
    if not isinstance(stored, dict):
        raise ModelError(f"{path}: split settings must be a dict, got {stored!r}")
    if "radius_m" in stored and stored["radius_m"] != r:
        raise ModelError(f"{path}: radius_m {r!r} differs from the pipeline settings' {stored['radius_m']!r} "
                         "(edited file)")
    split = stored.get("split")
    if split is not None:
        try:
            SplitSettings(**split)
        except (TypeError, QuakeScanError) as e:
            raise ModelError(f"{path}: invalid split settings ({e}; edited or foreign file)") from None


def _check_classifier_record(path, record, estimator) -> None:
    """Refuse a file whose `classifier` metadata names another kind or calibration than the
    estimator it holds (absent: the first files' random forest without calibration)."""
    if record is None:
        record = {"kind": "rf", "calibration": None}
    if not isinstance(record, dict):
        raise ModelError(f"{path}: classifier metadata must be a dict, got {record!r}")
    held = describe_classifier(estimator)
    if held["kind"] not in CLASSIFIER_KINDS or held["calibration"] not in CALIBRATIONS:
        raise ModelError(f"{path}: the file holds a {held['kind']} classifier (calibration {held['calibration']}), "
                         f"not one QuakeScan trains ({', '.join(CLASSIFIER_KINDS)}): refused")
    said = (record.get("kind"), record.get("calibration"))
    if said != (held["kind"], held["calibration"]):
        raise ModelError(f"{path}: the metadata says kind {said[0]!r}, calibration {said[1]!r} but the file "
                         f"holds kind {held['kind']!r}, calibration {held['calibration']!r} (tampered or "
                         "inconsistent file)")
