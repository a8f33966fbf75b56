"""Damage grades for the buildings of a real or simulated pre-/post-event pair (`quakescan classify`).

Reads both epochs into one float64 local frame, takes building IDs from the clouds'
`building_id` dimension or from footprints, optionally aligns the post epoch to the pre
epoch by ICP on stable areas, describes every building's change (`quakescan.change.pipeline`, tile by
tile) and applies a model: the shipped default unless one is given. A building with too
few points is reported as not assessable, never guessed; a building without changed
points is "no damage" by the paper's rule, without asking the model, unless the model was
trained on every row (`DamageModel.no_change_rule` False) and is asked about all of them.

Long runs checkpoint every finished tile to OUT/.checkpoint.jsonl; a rerun with the same
inputs, model and options (`quakescan.runtime.fingerprint`'s rule) continues from there. Every output is
written under a temporary name and renamed. The output folder follows the rule of
`quakescan.runtime.output_folder` (`claimed_output_folder`): one run in it at a time, no
input replaced by a result, and the results of a previous run that this one does not write
removed by the record of its summary.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..change.detectability import of_building
from ..change.pipeline import (
    BuildingRow,
    PipelineSettings,
    describe_pair,
    settings_for_descriptors,
)
from ..errors import QuakeScanError, ResultsError, check_input_file
from ..formats.pointcloud import (
    Epoch,
    PointCloudError,
    check_pair,
    check_point_cloud_path,
    epoch_order_warning,
    epoch_origin,
    read_epoch,
    set_noise_apart,
)
from ..runtime import fingerprint, output_folder
from ..runtime.atomic import check_output_name, is_write_failure, remove_stale_temporaries, write_failure_message, write_json, write_text
from ..runtime.progress import ProgressCallback
from ..runtime.text_safety import json_text
from .model import DamageModel, ModelError, load_model
from .unseen_damage import prior_weights, unseen_shares, with_prior, with_unseen_damage

log = logging.getLogger(__name__)

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "data" / "default_model.skops"


class ClassifyError(QuakeScanError):
    """Classification cannot run as asked."""


def default_model_path() -> Path:
    if not DEFAULT_MODEL.is_file():
        raise ModelError(f"{DEFAULT_MODEL}: the shipped default model is missing; rebuild it with "
                         "`python blender_scripts/make_default_model.py` or pass --model")
    return DEFAULT_MODEL


def model_settings(model: DamageModel, source: str = "model") -> PipelineSettings:
    """The pipeline settings the model was trained with; refuses a model for other features."""
    stored = model.split if isinstance(model.split, dict) else {}
    try:
        settings = settings_for_descriptors(model.feature_names, model.radius_m, stored.get("split"), stored,
                                            min_points_pre=int(stored.get("min_points_pre", 50)),
                                            min_points_post=int(stored.get("min_points_post", 10)),
                                            tile_m=float(stored.get("tile_m", 150.0)),
                                            core_point_step=int(stored.get("core_point_step", 1)))
    except (QuakeScanError, TypeError, ValueError, KeyError, AttributeError) as e:  # settings out of range or of the wrong type
        raise ModelError(f"{source}: the model's settings are invalid ({e}): an edited or foreign file; "
                         "retrain it with `quakescan train`") from None
    version = (model.provenance or {}).get("descriptor_version")
    if settings.surface is not None and version is not None:
        from ..change.surface import DESCRIPTOR_VERSION

        if version != DESCRIPTOR_VERSION:
            log.warning("%s: trained on surface descriptors of version %s, this QuakeScan computes version %s: "
                        "retrain it (blender_scripts/make_default_model.py) for results it was measured on",
                        source, version, DESCRIPTOR_VERSION)
    if settings.descriptor_names() != list(model.feature_names):
        raise ModelError(f"{source}: the model's descriptor columns are not in the order this QuakeScan "
                         f"computes them ({model.feature_names[:4]}...): retrain it with `quakescan train`")
    return settings


@dataclass
class PairData:
    pre: Epoch
    post: Epoch
    footprints: object = None  # quakescan.formats.footprints.Footprints
    footprint_ids_without_points: list = field(default_factory=list)
    noise_points: dict = field(default_factory=dict)  # {"pre": n, "post": n}: ASPRS noise, in no building


def load_pair(pre_path, post_path, footprints_path=None, id_field: str | None = None, labels: bool = True) -> PairData:
    """Both epochs in the pre epoch's local frame, with building IDs (and, unless `labels` is
    False, a simulated cloud's per-point grade and surface)."""
    # both epochs at once, in the pre-event file's frame: decoding and scaling are numpy and
    # file reads, which run side by side (a 2 x 75 M-point pair in 20 s instead of 26-33 s)
    origin = epoch_origin(pre_path)
    check_point_cloud_path(post_path)  # before the pre-event epoch is read, not after
    with ThreadPoolExecutor(max_workers=2) as pool:
        pre_job, post_job = (pool.submit(read_epoch, pre_path, origin, labels=labels),
                              pool.submit(read_epoch, post_path, origin, labels=labels))
        pre, post = pre_job.result(), post_job.result()
    check_pair(pre, post)
    if footprints_path is None:
        for e in (pre, post):
            if e.building_id is None:
                raise ClassifyError(f"{e.source}: no building_id dimension; give building footprints "
                                    "(--footprints F.geojson in the clouds' CRS)")
        return PairData(pre, post, noise_points=_noise_apart(pre, post))
    from ..formats.footprints import assign_buildings, read_footprints

    fp = read_footprints(footprints_path, id_field)
    if fp.crs and pre.crs and fp.crs != pre.crs:
        raise ClassifyError(f"{footprints_path}: footprints are in {fp.crs} but the point clouds in {pre.crs}; "
                            "reproject the footprints")
    if fp.crs and not pre.crs and not post.crs:
        log.info("%s: the point clouds name no CRS; taking the footprints' %s", pre.source, fp.crs)
        pre.crs = post.crs = fp.crs  # footprints that hit the points share their CRS
    for e in (pre, post):
        e.building_id = assign_buildings(e.xyz[:, 0] + e.origin[0], e.xyz[:, 1] + e.origin[1], fp)
    if not (pre.building_id > 0).any():
        b = fp.bounds()
        raise ClassifyError(f"{footprints_path}: no footprint contains a pre-event point (footprints span "
                            f"x {b[:, 0].min():.1f}..{b[:, 2].max():.1f}, y {b[:, 1].min():.1f}..{b[:, 3].max():.1f}; "
                            f"points x {pre.bounds_xy()[:, 0].round(1).tolist()}); wrong CRS?")
    noise = _noise_apart(pre, post)
    hit = set(np.unique(pre.building_id).tolist()) | set(np.unique(post.building_id).tolist())
    empty = sorted(int(i) for i in fp.ids if int(i) not in hit)
    return PairData(pre, post, fp, empty, noise)


