"""The summary file of a simulated cloud (`OUT.summary.json` of `quakescan acquire`, `scan`
and `dim`): the sensor's report, the settings it flew with, and the fingerprint and the
output's size and SHA-256 from the cloud's record (`quakescan.acquisition.acquire`, whose record,
not this file, decides whether a rerun reuses the cloud)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from ..runtime.atomic import write_json
from .acquire import Acquired, Acquisition


def settings_key(acquisition: Acquisition) -> str:
    """Where the summary keeps the settings: the sensor's name for them ("survey", "photo_survey")."""
    return acquisition.sensor.settings_name.replace(" ", "_")


def write_summary(summary_path: Path, acquired: Acquired, acquisition: Acquisition) -> None:
    """The report of a cloud just acquired, with the settings and what its record keeps of the file."""
    settings = acquisition.settings
    report = dict(acquired.record["summary"])
    report[settings_key(acquisition)] = (settings.to_json() if hasattr(settings, "to_json")
                                         else dataclasses.asdict(settings))
    report["fingerprint"] = acquired.record["fingerprint"]
    report["output_file"] = acquired.record["output_file"]
    write_json(summary_path, report)


__all__ = ["settings_key", "write_summary"]
