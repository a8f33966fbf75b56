"""Damage grades for the buildings of a real or simulated pre-/post-event pair (`quakescan classify`).

One run, whichever engine describes the buildings: the inputs checked and the output folder
claimed, the run's fingerprint (a folder holding the finished results of the same inputs,
model and options is up to date), the pair read by the engine (this process's threads,
`quakescan.assessment.in_process`, or Dask workers, `quakescan.distributed.engine`), its
registration checked and every building's change described (tile by tile, each finished tile
checkpointed to OUT/.checkpoint.jsonl so that a rerun continues from there), the model
applied (`quakescan.learning.prediction`), the result files and the graded post-event cloud
written, and the summary written last.

A building with too few points is reported as not assessable, never guessed; a building
without changed points is "no damage" by the paper's rule, without asking the model, unless
the model was trained on every row (`DamageModel.no_change_rule` False). Every output is
written under a temporary name and renamed. The output folder follows the rule of
`quakescan.runtime.output_folder` (`record.claimed_output_folder`): one run in it at a time,
no input replaced by a result, and the results of a previous run that this one does not
write removed by the record of its summary.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

from ..formats.footprints import coverage_words
from ..learning.model import load_model
from ..learning.prediction import model_settings, predict_rows
from ..learning.unseen_damage import prior_weights
from ..runtime.progress import ProgressCallback
from . import record
from .engine import Engine, Job

log = logging.getLogger(__name__)


def classify(pre_path, post_path, out_dir, *, model_path=None, footprints_path=None, id_field=None,
             align: bool | None = None, workers: int = -1, progress: ProgressCallback | None = None,
             write_las: bool = True, laz: bool | None = None, force: bool = False, unseen_damage: bool = True,
             prior: dict | None = None, csv_raw: bool = False, engine: Engine | None = None) -> dict:
    """Run the whole classification and write OUT/buildings.csv, .geojson, .qml (its QGIS
    style), damage_map.png, damage_map.html (offline), post_grades.las and summary.json.
    Returns the summary.

    `align`: True aligns the post epoch to the pre epoch on stable ground (ICP) first; False
    takes the epochs as they are; None (default) checks their registration and aligns when
    they disagree beyond what the model tolerates, saying so
    (`quakescan.change.registration`). The graded post-event cloud keeps every attribute of
    the post-event file and is compressed (post_grades.laz) when `laz`, or when `laz` is None
    and the post-event file is LAZ. A folder that holds the finished results of the same
    inputs, model and options is up to date: its summary is returned (with "up_to_date": True)
    and nothing is recomputed, unless `force`. `unseen_damage`: the probabilities count the
    damage each building's data could not have shown (`predict_rows`); False gives the model's
    own. `prior` {grade: share}: the mix of grades expected, for the model's equal one
    (`predict_rows`). `csv_raw`: buildings.csv keeps footprint IDs that begin like a formula as
    they are (for machine readers; `quakescan.results.csv_table.write_csv`). `engine`: who reads
    and describes the pair; by default this process, on `workers` threads
    (`quakescan.assessment.in_process.InProcess`); `quakescan.distributed.engine.DaskEngine`
    runs the tiles on a Dask cluster, with the same files as the result."""
    if engine is None:
        from .in_process import InProcess

        engine = InProcess(workers)
    with record.claimed_output_folder(out_dir, "classify", pre_path, post_path, footprints_path, model_path,
                                      working_folders=engine.working_folders):
        return _classify(pre_path, post_path, Path(out_dir), engine, model_path=model_path,
                         footprints_path=footprints_path, id_field=id_field, align=align, progress=progress,
                         write_las=write_las, laz=laz, force=force, unseen_damage=unseen_damage, prior=prior,
                         csv_raw=csv_raw)


def _classify(pre_path, post_path, out: Path, engine: Engine, *, model_path, footprints_path, id_field, align,
              progress, write_las, laz, force, unseen_damage, prior, csv_raw) -> dict:
    """`classify` in the output folder it has claimed."""
    from ..results.outlines import building_outlines

    t0 = time.perf_counter()
    options = record.run_options(id_field, write_las, laz, unseen_damage, prior, csv_raw)
    model_path, run_fp, done = record.begin(pre_path, post_path, out, model_path=model_path,
                                            footprints_path=footprints_path, align=align, options=options,
                                            force=force)
    if done is not None:
        return done
    retired: list = []

    def before_first_write():
        if not retired:
            record.retire_previous_results(out)
            retired.append(True)

    loaded: dict = {}

    def load():
        if "settings" not in loaded:
            model = load_model(model_path)
            if prior is not None:  # before the long part: a prior the model's grades do not fit is refused
                prior_weights(prior, sorted(set(model.classes) | ({0} if model.no_change_rule else set())))
            loaded["model"], loaded["settings"] = model, model_settings(model, str(model_path))
        return loaded["settings"]

    job = Job(pre_path, post_path, footprints_path, id_field, align, out, run_fp.digest, progress,
              before_first_write)
    pair = engine.read(job, load)
    settings = load()
    model = loaded["model"]
    summary = record.run_summary(pre_path, post_path, model_path, model, settings, pair.points, pair.noise_points,
                                 pair.crs)
    if pair.coverage:
        summary["coverage"] = dict(pair.coverage)
        # an epoch that misses buildings the other saw is a fact the responder must see on
        # stderr; footprints beyond both clouds (a city's file over one tile) are not
        if pair.coverage["pre_only"] or pair.coverage["post_only"]:
            log.warning("%s: %s", post_path, coverage_words(pair.coverage))
        else:
            log.info("%s: %s", post_path, coverage_words(pair.coverage))
    t_read = time.perf_counter()
    rows, resumed = engine.describe(job, pair, settings, summary)
    rows += record.footprint_rows(pair.footprints, rows, pair.footprint_ids_without_points)
    rows.sort(key=lambda r: r.building_id)
    t_describe = time.perf_counter()
    engine.described(job, pair)
    res = predict_rows(rows, model, unseen_damage=unseen_damage, prior=prior)
    summary["unseen_damage"] = bool(unseen_damage)
    summary["prior"] = options.get("prior", "equal (the model's)")
    out.mkdir(parents=True, exist_ok=True)
    fp = pair.footprints
    outlines = building_outlines(res, fp, pair.outline_points if fp is None else None, pair.outline_origin)
    record.write_building_results(out, res, model.grades, fp, outlines, pair.crs, pair.map_xy,
                                  f"Damage grades: {Path(post_path).name}", csv_raw=csv_raw)
    t_graded = time.perf_counter()
    if write_las:
        graded = record.graded_cloud_path(out, post_path, laz)
        engine.write_graded_cloud(job, pair, graded, {r.building_id: r.grade for r in res})
        summary["post_grades"] = str(graded)
    t_graded = time.perf_counter() - t_graded
    end = time.perf_counter()
    seconds = {"read": round(t_read - t0, 2), "describe": round(t_describe - t_read, 2),
               "graded_cloud": round(t_graded, 2), "total": round(end - t0, 2)}
    engine.add_to_summary(pair, summary, seconds, end)
    record.finish(out, summary, res, options=options, digest=run_fp.digest, resumed=resumed, seconds=seconds)
    engine.close(job, pair)
    return summary


__all__ = ["classify"]
