"""Documented JSON files of a settings dataclass (the survey and the photo survey).

A file holds `format`, `version`, any subset of the dataclass's fields, optionally
`preset` (the values missing from the file are taken from it) and `_doc` (each field with
its meaning and unit, written by `to_json`, ignored on reading)."""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

from ..errors import SurveyError, read_json_file


def to_json(settings, fmt: str, version: int, field_doc: dict) -> dict:
    """The file's content: format, version, every field, and `_doc` from field_doc
    ({field: (meaning, unit)})."""
    d = {"format": fmt, "version": version}
    d.update(dataclasses.asdict(settings))
    d["_doc"] = {k: f"{text} [{unit}]" for k, (text, unit) in field_doc.items()}
    return d


def load(spec: str | os.PathLike, *, cls: type, fmt: str, version: int, kind: str,
         preset: Callable[[str], object]):
    """`spec` is a preset name (-> preset(spec)) or the path of a `kind` file; a value the
    dataclass refuses (its validate raises SurveyError "<kind>: ...") is reported against
    the file."""
    spec = str(spec)
    if not spec.endswith(".json") and not Path(spec).exists():
        return preset(spec)
    path = Path(spec)
    data = read_json_file(path, f"{kind} file", SurveyError)
    if not isinstance(data, dict) or data.get("format") != fmt:
        raise SurveyError(f"{path}: not a {kind} file (format must be {fmt!r})")
    if data.get("version") != version:
        raise SurveyError(f"{path}: {kind} version {data.get('version')!r} not supported (expected {version})")
    values = {k: v for k, v in data.items() if not k.startswith("_") and k not in ("format", "version")}
    return from_values(values, cls=cls, kind=kind, preset=preset, source=str(path))


def from_values(values: dict, *, cls: type, kind: str, preset: Callable[[str], object], source: str):
    """The dataclass from a dict of (some of) its fields and optionally `preset` (missing
    fields come from it, else from the defaults); every refusal names `source`. Shared by the
    settings files and the documents that embed settings (quakescan.acquisition.acquire)."""
    values = dict(values)
    known = {f.name for f in dataclasses.fields(cls)}
    base = preset(values.pop("preset")) if "preset" in values else cls()
    unknown = sorted(set(values) - known)
    if unknown:
        raise SurveyError(f"{source}: unknown {kind} fields {unknown}; known fields: {sorted(known)}")
    try:
        return dataclasses.replace(base, **values)
    except SurveyError as e:
        raise SurveyError(f"{source}: {str(e).removeprefix(f'{kind}: ')}") from None
    except TypeError as e:
        raise SurveyError(f"{source}: {e}") from None


def write_template(path: str | os.PathLike, content: dict) -> None:
    """The file with every field and its documentation, written whole or not at all."""
    from .atomic import write_json

    path = Path(path)
    if path.is_dir():
        raise SurveyError(f"{path}: is a folder; give the name of the JSON file to write")
    write_json(path, content, ensure_ascii=False)
