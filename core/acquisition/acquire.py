"""Acquisitions: which sensor flew, with which settings — the one seam where simulated
training data varies the sensor the way real pre/post pairs do — and `acquire`, the one
way a scene becomes a simulated cloud.

An `Acquisition` is a sensor kind and the full settings that kind uses; the kinds and
what each needs are those of the sensor registry `quakescan.acquisition.sensors` (built in:
`uls` and `als`, a `quakescan.acquisition.survey.Survey`; `dim`, a
`quakescan.acquisition.dim_settings.PhotoSurvey`). `acquire` runs one on a scene,
resumably; `random_acquisition` draws one for the training set from the ranges its sensor
documents (`quakescan.acquisition.sensor_lidar`, `quakescan.acquisition.sensor_dim`); the
density of an epoch and a sparser copy of it are `quakescan.acquisition.density`'s.

The resume rule of a simulated cloud (`quakescan.runtime.fingerprint`'s, for every caller:
the commands `acquire`, `scan` and `dim`, the library, the demo, the training set and the
studies): beside the cloud OUT, its record OUT.acquisition.json holds the fingerprint of
what made it (sensor kind, settings, seed, the scene's fingerprint, the record's format and
QuakeScan's version) and the size and SHA-256 of the file written. A rerun reuses the
cloud only when the fingerprint is the one it would record now and the file is still the
one recorded (`reusable_record`); a cut, replaced or differently made cloud is acquired
again.
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
from ..runtime.fingerprint import Fingerprint, file_sha256, make, matches, scene_fingerprint
from ..runtime.progress import ProgressCallback
from . import sensors

log = logging.getLogger(__name__)

FORMAT = "quakescan-acquisition"
VERSION = 1
RECORD_FORMAT = "quakescan-acquisition-record"
RECORD_VERSION = 2
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
    def sensor(self) -> sensors.Sensor:
        return sensors.get(self.kind)

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'uls 80m 300kHz noise 0.020 mis 0.030'."""
        return self.sensor.label(self.settings)

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


# The record beside a cloud and the resume rule ---------------------------------------

def sidecar_path(out_path: str | os.PathLike) -> Path:
    """OUT.acquisition.json beside the cloud OUT."""
    out = Path(out_path)
    return out.with_name(out.name + SIDECAR_SUFFIX)


def cloud_fingerprint(acquisition: Acquisition, seed: int, scene_digest: str) -> Fingerprint:
    """What a simulated cloud depends on: the sensor kind, its settings and the seed, the
    scene (`quakescan.runtime.fingerprint.scene_fingerprint`), the record's format and QuakeScan's
    version (not the label, the summary, the threads or where the scene was read from)."""
    return make("acquisition", inputs={"scene": scene_digest},
                settings={"kind": acquisition.kind, "settings": dataclasses.asdict(acquisition.settings),
                          "seed": int(seed)},
                code={"record": RECORD_FORMAT, "record_version": RECORD_VERSION})