def warn_of_epoch_order(pre_path, post_path, summary: dict) -> None:
    """Say so (on the console and in the summary's "warnings") when the files date the
    post-event epoch before the pre-event one (`epoch_order_warning`)."""
    warning = epoch_order_warning(pre_path, post_path)
    if warning:
        log.warning("%s", warning)
        summary.setdefault("warnings", []).append(warning)


def _noise_apart(pre: Epoch, post: Epoch) -> dict:
    """Both epochs' noise returns in no building (`set_noise_apart`), counted and said."""
    counts = {"pre": set_noise_apart(pre), "post": set_noise_apart(post)}
    for name, e in (("pre", pre), ("post", post)):
        if counts[name]:
            log.info("%s: %d noise returns (ASPRS class 7/18) left out of every building", e.source, counts[name])
    return counts


def _fingerprint(pre_path, post_path, footprints_path, model_path, align: bool | None, options: dict):
    """What a classification depends on (`quakescan.runtime.fingerprint`): the clouds by path, size and time
    (gigabytes: hashing them would cost more than many reruns), the footprints and the model
    by content, the alignment mode and the output options."""
    inputs = {"pre": fingerprint.stat(pre_path), "post": fingerprint.stat(post_path),
              "footprints": fingerprint.content(footprints_path), "model": fingerprint.content(model_path)}
    return fingerprint.make("classify", inputs=inputs, settings={"align": align, **options})


