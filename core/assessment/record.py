"""A classification's folder and record, whichever engine describes its rows: the output
folder claimed, the run's options and fingerprint, the up-to-date test, the tiles'
checkpoint, the rows of footprints without points, the result files, and the summary
written last.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from ..change.pipeline import BuildingRow
from ..errors import ClassifyError, ResultsError, check_input_file
from ..formats.pointcloud import epoch_order_warning
from ..learning.default_model import default_model_path
from ..runtime import fingerprint, output_folder
from ..runtime.atomic import (
    check_output_name,
    is_write_failure,
    remove_stale_temporaries,
    write_failure_message,
    write_json,
    write_text,
)
from ..runtime.text_safety import json_text

log = logging.getLogger(__name__)

def warn_of_epoch_order(pre_path, post_path, summary: dict) -> None:
    """Say so (on the console and in the summary's "warnings") when the files date the
    post-event epoch before the pre-event one (`epoch_order_warning`)."""
    warning = epoch_order_warning(pre_path, post_path)
    if warning:
        log.warning("%s", warning)
        summary.setdefault("warnings", []).append(warning)


def run_fingerprint(pre_path, post_path, footprints_path, model_path, align: bool | None, options: dict):
    """What a classification depends on (`quakescan.runtime.fingerprint`): the clouds by path, size and time
    (gigabytes: hashing them would cost more than many reruns), the footprints and the model
    by content, the alignment mode and the output options."""
    inputs = {"pre": fingerprint.stat(pre_path), "post": fingerprint.stat(post_path),
              "footprints": fingerprint.content(footprints_path), "model": fingerprint.content(model_path)}
    return fingerprint.make("classify", inputs=inputs, settings={"align": align, **options})


def run_options(id_field, write_las: bool, laz, unseen_damage: bool, prior: dict | None,
                csv_raw: bool = False) -> dict:
    """The options of a classify run that its results depend on (its fingerprint's, the
    summary's), for one process and the Dask path alike."""
    options = {"id_field": id_field, "write_las": bool(write_las), "laz": laz}
    if not unseen_damage:  # only a departure from the defaults enters the fingerprint, so results stay current
        options["unseen_damage"] = False
    if csv_raw:
        options["csv_raw"] = True
    if prior is not None:
        options["prior"] = {str(int(g)): float(v) for g, v in sorted(prior.items())}
    return options


MAP_POINTS = 200_000  # pre-event points drawn under the damage map


def map_step(n: int) -> int:
    """Every k-th pre-event point is drawn under the damage map."""
    return max(1, n // MAP_POINTS)


def write_building_results(out: Path, res, classes, fp, outlines, crs, map_xy, title: str,
                           csv_raw: bool = False) -> None:
    """buildings.csv, .geojson, .qml, damage_map.png and .html of graded buildings (also a
    distributed run's, `quakescan.distributed`): `map_xy` the world x/y drawn under the map;
    `csv_raw`: footprint IDs unescaped in the CSV (`write_csv`'s `raw_text`)."""
    from ..results.csv_table import write_csv
    from ..results.geojson import write_geojson
    from ..results.png_map import write_map_png
    from ..results.qgis_style import write_qml
    from ..results.webmap import write_map_html

    own = fp.own_ids() if fp is not None else None
    write_csv(res, out / "buildings.csv", classes, own_ids=own, raw_text=csv_raw)
    attributes = (fp.attributes() or None) if fp is not None else None
    write_geojson(res, outlines, out / "buildings.geojson", crs, classes, attributes)
    write_qml(out / "buildings.qml")
    write_map_png(res, outlines, out / "damage_map.png", title, points_xy=map_xy, crs=crs)
    write_map_html(res, outlines, out / "damage_map.html", title, crs, classes, own_ids=own)


def counts_by_grade_name(res) -> dict:
    """{"0 no damage": n, "3 substantial to heavy (heavy)": n, ..., "not assessable": n} in
    grade order: what the CLI prints (quakescan.grades)."""
    from ..grades import long_label
    from ..results.building_result import NOT_ASSESSABLE

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


def finished_summary(out: Path, fp) -> dict | None:
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


def json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


class RowCheckpoint:
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


def begin(pre_path, post_path, out, *, model_path, footprints_path, align: bool | None, options: dict,
          force: bool):
    """A run's start in its claimed folder, one process or Dask: (the model file, the run's
    fingerprint, the summary of finished results of the same run or None). Unless `force`,
    a caller given a summary returns it: the folder is up to date."""
    model_path = Path(model_path) if model_path else default_model_path()
    check_input_file(model_path, "model file", ClassifyError)  # the inputs given were checked with the folder
    run_fp = run_fingerprint(pre_path, post_path, footprints_path, model_path, align, options)
    done = finished_summary(out, run_fp)
    return model_path, run_fp, (None if force or done is None else {**done, "up_to_date": True})


def footprint_rows(fp, rows, without_points) -> list:
    """The rows of the footprints the described `rows` lack: each of `without_points`
    (`footprints_without_points`), and each the footprints file could not use, with its
    reason. The building stays in the results, not assessable."""
    if fp is None:
        return []
    out = [BuildingRow(int(b), 0, 0, False, "no point inside the footprint") for b in without_points]
    described = {r.building_id for r in rows} | {r.building_id for r in out}
    return out + [BuildingRow(int(b), 0, 0, False, why) for b, why, _ in fp.rejected if int(b) not in described]


def graded_cloud_path(out: Path, post_path, laz: bool | None) -> Path:
    """post_grades.laz when `laz`, or when `laz` is None and the post-event file is LAZ; else .las."""
    compress = Path(post_path).suffix.lower() == ".laz" if laz is None else laz
    return out / ("post_grades.laz" if compress else "post_grades.las")


def run_summary(pre_path, post_path, model_path, model, settings, points: dict, noise_points: dict, crs) -> dict:
    """The summary's head: inputs, the model and its settings, the points read."""
    summary = {"pre": str(pre_path), "post": str(post_path), "model": str(model_path),
               "model_provenance": model.provenance, "settings": settings.to_json(), "points": points,
               "noise_points": noise_points, "crs": crs}
    warn_of_epoch_order(pre_path, post_path, summary)
    return summary


def finish(out: Path, summary: dict, res, *, options: dict, digest: str, resumed: int, seconds: dict) -> dict:
    """The summary's tail (the buildings by label and grade, their detectability, the
    seconds, the fingerprint and the files written), written last: a folder holds a summary
    only over finished results."""
    counts: dict[str, int] = {}
    for r in res:
        counts[r.label] = counts.get(r.label, 0) + 1
    summary.update({"buildings": len(res), "by_label": counts, "by_grade_name": counts_by_grade_name(res),
                    "detectability": detectability_counts(res), "resumed_buildings": resumed,
                    "seconds": seconds, "fingerprint": digest, "options": options})
    summary["outputs"] = result_names(summary)
    warn_of_foreign_results(out, summary)
    write_text(out / "summary.json", json_text(summary, indent=1, default=json_default))  # strict: NaN is null
    return summary
