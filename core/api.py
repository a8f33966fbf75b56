"""The public Python API: what a notebook needs, in one place (`import quakescan as qs`).

A damaged city's two scene bundles are acquired with a sensor into pre- and post-event
point clouds, the change between them is described per building, a classifier is trained
on described pairs with known grades, and a model grades the buildings of any pair,
simulated or real::

    import quakescan as qs

    qs.acquire("city/pre", "pre.las", kind="uls", seed=1)
    qs.acquire("city/post", "post.las", kind="dim", seed=2)
    summary = qs.classify("pre.las", "post.las", "result")          # the shipped model
    report = qs.evaluate("result/buildings.csv", "city/post")       # against the scene's grades

Coordinates are metres in the clouds' CRS; epochs are held in a local frame (`Epoch.origin`
+ `Epoch.xyz`), so that UTM coordinates keep millimetres in float64. Every function here
is a thin front to the module that owns the work (named in its docstring), with the
defaults the command line uses; the modules stay available for finer control.
"""
from __future__ import annotations

import os
from collections.abc import Sequence

from .acquisition import acquire as _acquisition
from .acquisition.acquire import Acquired, Acquisition
from .change.pipeline import BuildingRow, describe_pair
from .change.settings import training_settings
from .errors import QuakeScanError
from .formats.pointcloud import Epoch, read_epoch
from .formats.scene import Scene, read_scene, write_scene
from .formats.pair import PairData, load_pair
from .learning.default_model import default_model_path
from .learning.prediction import model_settings
from .learning.model import DamageModel, load_model as _load_model, save_model
from .results.evaluation import Evaluation, evaluate_files

__all__ = ["acquire", "read_scene", "write_scene", "read_epoch", "read_pair", "describe", "train",
           "load_model", "save_model", "classify", "evaluate", "inject", "sensor_kinds",
           "Acquired", "BuildingRow", "DamageModel", "Epoch", "Evaluation", "PairData", "Scene"]

PathLike = str | os.PathLike


def sensor_kinds() -> tuple[str, ...]:
    """Names of the registered sensors (`quakescan.acquisition.sensors`): 'uls', 'als', 'dim', and any
    a user module registered."""
    from .acquisition import sensors

    return tuple(sensors.kinds())


def acquire(scene: PathLike | Scene, out: PathLike, kind: str = "uls", settings=None, *, seed: int = 0,
            workers: int = -1) -> Acquired:
    """Acquire a scene with a simulated sensor into a LAS/LAZ epoch (`quakescan.acquisition.acquire`).

    Parameters
    ----------
    scene : path or Scene
        A scene bundle folder (scene.json + mesh.ply) or a `Scene` in memory.
    out : path
        The point cloud to write (.las or .laz), LAS 1.4 point format 6 at 1 mm, with the
        extra dimensions building_id, grade and surface.
    kind : str
        The sensor: 'uls' (UAV laser scanning), 'als' (airborne, from an aircraft), 'dim'
        (dense image matching of a UAV photo flight), or a registered one (`sensor_kinds`).
    settings : None, str, path or the sensor's settings object
        None: the sensor's default preset (the paper's survey); a preset name ('paper',
        'als'), a settings file written by `quakescan survey-template` /
        `dim-survey-template`, or a settings object (`quakescan.acquisition.survey.Survey`,
        `quakescan.acquisition.dim_settings.PhotoSurvey`).
    seed : int
        Seeds the sensor's noise: the same scene, settings and seed give the same bytes.
    workers : int
        Worker threads (-1: every core). The bytes do not depend on it.

    Returns
    -------
    Acquired
        `path`, the sidecar's `record`, `resumed` (True when an up-to-date cloud of the
        same acquisition was already there and nothing was simulated) and the sensor's
        `summary` of a cloud simulated now.
    """
    from .acquisition import sensors

    sensor = sensors.get(kind)
    if settings is None:
        settings = sensor.default()
    elif isinstance(settings, (str, os.PathLike)):
        settings = sensor.load_settings(settings)
    return _acquisition.acquire(scene, Acquisition(kind, settings), out, seed=seed, workers=workers)