class _Checkpoint:
    """Rows of finished tiles, one JSON line each, valid for one fingerprint.

    The first line (the fingerprint) is written under a temporary name and renamed, so an
    interruption never leaves a file without it; a file that is unreadable anyway (cut,
    edited, another program's) is discarded with a warning and its tiles are recomputed."""

    def __init__(self, path: Path, digest: str):
        self.path, self.fp = path, digest
        self.rows: dict[int, BuildingRow] = {}
        if path.is_file():
            self._read(path, digest)
        if not path.is_file():
            write_json(path, {"fingerprint": digest}, indent=None)

    def _read(self, path: Path, digest: str) -> None:
        try:
            lines = path.read_text().splitlines()
            head = json.loads(lines[0]) if lines else None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            log.warning("%s: unreadable checkpoint (%s), discarded: every tile is recomputed", path, e)
            head = None
        if isinstance(head, dict) and head.get("fingerprint") == digest:
            for line in lines[1:]:
                try:
                    d = json.loads(line)
                    r = BuildingRow(int(d["building_id"]), int(d["n_pre"]), int(d["n_post"]), True, "",
                                    dict(d["descriptors"]), tuple(d["centre_xy"]), d.get("quality", {}))
                except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                    break  # a line cut by the interruption: that tile is redone
                self.rows[r.building_id] = r
        else:
            path.unlink()

    def add(self, rows):
        try:
            with open(self.path, "a") as f:
                for r in rows:
                    f.write(json.dumps({"building_id": r.building_id, "n_pre": r.n_pre, "n_post": r.n_post,
                                        "descriptors": r.descriptors, "centre_xy": list(r.centre_xy),
                                        "quality": r.quality}) + "\n")
                f.flush()
                os.fsync(f.fileno())
        except OSError as e:  # a rerun reads the lines before the cut one and redoes the rest
            if not is_write_failure(e):
                raise
            raise ResultsError(write_failure_message(self.path, e)) from e


def predict_rows(rows, model: DamageModel, rule: bool | None = None, unseen_damage: bool = True,
                 prior: dict | None = None) -> list:
    """BuildingResults: not assessable stays so; no changed points → no damage by rule;
    else the model. `confidence`: the model's probability of the grade it gives, 1.0 for a
    grade given by rule, None when not assessable.

    rule: decide buildings without changed points without asking the model (the paper's
    rule); None: as the model was trained (`model.no_change_rule`; True for every model
    file written before the switch existed). Every assessed building carries what its data
    could resolve (`quakescan.change.detectability.of_building`), where its row says.

    unseen_damage: the probabilities, and so the confidence of the grade, count the damage the
    building's data could not have shown (`quakescan.learning.unseen_damage`): "no damage"
    under an airborne laser that resolves no wall holes is not said with a drone's confidence.
    The grade is the model's either way (what the data show). False: the model's own
    probabilities (damage assumed to show). `prior` {grade: share}: the mix of grades the user
    expects, for the equal one the model's probabilities carry (`unseen_damage.with_prior`);
    the grades stay the model's."""
    from ..results.writers import BuildingResult

    rule = model.no_change_rule if rule is None else bool(rule)
    classes = model.classes
    grades = sorted(set(classes) | ({0} if rule else set()))
    if prior is not None:
        prior_weights(prior, grades)  # a prior that cannot be used is refused before any row
    out, ask = [], []
    for r in rows:
        if not r.assessable:
            out.append(BuildingResult(r.building_id, r.n_pre, r.n_post, False, r.reason))
            continue
        # the paper's share of changed points, or for a surface model its share of changed surface
        share = float(r.descriptors.get("share_changed", r.descriptors.get("m_changed", 0.0)))
        res = BuildingResult(r.building_id, r.n_pre, r.n_post, True, "", share_changed=share)
        seen = of_building(r.quality)
        if seen is not None:
            res.detectable_grade, res.min_opening_m2, res.min_lowering_m = (seen.detectable_grade,
                                                                            seen.min_opening_m2, seen.min_lowering_m)
            res.walls_resolved, res.min_wall_opening_m2 = seen.walls_resolved, seen.min_wall_opening_m2
        if rule and share == 0.0:
            p = np.array([[float(c == 0) for c in grades]])
            if unseen_damage:
                p = with_unseen_damage(p, grades, [unseen_shares(seen, grades)])
            p = with_prior(p, grades, prior)
            res.grade = 0
            res.probabilities = {c: float(v) for c, v in zip(grades, p[0])}
            res.decided_by = "no change"
            res.confidence = res.probabilities[0]
        else:
            ask.append((res, r, seen))
        out.append(res)
    if ask:
        table = {n: np.array([r.descriptors[n] for _, r, _ in ask]) for n in model.feature_names}
        proba = model.predict_proba(table)
        # the grade is what the data show (the model's own answer); its probabilities, and so
        # its confidence, count what they could not show
        said = np.argmax(proba, axis=1)
        if unseen_damage:
            proba = with_unseen_damage(proba, classes, [unseen_shares(seen, classes) for _, _, seen in ask])
        proba = with_prior(proba, classes, prior)
        for (res, _, _), p, k in zip(ask, proba, said):
            res.probabilities = {c: 0.0 for c in grades}
            res.probabilities.update({c: float(v) for c, v in zip(classes, p)})
            res.grade = int(classes[int(k)])
            res.decided_by = "model"
            res.confidence = float(p[k])
    return out


