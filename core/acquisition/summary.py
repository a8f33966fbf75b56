"""The summary file of a simulated cloud (`OUT.summary.json` of `quakescan scan` and
`quakescan dim`): the simulator's report, the fingerprint of what made the cloud (scene
bundle, settings, seed) and the size and SHA-256 of the file written, so that a rerun
reuses the cloud only when it is the one those inputs made (`quakescan.runtime.fingerprint`)."""
from __future__ import annotations

import json
from pathlib import Path

from ..runtime.atomic import write_json
from ..runtime.fingerprint import Fingerprint, file_sha256, make, matches, scene_fingerprint


def cloud_fingerprint(kind: str, scene_dir: Path, survey, seed: int) -> Fingerprint:
    """What a simulated cloud depends on: the scene bundle's bytes, the survey and the seed
    (threads do not change the bytes)."""
    return make(kind, inputs={"scene": scene_fingerprint(scene_dir)}, settings={"survey": survey.to_json(),
                                                                              "seed": seed})


def cloud_is_up_to_date(out: Path, summary_path: Path, fp: Fingerprint) -> bool:
    """The summary holds the same fingerprint and the output is the file the run wrote (size
    and SHA-256 as recorded): a truncated or replaced output is made again."""
    if not (out.is_file() and summary_path.is_file()):
        return False
    try:
        summary = json.loads(summary_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return False
    if not matches(summary, fp):
        return False
    recorded = summary.get("output_file")
    if not isinstance(recorded, dict) or recorded.get("bytes") != out.stat().st_size:
        return False
    return recorded.get("sha256") == file_sha256(out)


def write_cloud_summary(summary_path: Path, report: dict, out: Path, fp: Fingerprint) -> None:
    """The run's `report` with what `cloud_is_up_to_date` compares a rerun against."""
    report["fingerprint"] = fp.digest
    report["output_file"] = {"bytes": out.stat().st_size, "sha256": file_sha256(out)}
    write_json(summary_path, report)


__all__ = ["cloud_fingerprint", "cloud_is_up_to_date", "write_cloud_summary"]