def read_pair(pre: PathLike, post: PathLike, footprints: PathLike | None = None,
              id_field: str | None = None) -> PairData:
    """Both epochs in the pre-event epoch's local frame, with building IDs
    (`quakescan.formats.pair.load_pair`).

    Parameters
    ----------
    pre, post : path
        LAS/LAZ point clouds of the same area before and after the event.
    footprints : path, optional
        Building footprints (GeoJSON polygons in the clouds' CRS) that give every point its
        building; without them both clouds must carry a `building_id` dimension.
    id_field : str, optional
        The footprints' property holding the building ID (default: the feature id).
    """
    return load_pair(pre, post, footprints, id_field)


def describe(pre: PathLike | PairData, post: PathLike | None = None, *, footprints: PathLike | None = None,
             model: PathLike | DamageModel | None = None, workers: int = -1) -> list[BuildingRow]:
    """Change descriptors of every building of a pair, as `model` reads them
    (`quakescan.change.pipeline.describe_pair`).

    Parameters
    ----------
    pre, post : path, or a PairData from `read_pair` as `pre` alone
    footprints : path, optional
        As in `read_pair`.
    model : path or DamageModel, optional
        Whose descriptors and settings to compute (default: the shipped model).
    workers : int
        Worker threads (-1: every core).

    Returns
    -------
    list of BuildingRow
        One per building: `building_id`, point counts, `assessable` and its `reason`,
        `descriptors` ({name: value}; shares are dimensionless, lengths in metres) and
        `quality` (planimetric densities in pts/m², post-event coverage, footprint cells and
        area in m², lowering resolution in m: what `quakescan.change.detectability` reads).
    """
    pair = pre if isinstance(pre, PairData) else read_pair(pre, _required(post, "post"), footprints)
    settings = model_settings(load_model(model) if not isinstance(model, DamageModel) else model)
    return describe_pair(pair.pre, pair.post, settings, workers=workers)


def train(pairs: Sequence[tuple], *, descriptors: str = "surface", test_size: float = 0.3, seed: int = 0,
          classifier: dict | None = None, workers: int = -1):
    """Train a damage model on described pairs with known grades (`quakescan.learning.training.train`).

    Parameters
    ----------
    pairs : sequence of (pre, post) or (pre, post, truth) or (pre, post, truth, footprints)
        Paths of LAS/LAZ epochs; `truth` a CSV of building_id,grade (None: the post-event
        cloud's `grade` dimension, as simulated clouds carry); `footprints` as in `read_pair`.
    descriptors : {'surface', 'paper', 'both'}
        The shipped model's density-free surface descriptors, the paper's point-feature
        descriptors and changed share, or both.
    test_size : float
        Share of the buildings held out for the returned evaluation (0: fit on all).
    seed : int
    classifier : dict, optional
        `quakescan.learning.model.fit_classifier` arguments, e.g. {"kind": "hgb"} or
        {"kind": "rf", "n_estimators": 300, "max_depth": None, "calibration": "sigmoid"}.
    workers : int
        Worker threads (-1: every core).

    Returns
    -------
    (DamageModel, Evaluation or None, TrainingTable)
        The model (save it with `save_model`), its evaluation on the held-out buildings and
        the described rows (`x`: (n, k) descriptors named `names`, `y`: grades).
    """
    from .learning.training import TrainingPair
    from .learning.training import train as run

    items = []
    for i, p in enumerate(pairs):
        if not 2 <= len(p) <= 4:
            raise QuakeScanError(f"train: pair {i} must be (pre, post[, truth[, footprints]]), got {p!r}")
        items.append(TrainingPair(*[None if v is None else os.fspath(v) for v in p]))
    settings = training_settings(descriptors)
    kw = {"classifier": classifier} if classifier else {}
    return run(items, settings, test_size=test_size, seed=seed, workers=workers,
               rule=settings.paper_descriptors, **kw)