def _read_record(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def reusable_record(out_path: str | os.PathLike, fp: Fingerprint) -> dict | None:
    """The record of the cloud `out_path` when a rerun may reuse the cloud: the record beside
    it holds `fp` and the cloud is the file the run wrote (size and SHA-256 as recorded);
    None otherwise (no cloud, no readable record, other inputs or settings, a cut or
    replaced cloud), and the cloud is acquired again."""
    out = Path(out_path)
    sidecar = sidecar_path(out)
    if not (out.is_file() and sidecar.is_file()):
        return None
    record = _read_record(sidecar)
    if not matches(record, fp):
        return None
    recorded = record.get("output_file")
    if not isinstance(recorded, dict) or recorded.get("bytes") != out.stat().st_size:
        return None
    return record if recorded.get("sha256") == file_sha256(out) else None


# Acquiring ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Acquired:
    """What `acquire` made (or found): the cloud, its sidecar's record, and whether the
    cloud was already there (`resumed`: nothing was simulated); `summary` is the sensor's
    summary of a cloud simulated now (None when resumed: the record keeps its JSON)."""

    path: Path
    record: dict
    resumed: bool
    summary: object = None


@dataclass(frozen=True)
class PlannedAcquisition:
    """An acquisition of a loaded scene into `out`, before it runs (`plan`): its fingerprint,
    the record of a cloud already there that a rerun may reuse, and the sensor's estimate of
    what it will cost (`estimate`)."""

    scene: Scene
    source: str
    acquisition: Acquisition
    out: Path
    seed: int
    fingerprint: Fingerprint
    reusable: dict | None

    @property
    def sidecar(self) -> Path:
        return sidecar_path(self.out)

    @property
    def checkpoint(self) -> Path | None:
        """Where the sensor keeps the finished part of an interrupted run (None: it keeps none)."""
        hook = self.acquisition.sensor.checkpoint
        return None if hook is None else Path(hook(self.out))

    def estimate(self):
        """The sensor's estimate of the run's cost (None: the sensor has no `estimate`)."""
        hook = self.acquisition.sensor.estimate
        return None if hook is None else hook(self.scene, self.acquisition.settings, self.out)

    def run(self, workers: int = -1, progress: ProgressCallback | None = None,
            checkpoint: bool = False) -> Acquired:
        """Simulate the cloud (whatever is there) and write its record after it.

        `checkpoint`: keep the finished part in the sensor's checkpoint folder (when it has
        one), from which a rerun after an interruption continues, writing the same bytes."""
        acq = self.acquisition
        self.sidecar.unlink(missing_ok=True)  # a cloud without its record is acquired again, never trusted
        folder = self.checkpoint if checkpoint else None
        summary = sensors.simulate(acq.kind, self.scene, acq.settings, self.out, seed=self.seed, workers=workers,
                                   progress=progress, source=self.source, checkpoint=folder,
                                   fingerprint=self.fingerprint.digest)
        record = {"format": RECORD_FORMAT, "version": RECORD_VERSION, "acquisition": acq.to_json(),
                  "seed": self.seed, "scene": {"source": self.source, "fingerprint": self.fingerprint.inputs["scene"]},
                  "quakescan_version": __version__, "fingerprint": self.fingerprint.digest,
                  "summary": summary.to_json(),
                  "output_file": {"bytes": self.out.stat().st_size, "sha256": file_sha256(self.out)}}
        write_json(self.sidecar, record, ensure_ascii=False)
        log.info("%s: %s, seed %d, %d points in %.1f s", self.out, acq.label, self.seed, summary.points,
                 summary.wall_time_s)
        return Acquired(self.out, record, False, summary)


def plan(scene: str | os.PathLike | Scene, acquisition: Acquisition, out_path: str | os.PathLike,
         seed: int = 0, reuse: bool = True) -> PlannedAcquisition:
    """The acquisition of `scene` (a bundle folder, which is read, or a Scene) into
    `out_path` (.las/.laz), checked and fingerprinted, not run (see `acquire`). `reuse`
    False: a cloud already there is not looked at (`reusable` None), so a forced run does not
    hash the file it replaces."""
    if not isinstance(acquisition, Acquisition):
        raise QuakeScanError(f"acquire: acquisition must be an Acquisition (kind one of {sensors.kinds()}), "
                             f"got {type(acquisition).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise QuakeScanError(f"acquire: seed must be an integer >= 0, got {seed!r}")
    out = Path(out_path)
    if out.suffix.lower() not in (".las", ".laz"):
        raise PointCloudError(f"{out}: output must end in .las or .laz")
    source = "scene object" if isinstance(scene, Scene) else str(scene)
    loaded = scene if isinstance(scene, Scene) else read_scene(scene)
    fp = cloud_fingerprint(acquisition, int(seed), scene_fingerprint(loaded))
    return PlannedAcquisition(loaded, source, acquisition, out, int(seed), fp,
                              reusable_record(out, fp) if reuse else None)


def acquire(scene: str | os.PathLike | Scene, acquisition: Acquisition, out_path: str | os.PathLike,
            seed: int = 0, workers: int = -1, progress: ProgressCallback | None = None,
            checkpoint: bool = False) -> Acquired:
    """Acquire `scene` (a bundle folder or a Scene) with `acquisition` into `out_path`
    (.las/.laz) with its sensor (`quakescan.acquisition.sensors.simulate`).

    Resumable (the module's rule): when `out_path` is the cloud its record
    OUT.acquisition.json says the same acquisition, seed, scene and QuakeScan made, nothing
    is simulated. `checkpoint` as in `PlannedAcquisition.run`.
    Atomic: the cloud appears under its name only when complete, and its record only
    after it (a stale record is removed first), so an interrupted run is redone, never
    half-used."""
    planned = plan(scene, acquisition, out_path, seed)
    if planned.reusable is not None:
        log.info("%s: up to date (%s, seed %d)", planned.out, acquisition.label, planned.seed)
        return Acquired(planned.out, planned.reusable, True)
    return planned.run(workers, progress, checkpoint)


__all__ = ["KINDS", "Acquired", "Acquisition", "PlannedAcquisition", "acquire", "cloud_fingerprint", "plan",
           "random_acquisition", "reusable_record", "sidecar_path"]
