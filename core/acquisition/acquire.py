"""Acquisitions: which sensor flew, with which settings — the one seam where simulated
training data varies the sensor the way real pre/post pairs do.

An `Acquisition` is a sensor kind and the full settings that kind uses; the kinds and
what each needs are those of the sensor registry `quakescan.acquisition.sensors` (built in:
`uls` and `als`, a `quakescan.acquisition.survey.Survey`; `dim`, a
`quakescan.acquisition.dim_settings.PhotoSurvey`). `acquire` runs one on a scene,
resumably; `random_acquisition` draws one for the training set from the ranges its sensor
documents (`quakescan.acquisition.sensor_lidar`, `quakescan.acquisition.sensor_dim`); the
density of an epoch and a sparser copy of it are `quakescan.acquisition.density`'s.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import PointCloudError, QuakeScanError, SurveyError
from ..formats.scene import Scene, read_scene
from ..runtime.atomic import write_json
from ..runtime.fingerprint import Fingerprint, make, scene_fingerprint
from ..runtime.progress import ProgressCallback
from . import sensors

log = logging.getLogger(__name__)

FORMAT = "quakescan-acquisition"
VERSION = 1
RECORD_FORMAT = "quakescan-acquisition-record"
SIDECAR_SUFFIX = ".acquisition.json"


def __getattr__(name):
    # KINDS follows the registry: a sensor registered after this module was imported is in it.
    if name == "KINDS":
        return sensors.kinds()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")



@dataclass(frozen=True)
class Acquisition:
    """A sensor kind (one of `quakescan.acquisition.sensors.kinds()`) and the full settings it flies with."""

    kind: str
    settings: object

    def __post_init__(self):
        sensors.check_settings(self.kind, self.settings)

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'uls 80m 300kHz noise 0.020 mis 0.030'."""
        return sensors.get(self.kind).label(self.settings)

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "kind": self.kind, "label": self.label,
                "settings": dataclasses.asdict(self.settings)}

    @classmethod
    def from_json(cls, data, source: str = "acquisition") -> Acquisition:
        """The acquisition of a `to_json` document (the label is ignored: it is derived)."""
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise SurveyError(f"{source}: not an acquisition (format must be {FORMAT!r})")
        if data.get("version") != VERSION:
            raise SurveyError(f"{source}: acquisition version {data.get('version')!r} not supported "
                              f"(expected {VERSION})")
        try:
            sensor = sensors.get(data.get("kind"))
        except SurveyError as e:
            raise SurveyError(f"{source}: {e}") from None
        values = data.get("settings")
        if not isinstance(values, dict):
            raise SurveyError(f"{source}: 'settings' must be an object of survey fields")
        return cls(sensor.kind, sensor.from_values(values, source))


def random_acquisition(kind: str, rng) -> Acquisition:
    """An acquisition of `kind` with settings drawn from the ranges its sensor documents.

    `rng` is a numpy Generator or a seed; the same seed gives the same acquisition. Values
    are rounded to a resolution that matters (0.1 m, 0.1 mm, 1 kHz, …) so labels and
    sidecars stay readable."""
    sensor = sensors.get(kind)
    return Acquisition(kind, sensor.draw(np.random.default_rng(rng)))


# Acquiring ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Acquired:
    """What `acquire` made (or found): the cloud, its sidecar's record, and whether the
    cloud was already there (`resumed`: nothing was simulated)."""

    path: Path
    record: dict
    resumed: bool


def sidecar_path(out_path: str | os.PathLike) -> Path:
    """OUT.acquisition.json beside the cloud OUT."""
    out = Path(out_path)
    return out.with_name(out.name + SIDECAR_SUFFIX)


def _record(acquisition: Acquisition, seed: int, scene_source: str, fingerprint: str) -> dict:
    return {"format": RECORD_FORMAT, "version": 1, "acquisition": acquisition.to_json(), "seed": seed,
            "scene": {"source": scene_source, "fingerprint": fingerprint}, "quakescan_version": __version__}


def _fingerprint(record: dict) -> Fingerprint:
    """What an acquisition record says the cloud depends on: its kind, settings and seed, the
    scene and the QuakeScan that made it (not the label, summary or the scene's path)."""
    return make("acquisition", inputs={"scene": record["scene"]["fingerprint"]},
                settings={"kind": record["acquisition"]["kind"], "settings": record["acquisition"]["settings"],
                          "seed": record["seed"]},
                code={"record": record["format"], "quakescan": record.get("quakescan_version")})


def _same_acquisition(old: dict, new: dict) -> bool:
    try:
        return _fingerprint(old).digest == _fingerprint(new).digest
    except (KeyError, TypeError):  # a record of another format or edited
        return False


def _same_size(record: dict, out: Path) -> bool:
    """The cloud is the size its record says: a cut or replaced one is acquired again (a record
    written before sizes were recorded: its settings decide)."""
    size = out.stat().st_size
    return record.get("output_bytes", size) == size


def _read_record(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def acquire(scene: str | os.PathLike | Scene, acquisition: Acquisition, out_path: str | os.PathLike,
            seed: int = 0, workers: int = -1, progress: ProgressCallback | None = None) -> Acquired:
    """Acquire `scene` (a bundle folder or a Scene) with `acquisition` into `out_path`
    (.las/.laz) with its sensor (`quakescan.acquisition.sensors.simulate`).

    Resumable (`quakescan.runtime.fingerprint`'s rule): when `out_path` exists with the size and its
    sidecar OUT.acquisition.json records the same acquisition, seed, scene (fingerprint) and
    QuakeScan version, nothing is simulated.
    Atomic: the cloud appears under its name only when complete, and its sidecar only
    after it (a stale sidecar is removed first), so an interrupted run is redone, never
    half-used."""
    if not isinstance(acquisition, Acquisition):
        raise QuakeScanError(f"acquire: acquisition must be an Acquisition (kind one of {sensors.kinds()}), "
                             f"got {type(acquisition).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise QuakeScanError(f"acquire: seed must be an integer >= 0, got {seed!r}")
    out = Path(out_path)
    if out.suffix.lower() not in (".las", ".laz"):
        raise PointCloudError(f"{out}: output must end in .las or .laz")
    source = "scene object" if isinstance(scene, Scene) else str(scene)
    record = _record(acquisition, int(seed), source, scene_fingerprint(scene))
    sidecar = sidecar_path(out)
    old = _read_record(sidecar) if out.is_file() and sidecar.is_file() else None
    if old is not None and _same_acquisition(old, record) and _same_size(old, out):
        log.info("%s: up to date (%s, seed %d)", out, acquisition.label, seed)
        return Acquired(out, old, True)
    sidecar.unlink(missing_ok=True)
    loaded = scene if isinstance(scene, Scene) else read_scene(scene)
    summary = sensors.simulate(acquisition.kind, loaded, acquisition.settings, out, seed=int(seed),
                               workers=workers, progress=progress, source=source)
    record["summary"] = summary.to_json()
    record["output_bytes"] = out.stat().st_size  # a cut or replaced cloud is acquired again
    write_json(sidecar, record, ensure_ascii=False)
    log.info("%s: %s, seed %d, %d points in %.1f s", out, acquisition.label, seed, summary.points,
             summary.wall_time_s)
    return Acquired(out, record, False)


__all__ = ["KINDS", "Acquired", "Acquisition", "acquire", "random_acquisition", "scene_fingerprint", "sidecar_path"]