def load_model(path: PathLike | None = None) -> DamageModel:
    """A model file (`quakescan.learning.model.load_model`; default: the model QuakeScan ships). Files
    are checked before anything in them runs; a file of another QuakeScan says what differs."""
    return _load_model(default_model_path() if path is None else path)


def classify(pre: PathLike, post: PathLike, out_dir: PathLike, *, footprints: PathLike | None = None,
             model: PathLike | None = None, workers: int = -1, **options) -> dict:
    """Grade every building of a pair and write the results (`quakescan.assessment.run.classify`).

    Parameters
    ----------
    pre, post : path
        LAS/LAZ epochs; real ones need `footprints`.
    out_dir : path
        Receives buildings.csv (grade, label, per-grade probabilities, confidence, reason when
        not assessable, what each building's data could resolve), buildings.geojson (+ QGIS style), damage maps, the graded post-event
        cloud and summary.json. Resumable: finished tiles are not redone.
    footprints : path, optional
    model : path, optional
        Default: the shipped model.
    workers : int
        Worker threads (-1: every core).
    **options
        `align` (None: check registration, align when needed), `write_las`, `laz`, `force`,
        `id_field`, `progress` (a `quakescan.runtime.progress.ProgressCallback`: called with (done, total)).

    Returns
    -------
    dict
        The run's summary (also in summary.json): counts per grade, timings, alignment.
    """
    from .assessment.run import classify as run

    return run(pre, post, out_dir, model_path=model, footprints_path=footprints, workers=workers, **options)


def evaluate(result_csv: PathLike, truth: PathLike) -> Evaluation:
    """Compare graded buildings with known grades (`quakescan.results.evaluation.evaluate_files`).

    Parameters
    ----------
    result_csv : path
        A buildings.csv written by `classify`.
    truth : path
        A CSV of building_id,grade or a post-event scene bundle folder (its scene.json grades).

    Returns
    -------
    Evaluation
        `overall_accuracy`, `per_grade` ({grade: {precision, recall, f1}}), `damaged`
        (damaged vs undamaged metrics), `confusion`, `n`, `not_assessable`.
    """
    return evaluate_files(result_csv, truth)


def inject(cloud: PathLike, footprints: PathLike, out_dir: PathLike, *, grades: dict | None = None,
           grade_mix: dict | None = None, seed: int = 0, **settings):
    """EMS-98 damage injected into a real point cloud (`quakescan.injection.inject.inject`).

    Parameters
    ----------
    cloud, footprints : path
        A real LAS/LAZ cloud and its building footprints (GeoJSON, the cloud's coordinates).
    out_dir : path
        Output folder: post.las (post.laz for a compressed input), truth.csv, inject.json, scenes/.
    grades : dict, optional
        {building ID: grade 0-5}; the others stay at 0. Or:
    grade_mix : dict, optional
        {grade 3/4/5: count} drawn by `seed` among the buildings with `min_points` points
        (default {3: 5, 4: 5, 5: 5} when neither is given).
    seed : int
        Which buildings and which patterns; the same seed gives the same bytes.
    settings
        Further `InjectSettings` fields: `min_points`, `damage` ("patterns", "physics",
        "both"), `kind` ("auto", "lidar", "dim"), `range_noise_m`, `id_field`.

    Returns
    -------
    InjectResult
        `post`, `truth`, `record` paths, `grades` per footprint, `counts` of kept, moved
        and removed returns, `reused` when an earlier run with the same inputs was kept.
    """
    from .injection.inject import InjectSettings, inject as _inject

    if grades is None and grade_mix is None:
        grade_mix = {3: 5, 4: 5, 5: 5}
    return _inject(cloud, footprints, out_dir, InjectSettings(seed=seed, grades=grades, grade_mix=grade_mix,
                                                              **settings))


def _required(value, name):
    if value is None:
        raise QuakeScanError(f"describe: give the {name}-event cloud (or a PairData from read_pair as pre)")
    return value