def run_options(id_field, write_las: bool, laz, unseen_damage: bool, prior: dict | None,
                csv_raw: bool = False) -> dict:
    """The options of a classify run that its results depend on (its fingerprint's, the
    summary's), for one process and the Dask path alike."""
    options = {"id_field": id_field, "write_las": bool(write_las), "laz": laz}
    if not unseen_damage:  # the defaults leave the fingerprint of earlier results as it was
        options["unseen_damage"] = False
    if csv_raw:
        options["csv_raw"] = True
    if prior is not None:
        options["prior"] = {str(int(g)): float(v) for g, v in sorted(prior.items())}
    return options


def classify(pre_path, post_path, out_dir, *, model_path=None, footprints_path=None, id_field=None,
             align: bool | None = None, workers: int = -1, progress: ProgressCallback | None = None,
             write_las: bool = True, laz: bool | None = None, force: bool = False, unseen_damage: bool = True,
             prior: dict | None = None, csv_raw: bool = False) -> dict:
    """Run the whole classification and write OUT/buildings.csv, .geojson, .qml (its QGIS
    style), damage_map.png, damage_map.html (offline), post_grades.las and summary.json.
    Returns the summary.

    `align`: True aligns the post epoch to the pre epoch on stable ground (ICP) first; False
    takes the epochs as they are; None (default) checks their registration and aligns when
    they disagree beyond what the model tolerates, saying so (`_register`). The graded
    post-event cloud keeps every attribute of the post-event file and is compressed
    (post_grades.laz) when `laz`, or when `laz` is None and the post-event file is LAZ.
    A folder that holds the finished results of the same inputs, model and options is up to
    date: its summary is returned (with "up_to_date": True) and nothing is recomputed,
    unless `force`. `unseen_damage`: the probabilities count the damage each building's data
    could not have shown (`predict_rows`); False gives the model's own. `prior` {grade: share}:
    the mix of grades expected, for the model's equal one (`predict_rows`). `csv_raw`:
    buildings.csv keeps footprint IDs that begin like a formula as they are (for machine
    readers; `quakescan.results.writers.write_csv`)."""
    with claimed_output_folder(out_dir, "classify", pre_path, post_path, footprints_path, model_path):
        return _classify(pre_path, post_path, out_dir, model_path=model_path, footprints_path=footprints_path,
                         id_field=id_field, align=align, workers=workers, progress=progress, write_las=write_las,
                         laz=laz, force=force, unseen_damage=unseen_damage, prior=prior, csv_raw=csv_raw)


