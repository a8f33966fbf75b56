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

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..change.detectability import of_building
from ..change.pipeline import describe_pair, descriptor_matrix
from ..change.settings import PipelineSettings, settings_for_descriptors
from ..errors import QuakeScanError
from ..formats.pointcloud import (
    Epoch,
    PointCloudError,
    check_pair,
    check_point_cloud_path,
    epoch_origin,
    read_epoch,
    set_noise_apart,
)
from ..runtime.progress import ProgressCallback
from .classify_run import (  # noqa: F401  (ClassifyError, DEFAULT_MODEL, default_model_path: the API's, here as ever)
    DEFAULT_MODEL,
    ClassifyError,
    RowCheckpoint,
    begin,
    claimed_output_folder,
    default_model_path,
    finish,
    footprint_rows,
    footprints_without_points,
    graded_cloud_path,
    map_step,
    no_footprint_contains_a_point,
    retire_previous_results,
    run_options,
    run_summary,
    write_building_results,
)
from .model import DamageModel, ModelError, changed_share, load_model
from .unseen_damage import prior_weights, unseen_shares, with_prior, with_unseen_damage

log = logging.getLogger(__name__)







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
        from ..change.descriptors import DESCRIPTOR_VERSION

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
        raise no_footprint_contains_a_point(footprints_path, fp, pre.bounds_xy()[:, 0])
    noise = _noise_apart(pre, post)
    hit = set(np.unique(pre.building_id).tolist()) | set(np.unique(post.building_id).tolist())
    return PairData(pre, post, fp, footprints_without_points(fp, hit), noise)




def _noise_apart(pre: Epoch, post: Epoch) -> dict:
    """Both epochs' noise returns in no building (`set_noise_apart`), counted and said."""
    counts = {"pre": set_noise_apart(pre), "post": set_noise_apart(post)}
    for name, e in (("pre", pre), ("post", post)):
        if counts[name]:
            log.info("%s: %d noise returns (ASPRS class 7/18) left out of every building", e.source, counts[name])
    return counts




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
    from ..results.building_result import BuildingResult

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
        share = changed_share(r.descriptors)  # the rule's column, as training reads it
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
        proba = model.predict_proba_matrix(descriptor_matrix([r for _, r, _ in ask], model.feature_names))
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
    from ..results.graded_cloud import write_grade_las
    from ..results.outlines import building_outlines

    t0 = time.perf_counter()
    out = Path(out_dir)
    options = run_options(id_field, write_las, laz, unseen_damage, prior, csv_raw)
    model_path, run_fp, done = begin(pre_path, post_path, out, model_path=model_path,
                                     footprints_path=footprints_path, align=align, options=options, force=force)
    if done is not None:
        return done
    model = load_model(model_path)
    if prior is not None:  # before the long part: a prior the model's grades do not fit is refused
        prior_weights(prior, sorted(set(model.classes) | ({0} if model.no_change_rule else set())))
    settings = model_settings(model, str(model_path))
    data = load_pair(pre_path, post_path, footprints_path, id_field, labels=False)  # 2 bytes a point less
    pre, post = data.pre, data.post
    summary = run_summary(pre_path, post_path, model_path, model, settings, {"pre": len(pre), "post": len(post)},
                          data.noise_points, pre.crs)
    summary["registration"] = _register(pre, post, settings, align, summary, workers)
    t_read = time.perf_counter()
    retire_previous_results(out)  # before the first write
    ckpt = RowCheckpoint(out / ".checkpoint.jsonl", run_fp.digest)
    resumed = len(ckpt.rows)
    if resumed:
        log.warning("%s: resuming, %d buildings already described", out, resumed)
    rows = describe_pair(pre, post, settings, workers=workers, progress=progress, done=ckpt.rows,
                         on_tile=ckpt.add)
    rows += footprint_rows(data.footprints, rows, data.footprint_ids_without_points)
    rows.sort(key=lambda r: r.building_id)
    t_describe = time.perf_counter()
    res = predict_rows(rows, model, unseen_damage=unseen_damage, prior=prior)
    summary["unseen_damage"] = bool(unseen_damage)
    summary["prior"] = options.get("prior", "equal (the model's)")
    out.mkdir(parents=True, exist_ok=True)
    fp = data.footprints
    outlines = building_outlines(res, fp, _XYByBuilding(pre) if fp is None else None, pre.origin)
    write_building_results(out, res, model.grades, fp, outlines, pre.crs,
                           pre.xyz[:: map_step(len(pre)), :2] + pre.origin[:2], f"Damage grades: {Path(post_path).name}",
                           csv_raw=csv_raw)
    t_graded = time.perf_counter()
    if write_las:
        graded = graded_cloud_path(out, post_path, laz)
        write_grade_las(graded, post.xyz, post.origin, post.crs, post.building_id,
                                {r.building_id: r.grade for r in res}, source=post_path)
        summary["post_grades"] = str(graded)
    t_graded = time.perf_counter() - t_graded
    seconds = {"read": round(t_read - t0, 2), "describe": round(t_describe - t_read, 2),
               "graded_cloud": round(t_graded, 2), "total": round(time.perf_counter() - t0, 2)}
    finish(out, summary, res, options=options, digest=run_fp.digest, resumed=resumed, seconds=seconds)
    ckpt.path.unlink(missing_ok=True)
    return summary












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
    from ..grid.cells import column_bounds

    lo, hi = column_bounds(np.asarray(xyz, dtype=np.float64))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(np.linalg.norm(a.apply(corners) - corners, axis=1).max())


















class _XYByBuilding:
    """{building ID: its points' local x/y} for the outlines, each building's copied only when
    asked for: all of them at once were a second copy of a city's x/y (1.2 GB of a 75 M-point
    epoch, with an 8-byte argsort beside it: the run's memory peak)."""

    def __init__(self, e: Epoch):
        from ..change.tiling import members_by_id

        self.xyz = e.xyz
        self.members = members_by_id(e.building_id)

    def get(self, bid: int, default=None):
        idx = self.members(bid) if bid > 0 else None
        return default if idx is None or len(idx) == 0 else self.xyz[idx, :2]


__all__ = ["ClassifyError", "PointCloudError", "classify", "default_model_path", "load_pair", "model_settings",
           "predict_rows"]
