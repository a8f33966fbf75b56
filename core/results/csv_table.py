"""`buildings.csv`: one line per building, and the fields of a row that the GeoJSON shares.
"""
from __future__ import annotations

import csv
import math
import re
from pathlib import Path

from ..errors import ResultsError, check_input_file
from ..runtime.atomic import open_replacing
from .building_result import BuildingResult, in_id_order

_FIXED = ["building_id", "assessable", "predicted_grade", "label"]
_TAIL = ["share_changed", "n_pre", "n_post", "decided_by", "reason"]
# Columns added after the first files: written after all others, optional on reading, so
# readers that look columns up by name (quakescan.results.evaluation, read_csv) take old and new files.
_ADDED = ["confidence", "grade_name", "detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved",
          "min_wall_opening_m2"]


def _fmt(v: float | None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return format(float(v), ".6g")


_FLOATS = ("share_changed", "min_opening_m2", "min_lowering_m", "min_wall_opening_m2")  # written with `_fmt`, empty when None


def csv_columns(classes) -> list[str]:
    return _FIXED + [f"p_{int(c)}" for c in classes] + _TAIL + _ADDED


def result_fields(r: BuildingResult, classes) -> dict:
    """The CSV/GeoJSON fields of a row as Python values (None = empty)."""
    ok = bool(r.assessable) and r.grade is not None
    rec = {"building_id": int(r.building_id), "assessable": ok,
           "predicted_grade": int(r.grade) if ok else None, "label": r.label}
    for c in classes:
        p = r.probabilities.get(int(c)) if ok else None
        rec[f"p_{int(c)}"] = None if p is None else float(p)
    rec.update({"share_changed": None if r.share_changed is None else float(r.share_changed),
                "n_pre": int(r.n_pre), "n_post": int(r.n_post), "decided_by": r.decided_by if ok else "",
                "reason": r.reason or "",
                "confidence": float(r.confidence) if ok and r.confidence is not None else None,
                "grade_name": r.grade_name})
    known = ok and r.min_opening_m2 is not None  # detectability of an assessed building only
    rec.update({"detectable_grade": int(r.detectable_grade) if known and r.detectable_grade is not None else None,
                "min_opening_m2": float(r.min_opening_m2) if known else None,
                "min_lowering_m": float(r.min_lowering_m) if known and r.min_lowering_m is not None else None})
    walls = known and r.walls_resolved is not None
    rec.update({"walls_resolved": (1 if r.walls_resolved else 0) if walls else None,
                "min_wall_opening_m2": float(r.min_wall_opening_m2) if walls and r.min_wall_opening_m2 is not None
                else None})
    return rec


def write_csv(rows, path, classes, own_ids: dict | None = None, raw_text: bool = False) -> None:
    """One line per building, sorted by building_id. Columns: building_id, assessable (1/0),
    predicted_grade (empty when not assessable), label, p_<grade> per model class (empty when
    not assessable), share_changed, n_pre, n_post, decided_by, reason, confidence (probability
    of the predicted grade; empty when not assessable), grade_name (EMS-98 name, quakescan.grades;
    "not assessable" without a grade), detectable_grade (the lowest of 3, 4, 5 the building's
    data resolve; empty when they resolve none, or when min_opening_m2 is empty too: unknown),
    min_opening_m2 and min_lowering_m (the smallest roof opening and lowering they resolve;
    empty when unknown: not assessable, no surface descriptors, or no comparable core point
    for the lowering), walls_resolved (1/0: whether heavy damage confined to the walls could
    show; empty when unknown) and min_wall_opening_m2 (the smallest wall hole resolved). `quakescan.results.evaluation` reads it. `own_ids`
    ({building_id: footprint ID}, for footprints whose IDs are text) adds a last column
    `footprint_id`.

    The footprint IDs are somebody else's text: one that a spreadsheet would run as a
    formula (it begins with = + - @, TAB or CR) is written with a leading single quote
    (`quakescan.runtime.text_safety.spreadsheet_cell`; `read_footprint_ids` takes it off),
    unless `raw_text` (for machine readers). Numbers, ours or a footprint's, are never
    escaped. A field holding a comma, quote, CR or LF is quoted, so no ID splits a row.
    UTF-8 whatever the locale."""
    from ..runtime.text_safety import csv_line, spreadsheet_cell, utf8_text

    classes = [int(c) for c in classes]
    with open_replacing(path, "w", encoding="utf-8", newline="") as f:
        f.write(csv_line(csv_columns(classes) + (["footprint_id"] if own_ids else [])))
        for r in in_id_order(rows):
            rec = result_fields(r, classes)
            line = []
            for col in csv_columns(classes):
                v = rec[col]
                if col == "assessable":
                    line.append("1" if v else "0")
                elif isinstance(v, float) or (col.startswith("p_") and v is None) or col in _FLOATS:
                    line.append(_fmt(v))
                else:
                    line.append("" if v is None else str(v))
            if own_ids:
                own = own_ids.get(int(r.building_id))
                if own is None:
                    line.append("")
                elif isinstance(own, str):
                    line.append(utf8_text(own) if raw_text else spreadsheet_cell(own))
                else:  # a number in the footprint file stays a number
                    line.append(str(own))
            f.write(csv_line(line))


def read_csv_rows(path, error=None, what: str = "file") -> tuple[list, list[dict]]:
    """(column names, rows as dicts) of a CSV table; a missing or unreadable file raises
    `error` (default ResultsError) naming the file as `what` ("result file", "truth file")."""
    error = error or ResultsError
    path = Path(path)
    check_input_file(path, what, error)  # a FIFO would block the read, a device never end it
    try:
        # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte order mark, which is not
        # part of the first column's name
        with open(path, encoding="utf-8-sig", newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            return list(reader.fieldnames or []), rows
    except FileNotFoundError:
        raise error(f"{path}: {what} does not exist") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise error(f"{path}: cannot read as a CSV table ({e})") from None


def read_footprint_ids(path) -> dict:
    """{building_id: footprint ID} of a buildings.csv with a `footprint_id` column (empty
    without one), each ID as the footprint file holds it: the single quote `write_csv` puts
    before a text a spreadsheet would run as a formula is taken off."""
    from ..runtime.text_safety import spreadsheet_raw

    path = Path(path)
    cols, data = read_csv_rows(path, what="result file")
    if "footprint_id" not in cols:
        return {}
    try:
        return {int(d["building_id"]): spreadsheet_raw(d["footprint_id"]) for d in data if d["footprint_id"]}
    except (ValueError, TypeError) as e:
        raise ResultsError(f"{path}: building_id must be an integer ({e})") from None


def read_csv(path) -> list[BuildingResult]:
    """BuildingResults from a CSV that `write_csv` wrote (files without the later columns,
    `_ADDED`, too: those fields stay empty)."""
    path = Path(path)
    cols, data = read_csv_rows(path, what="result file")
    missing = [c for c in _FIXED + _TAIL if c not in cols]
    if missing:
        raise ResultsError(f"{path}: missing columns {missing} (has {cols})")
    pcols = {c: int(c[2:]) for c in cols if re.fullmatch(r"p_\d+", c)}
    out = []
    for i, d in enumerate(data, start=2):
        try:
            ok = d["assessable"].strip() == "1"
            g = d["predicted_grade"].strip()
            probs = {k: float(d[c]) for c, k in pcols.items() if d[c].strip()} if ok else {}
            share = d["share_changed"].strip()
            conf = (d.get("confidence") or "").strip()
            resolved, opening, lowering, walls, wall_opening = (
                (d.get(c) or "").strip() for c in
                ("detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved", "min_wall_opening_m2"))
            out.append(BuildingResult(int(d["building_id"]), int(d["n_pre"]), int(d["n_post"]), ok,
                                      d["reason"], int(g) if ok and g else None, probs,
                                      float(share) if share else None, d["decided_by"],
                                      float(conf) if ok and conf else None,
                                      int(resolved) if ok and resolved else None,
                                      float(opening) if ok and opening else None,
                                      float(lowering) if ok and lowering else None,
                                      (walls == "1") if ok and walls else None,
                                      float(wall_opening) if ok and wall_opening else None))
        except (ValueError, AttributeError) as e:
            raise ResultsError(f"{path}: line {i}: {e}") from None
    return out


__all__ = ["csv_columns", "read_csv", "read_csv_rows", "read_footprint_ids", "result_fields", "write_csv"]