def _classify(pre_path, post_path, out_dir, *, model_path=None, footprints_path=None, id_field=None,
              align: bool | None = None, workers: int = -1, progress: ProgressCallback | None = None,
              write_las: bool = True, laz: bool | None = None, force: bool = False, unseen_damage: bool = True,
              prior: dict | None = None, csv_raw: bool = False) -> dict:
    """`classify` in the output folder it has claimed."""
    from ..results import writers as results

    t0 = time.perf_counter()
    out = Path(out_dir)
    model_path = Path(model_path) if model_path else default_model_path()
    check_input_file(model_path, "model file", ClassifyError)  # the inputs given were checked with the folder
    options = run_options(id_field, write_las, laz, unseen_damage, prior, csv_raw)
    run_fp = _fingerprint(pre_path, post_path, footprints_path, model_path, align, options)
    done = _finished(out, run_fp)
    if done is not None and not force:
        log.info("%s: up to date (same inputs, model and options); force=True recomputes", out)
        return {**done, "up_to_date": True}
    model = load_model(model_path)
    if prior is not None:  # before the long part: a prior the model's grades do not fit is refused
        prior_weights(prior, sorted(set(model.classes) | ({0} if model.no_change_rule else set())))
    settings = model_settings(model, str(model_path))
    data = load_pair(pre_path, post_path, footprints_path, id_field, labels=False)  # 2 bytes a point less
    pre, post = data.pre, data.post
    summary: dict = {"pre": str(pre_path), "post": str(post_path), "model": str(model_path),
                     "model_provenance": model.provenance, "settings": settings.to_json(),
                     "points": {"pre": len(pre), "post": len(post)}, "noise_points": data.noise_points,
                     "crs": pre.crs}
    warn_of_epoch_order(pre_path, post_path, summary)
    summary["registration"] = _register(pre, post, settings, align, summary, workers)
    t_read = time.perf_counter()
    retire_previous_results(out)  # before the first write
    ckpt = _Checkpoint(out / ".checkpoint.jsonl", run_fp.digest)
    resumed = len(ckpt.rows)
    if resumed:
        log.warning("%s: resuming, %d buildings already described", out, resumed)
    rows = describe_pair(pre, post, settings, workers=workers, progress=progress, done=ckpt.rows,
                         on_tile=ckpt.add)
    rows += [BuildingRow(int(b), 0, 0, False, "no point inside the footprint")
             for b in data.footprint_ids_without_points]
    if data.footprints is not None:  # footprints that cannot be used: the building stays, with the reason
        described = {r.building_id for r in rows}
        rows += [BuildingRow(int(b), 0, 0, False, why) for b, why, _ in data.footprints.rejected
                 if int(b) not in described]
    rows.sort(key=lambda r: r.building_id)
    t_describe = time.perf_counter()
    res = predict_rows(rows, model, unseen_damage=unseen_damage, prior=prior)
    summary["unseen_damage"] = bool(unseen_damage)
    summary["prior"] = options.get("prior", "equal (the model's)")
    out.mkdir(parents=True, exist_ok=True)
    fp = data.footprints
    outlines = results.building_outlines(res, fp, _XYByBuilding(pre) if fp is None else None, pre.origin)
    write_building_results(out, res, model.grades, fp, outlines, pre.crs,
                           pre.xyz[:: map_step(len(pre)), :2] + pre.origin[:2], f"Damage grades: {Path(post_path).name}",
                           csv_raw=csv_raw)
    t_graded = time.perf_counter()
    if write_las:
        compress = Path(post_path).suffix.lower() == ".laz" if laz is None else laz
        graded = out / ("post_grades.laz" if compress else "post_grades.las")
        results.write_grade_las(graded, post.xyz, post.origin, post.crs, post.building_id,
                                {r.building_id: r.grade for r in res}, source=post_path)
        summary["post_grades"] = str(graded)
    t_graded = time.perf_counter() - t_graded
    counts: dict[str, int] = {}
    for r in res:
        counts[r.label] = counts.get(r.label, 0) + 1
    summary.update({"buildings": len(res), "by_label": counts, "by_grade_name": counts_by_grade_name(res),
                    "detectability": detectability_counts(res),
                    "resumed_buildings": resumed,
                    "seconds": {"read": round(t_read - t0, 2), "describe": round(t_describe - t_read, 2),
                                "graded_cloud": round(t_graded, 2), "total": round(time.perf_counter() - t0, 2)}})
    summary["fingerprint"] = run_fp.digest
    summary["options"] = options
    summary["outputs"] = result_names(summary)
    warn_of_foreign_results(out, summary)
    write_text(out / "summary.json", json_text(summary, indent=1, default=_json_default))  # strict: NaN is null
    ckpt.path.unlink(missing_ok=True)
    return summary


MAP_POINTS = 200_000  # pre-event points drawn under the damage map


def map_step(n: int) -> int:
    """Every k-th pre-event point is drawn under the damage map."""
    return max(1, n // MAP_POINTS)


def write_building_results(out: Path, res, classes, fp, outlines, crs, map_xy, title: str,
                           csv_raw: bool = False) -> None:
    """buildings.csv, .geojson, .qml, damage_map.png and .html of graded buildings (also a
    distributed run's, `quakescan.distributed`): `map_xy` the world x/y drawn under the map;
    `csv_raw`: footprint IDs unescaped in the CSV (`write_csv`'s `raw_text`)."""
    from ..results import writers as results
    from ..results.qgis_style import write_qml
    from ..results.webmap import write_map_html

    own = fp.own_ids() if fp is not None else None
    results.write_csv(res, out / "buildings.csv", classes, own_ids=own, raw_text=csv_raw)
    attributes = (fp.attributes() or None) if fp is not None else None
    results.write_geojson(res, outlines, out / "buildings.geojson", crs, classes, attributes)
    write_qml(out / "buildings.qml")
    results.write_map_png(res, outlines, out / "damage_map.png", title, points_xy=map_xy, crs=crs)
    write_map_html(res, outlines, out / "damage_map.html", title, crs, classes, own_ids=own)


def counts_by_grade_name(res) -> dict:
    """{"0 no damage": n, "3 substantial to heavy (heavy)": n, ..., "not assessable": n} in
    grade order: what the CLI prints (quakescan.grades)."""
    from ..grades import long_label
    from ..results.writers import NOT_ASSESSABLE

    grades = sorted({int(r.grade) for r in res if r.assessable and r.grade is not None})
    out = {long_label(g): sum(1 for r in res if r.assessable and r.grade == g) for g in grades}
    missing = sum(1 for r in res if not r.assessable or r.grade is None)
    if missing:
        out[NOT_ASSESSABLE] = missing
    return out


def detectability_counts(res) -> dict:
    """What the summary says of the assessed buildings' detectability
    (`quakescan.change.detectability`): how many graded 0 cannot resolve heavy damage (the
    maps hatch them), and how many resolve each lowest grade ("none": no grade 3-5;
    "unknown": no detectability, e.g. a model without surface descriptors)."""
    assessed = [r for r in res if r.assessable and r.grade is not None]
    by: dict[str, int] = {}
    for r in assessed:
        key = ("unknown" if r.min_opening_m2 is None else
               "none" if r.detectable_grade is None else str(int(r.detectable_grade)))
        by[key] = by.get(key, 0) + 1
    order = ["3", "4", "5", "none", "unknown"]
    walls = {"resolved": sum(1 for r in assessed if r.walls_resolved is True),
             "not_resolved": sum(1 for r in assessed if r.walls_resolved is False),
             "unknown": sum(1 for r in assessed if r.walls_resolved is None)}
    return {"no_damage_heavy_unresolved": sum(1 for r in assessed if r.heavy_unresolved),
            "by_detectable_grade": {k: by[k] for k in order if k in by},
            "walls_resolve_heavy": walls,
            "no_damage_walls_unresolved": sum(1 for r in assessed if r.grade == 0 and r.walls_resolved is False)}


# Epochs whose stable ground disagrees by more than this share of the model's level of
# detection are aligned before describing: a georeferencing offset of a few decimetres
# reads as change on every building (AHN3 shifted by 0.4 m: 134 of 134 called damaged).
# Below it the level of detection absorbs the offset, and ICP between different sensors
# finds spurious offsets of 2-8 cm on perfectly registered simulated pairs (bench_transfer's
# held-out city): aligning those would move the data, not correct it.
AUTO_ALIGN_SHARE_OF_LOD = 1.0
# ... and only when the alignment fits the stable points markedly better. On flat ground a
# shift or turn within the ground's plane changes no point-to-plane residual, so ICP's
# estimate of it is whatever it drifts to: airborne (ALS-like) vs DIM sampling of a 300 m
# city gave a 0.12° turn that moved the far corners 0.62 m and cut the rmse by 2 µm (0.0313
# m both), and aligning by it read as damage on undamaged buildings. A real offset beyond
# the level of detection shows in the residuals (AHN3 moved by 0.4 m and up 0.15 m: rmse
# 0.15 -> 0.03 m); a turn the residuals cannot see is no evidence of one.
MIN_FIT_GAIN = 0.10  # the share of the rmse an automatic alignment must remove
CHECK_MAX_POINTS = 500_000  # stable points ICP sees for the check: a rigid transform needs few
ALIGN_MAX_POINTS = 2_000_000  # and when asked to align


def registration_tolerance_m(settings: PipelineSettings) -> float:
    """The largest offset between epochs left as it is: the model's level of detection."""
    lod = settings.surface.lod_floor_m if settings.surface is not None else settings.split.lod_height_m
    return AUTO_ALIGN_SHARE_OF_LOD * lod


def _register(pre, post, settings: PipelineSettings, align: bool | None, summary: dict, workers: int = -1) -> dict:
    """Check (and, when asked or needed, apply) the rigid alignment of post to pre; moves
    post.xyz in place; returns what was done for the summary."""
    from ..change.align import sample_mask, stable_mask

    if align is False:
        return {"mode": "off", "checked": False}
    max_points = check_max_points(align)
    samples = []
    for e in (pre, post):
        keep = stable_mask(e.classification, e.building_id) & sample_mask(range(len(e)), len(e), max_points)
        samples.append(e.xyz[keep])
    return register_samples(samples[0], samples[1], post, settings, align, summary, workers=workers)


def check_max_points(align: bool | None) -> int:
    """How many stable points of each epoch the registration check samples."""
    return CHECK_MAX_POINTS if align is None else ALIGN_MAX_POINTS


def register_samples(pre_sample, post_sample, post, settings: PipelineSettings, align: bool | None, summary: dict,
                     post_bounds=None, workers: int = -1) -> dict:
    """`_register` on the epochs' sampled stable points (`sample_mask`): a streamed run
    (`quakescan.distributed`) samples the same points chunk by chunk. Moves post.xyz when
    the alignment is applied and `post` is an Epoch; returns the record."""
    from ..change.align import AlignmentError, align_epochs, format_alignment

    mode = "on" if align else "auto"
    tolerance = registration_tolerance_m(settings)
    pre_name, post_name = str(summary.get("pre", "the pre-event epoch")), str(summary.get("post", "the post-event epoch"))
    try:
        a = align_epochs(pre_sample, post_sample, np.ones(len(pre_sample), bool), np.ones(len(post_sample), bool),
                         max_points=check_max_points(align), pre_name=pre_name, post_name=post_name,
                         workers=workers)
    except AlignmentError as e:
        if mode == "on":
            raise AlignmentError(f"--align: cannot align {post_name} to {pre_name}: {e}") from None
        log.warning("cannot check that the epochs are registered (%s); classifying them as they are: an offset "
                    "between them would read as damage", e)
        return {"mode": mode, "checked": False, "reason": str(e)}
    offset = max_displacement_m(a, post.xyz if post_bounds is None else post_bounds)
    record = {"mode": mode, "checked": True, "offset_m": round(offset, 4), "tolerance_m": tolerance,
              "applied": False}
    needed = offset > tolerance and a.rmse_after_m < (1.0 - MIN_FIT_GAIN) * a.rmse_before_m
    if offset > tolerance and not needed:
        record["unobserved"] = (f"the fit moved {offset:.2f} m but its rmse only {a.rmse_before_m:.4f} -> "
                                f"{a.rmse_after_m:.4f} m: not applied")
        log.info("registration check: %s", record["unobserved"])
    if mode == "on" or needed:
        if post is not None and post_bounds is None:
            post.xyz = a.apply(post.xyz)
        summary["alignment"] = a.to_json()
        record["applied"] = True
        if mode == "auto":
            log.warning("the epochs disagree on stable ground by up to %.2f m (more than the %.2f m the model "
                        "tolerates): aligned the post-event epoch to the pre-event one (%s); --no-align keeps "
                        "them as they are", offset, tolerance, format_alignment(a))
        else:
            log.info("alignment: %s", format_alignment(a))
        if a.std_after_m * 1.96 > settings.split.lod_height_m:
            log.warning("the alignment's noise (std %.3f m) exceeds what the model's level of detection "
                        "(%.2f m) tolerates: expect undamaged buildings to look changed",
                        a.std_after_m, settings.split.lod_height_m)
    return record


def max_displacement_m(a, xyz: np.ndarray) -> float:
    """How far the alignment moves any corner of the cloud's bounding box (translation and
    rotation together: a small rotation moves the far edge of a large tile the most)."""
    from ..change._cell_kernels import column_bounds

    lo, hi = column_bounds(np.asarray(xyz, dtype=np.float64))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(np.linalg.norm(a.apply(corners) - corners, axis=1).max())


def _check_output_folder(out: Path, inputs) -> None:
    """Refuse an output folder that is a file, above all one of the inputs: classify writes
    several files into it and would otherwise fail half-way or overwrite its own input."""
    for p in inputs:
        if p is not None and Path(p).exists() and out.exists() and os.path.samefile(p, out):
            raise ClassifyError(f"{out}: the output folder (-o) is the input file {p}; give a folder for the results")
    if out.exists() and not out.is_dir():
        raise ClassifyError(f"{out}: the output (-o) is an existing file; classify writes a folder of results "
                            "(buildings.csv, buildings.geojson, damage_map.png, ...): give a folder")


RESULT_NAMES = ("buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.png", "damage_map.html")
GRADED_NAMES = ("post_grades.las", "post_grades.laz")
# Everything a classification writes, replaces or deletes in its output folder: none of it may be an input.
WRITTEN_NAMES = RESULT_NAMES + GRADED_NAMES + ("summary.json", ".checkpoint.jsonl", ".checkpoint.unmoved.jsonl",
                                               ".blocks", ".graded")


@contextlib.contextmanager
def claimed_output_folder(out_dir, command: str, pre_path, post_path, footprints_path, model_path,
                          working_folders=()):
    """The checks of `classify` (one process or Dask) before anything is read or written, and
    the output folder held for the run (`quakescan.runtime.output_folder`): the inputs exist,
    OUT is a folder, no input is a file the run writes or deletes in it, its `working_folders`
    (names in OUT) are QuakeScan's or absent, no other run is in it; the temporary files of a
    killed run there are removed."""
    out = output_folder.check_output_path(out_dir, "-o", ClassifyError)
    inputs = ((pre_path, "pre-event point cloud"), (post_path, "post-event point cloud"),
              (footprints_path, "footprint file"), (model_path, "model file"))
    for p, what in inputs:
        if p is not None:  # before the fingerprint reads them; a device or FIFO is refused as such
            check_input_file(p, what, ClassifyError)
    _check_output_folder(out, [p for p, _ in inputs])
    output_folder.refuse_replacing_inputs([out / name for name in WRITTEN_NAMES], inputs, ClassifyError, command)
    for name in RESULT_NAMES + GRADED_NAMES + ("summary.json",):  # refused now, not after the work
        if (out / name).is_symlink():
            check_output_name(out / name, ClassifyError)
    for name in working_folders:
        if (out / name).exists() or (out / name).is_symlink():
            output_folder.own_subfolder(out / name, ClassifyError)  # refuses one that is not QuakeScan's
    with output_folder.exclusive_run(out, command, ClassifyError):
        remove_stale_temporaries(out)  # a killed run's; not a live writer's (evaluate may write here too)
        yield out


def result_names(summary: dict) -> list[str]:
    """The files a finished classification wrote into its folder (its summary's "outputs")."""
    names = list(RESULT_NAMES)
    if "post_grades" in summary:
        names.append(Path(summary["post_grades"]).name)
    return names + ["summary.json"]


def retire_previous_results(out: Path) -> None:
    """Before a classification writes: the folder no longer says it holds finished results (a
    run stopped half-way must not leave a summary over a mix of two runs' files, which a
    rerun would take as up to date), and the graded cloud a previous run recorded writing is
    removed when this run writes another one or none (`--no-las`, `--laz` after a `.las`
    run): never left beside the new results as if it were theirs. Only QuakeScan's own names,
    and only those the previous summary lists."""
    summary_path = out / "summary.json"
    try:
        previous = json.loads(summary_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return
    if not isinstance(previous, dict) or "fingerprint" not in previous:
        return  # not a summary of ours: left as it is
    recorded = previous.get("outputs")
    if not isinstance(recorded, list):  # a summary written before "outputs": its graded cloud is named apart
        recorded = [Path(str(previous["post_grades"])).name] if "post_grades" in previous else []
    summary_path.unlink(missing_ok=True)
    for name in recorded:
        if name in GRADED_NAMES:  # written again under its name, or not at all: remove it now
            (out / name).unlink(missing_ok=True)


def warn_of_foreign_results(out: Path, summary: dict) -> None:
    """Say so when a graded cloud this run did not write, and no run recorded writing, sits
    beside the results (a user's file under QuakeScan's name): it is left as it is."""
    for name in GRADED_NAMES:
        if name not in summary["outputs"] and (out / name).exists():
            log.warning("%s: not written by this run nor recorded by an earlier one, so left as it is: it is not "
                        "the graded cloud of these results", out / name)


def _finished(out: Path, fp) -> dict | None:
    """The summary of a finished classification of the same inputs in `out`, else None."""
    try:
        summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not fingerprint.matches(summary, fp):
        return None
    wanted = ["buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.png", "damage_map.html"]
    if summary["options"]["write_las"]:
        wanted.append(Path(summary.get("post_grades", "post_grades.las")).name)
    return summary if all((out / name).is_file() for name in wanted) else None


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


class _XYByBuilding:
    """{building ID: its points' local x/y} for the outlines, each building's copied only when
    asked for: all of them at once were a second copy of a city's x/y (1.2 GB of a 75 M-point
    epoch, with an 8-byte argsort beside it: the run's memory peak)."""

    def __init__(self, e: Epoch):
        from ..change.pipeline import _members_by_id

        self.xyz = e.xyz
        self.members = _members_by_id(e.building_id)

    def get(self, bid: int, default=None):
        idx = self.members(bid) if bid > 0 else None
        return default if idx is None or len(idx) == 0 else self.xyz[idx, :2]


__all__ = ["ClassifyError", "PointCloudError", "classify", "default_model_path", "load_pair", "model_settings",
           "predict_rows"]
