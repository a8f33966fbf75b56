"""The sensor registry: every simulated sensor a scene can be acquired with, by kind name,
and `simulate`, the one call that runs any of them.

Built in: `uls` and `als` (laser scanning, `quakescan.acquisition.sensor_lidar`) and `dim` (dense image
matching of a photo flight, `quakescan.acquisition.sensor_dim`). Everything that acquires a scene
reaches a sensor only through this registry and `quakescan.acquisition.acquire` (the cloud's record
and its resume rule, random draws, hence the training set): the commands `quakescan acquire
--kind K`, `scan` and `dim`, `quakescan.studies.experiment`, `quakescan.studies.robustness` and
`quakescan.demo`. What only some sensors have (a cost estimate before the run, a checkpoint
an interrupted run continues from) are optional hooks of their `Sensor`, used by `acquire`
for any kind that has them.

A new sensor is one module that calls `register(Sensor(...))` when it is imported, and
its module name added to `BUILTIN` (the one place that imports the built-in sensors; a
sensor defined elsewhere registers when its module is imported). The `Sensor` it
registers provides:

- `kind`: its name (lower-case letters, digits, '-' and '_'), unique. It is stored in
  acquisition documents and sidecars and names clouds of the training set.
- `settings`: the class of everything the sensor flies with: a frozen dataclass whose
  fields all have defaults and are JSON values (`dataclasses.asdict` goes into the sidecar
  and comes back through `quakescan.runtime.settings_file.from_values`), that validates itself on
  construction (a bad value raises `quakescan.errors.SurveyError`) and has `replace(**changes)`.
- `settings_name`: what messages call those settings ("survey", "photo survey").
- `simulate(scene, settings, out_path, *, seed, workers, progress, source)`: writes the
  epoch point cloud of the `quakescan.formats.scene.Scene` to `out_path` (.las or .laz) under the
  contract of `quakescan.formats.pointcloud` (LAS 1.4 point format 6, 1 mm scale, offset
  `quakescan.acquisition.las_output.las_offset`, extra dimensions building_id, grade and surface of the face
  a point lies on): writing through `quakescan.formats.pointcloud.LasChunkWriter` gives all of it and
  makes the file appear only when complete. The same scene, settings and seed give the same
  bytes whatever `workers` (worker threads, -1: every core); `progress` is None or a
  `quakescan.runtime.progress.ProgressCallback`, called with (done, total); `source` names
  the scene in messages. It raises
  `quakescan.errors.SceneError` or `SurveyError` when it cannot acquire the scene (nothing to
  see, no points) and returns a summary with `points` (int), `wall_time_s` (float) and
  `to_json()` (a JSON object, kept in the sidecar).
- `preset(name)`: named settings (`SurveyError` for an unknown name); `default_preset`
  names the settings used when none are given.
- `label(settings)`: a one-line description ("uls 80m 300kHz noise 0.020 mis 0.030").
- optional `load(spec)`: a preset name or the path of the sensor's JSON settings file
  (without it only preset names are understood);
- optional `random(rng)`: settings drawn from a numpy Generator for the training set
  (`quakescan.acquisition.acquire.random_acquisition`); the same generator state gives the same
  settings. The built-in sensors draw the flight-line direction first
  (`LINE_DIRECTION_DEG`), then their own values.
- optional `estimate(scene, settings, out_path)`: what the run will cost, before it runs,
  from the plan alone: an object with `describe()` (one line), `points`, `megabytes`,
  `large` (announced before it starts) and `too_large` (refused unless forced)
  (`quakescan acquire --dry-run` prints it).
- optional `checkpoint(out_path)`: the folder beside the output where the sensor keeps the
  finished part of a run; with it `simulate` also takes `checkpoint` (that folder, or None
  for none) and `fingerprint` (the digest of what is acquired, `acquire`'s), and a rerun of
  the same acquisition continues from the folder, writing the same bytes as an
  uninterrupted run, and removes it when the output is complete.
"""
from __future__ import annotations

import importlib
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import QuakeScanError, SurveyError
from ..runtime import settings_file
from ..runtime.progress import ProgressCallback

# Modules (of this package) that register the built-in sensors, in the order of `kinds()`.
BUILTIN = ("sensor_lidar", "sensor_dim")

# Flight-line direction of every built-in sensor's random settings (deg): lines are planned
# along a block's long axis, not along a building's, so which facades a strip sees differs
# from flight to flight.
LINE_DIRECTION_DEG = (0.0, 180.0)

_KIND = re.compile(r"^[a-z0-9][a-z0-9_-]*$")


@dataclass(frozen=True)
class Sensor:
    """What a simulated sensor provides (see the module docstring)."""

    kind: str
    settings: type
    simulate: Callable[..., Any]
    preset: Callable[[str], Any]
    label: Callable[[Any], str]
    default_preset: str = "paper"
    settings_name: str = "settings"
    load: Callable[[str | os.PathLike], Any] | None = None
    random: Callable[[Any], Any] | None = None
    estimate: Callable[..., Any] | None = None
    checkpoint: Callable[[Path], Path] | None = None

    def default(self):
        """The settings used when none are given: preset `default_preset`."""
        return self.preset(self.default_preset)

    def load_settings(self, spec: str | os.PathLike):
        """A preset name or (when the sensor reads files) the path of a settings file."""
        return self.load(spec) if self.load is not None else self.preset(str(spec))

    def from_values(self, values: dict, source: str):
        """The settings of a dict of (some of) their fields, as stored in a sidecar."""
        return settings_file.from_values(values, cls=self.settings, kind=self.settings_name, preset=self.preset,
                                         source=source)

    def draw(self, rng):
        """Random settings for the training set, from a numpy Generator."""
        if self.random is None:
            raise SurveyError(f"sensor {self.kind!r} has no random settings (it registered no `random`)")
        return self.random(rng)


_SENSORS: dict[str, Sensor] = {}
_builtins_loaded = False


def _load_builtins() -> None:
    # Imported on first use, not with this module: the sensor modules import numba and
    # Embree bindings, and they import this module to register.
    global _builtins_loaded
    if not _builtins_loaded:
        for name in BUILTIN:
            importlib.import_module(f".{name}", __package__)
        _builtins_loaded = True


def register(sensor: Sensor) -> Sensor:
    """Add `sensor` under its kind; a kind is registered once."""
    if not isinstance(sensor, Sensor):
        raise QuakeScanError(f"register: expected a Sensor, got {type(sensor).__name__}")
    if not isinstance(sensor.kind, str) or not _KIND.match(sensor.kind):
        raise QuakeScanError(f"register: a sensor kind is lower-case letters, digits, '-' and '_', "
                             f"got {sensor.kind!r}")
    if sensor.kind in _SENSORS:
        raise QuakeScanError(f"register: sensor kind {sensor.kind!r} is already registered")
    _SENSORS[sensor.kind] = sensor
    return sensor


def unregister(kind: str) -> None:
    """Remove the sensor `kind` (a sensor registered for a while, as in tests)."""
    _SENSORS.pop(kind, None)


def kinds() -> tuple[str, ...]:
    """The registered kinds, built-in ones first."""
    _load_builtins()
    return tuple(_SENSORS)


def get(kind: str) -> Sensor:
    """The sensor registered as `kind`; SurveyError naming the known kinds otherwise."""
    _load_builtins()
    sensor = _SENSORS.get(kind) if isinstance(kind, str) else None
    if sensor is None:
        raise SurveyError(f"acquisition kind must be one of {kinds()}, got {kind!r}")
    return sensor


def check_settings(kind: str, settings) -> Sensor:
    """The sensor `kind`, after checking that `settings` are its settings class."""
    sensor = get(kind)
    if not isinstance(settings, sensor.settings):
        raise SurveyError(f"a {kind!r} acquisition needs a {sensor.settings.__name__}, "
                          f"got {type(settings).__name__}")
    return sensor


def simulate(kind: str, scene, settings, out_path: str | os.PathLike, seed: int = 0, workers: int = -1,
             progress: ProgressCallback | None = None, source: str = "scene",
             checkpoint: str | os.PathLike | None = None, fingerprint: str = ""):
    """Acquire the Scene `scene` with the sensor `kind` and `settings` into `out_path`;
    returns the sensor's summary. `checkpoint` and `fingerprint` as the sensor's `checkpoint`
    hook says (a checkpoint folder for a sensor without the hook is an error). No record and
    no resuming of a finished cloud: `quakescan.acquisition.acquire.acquire` adds them."""
    sensor = check_settings(kind, settings)
    resume = {}
    if checkpoint is not None:
        if sensor.checkpoint is None:
            raise QuakeScanError(f"sensor {kind!r} keeps no checkpoint (it registered no `checkpoint`)")
        resume = {"checkpoint": checkpoint, "fingerprint": fingerprint}
    return sensor.simulate(scene, settings, out_path, seed=seed, workers=workers, progress=progress, source=source,
                           **resume)


# Draws of random settings ------------------------------------------------------------

def uniform(rng, lo_hi: tuple[float, float], digits: int) -> float:
    """A uniform draw in lo_hi, rounded to `digits` decimals."""
    return round(float(rng.uniform(*lo_hi)), digits)


def log_uniform(rng, lo_hi: tuple[float, float], digits: int) -> float:
    """A log-uniform draw in lo_hi (for rates and densities, whose effects are
    multiplicative), rounded to `digits` decimals."""
    lo, hi = lo_hi
    return round(float(math.exp(rng.uniform(math.log(lo), math.log(hi)))), digits)


__all__ = ["BUILTIN", "LINE_DIRECTION_DEG", "Sensor", "check_settings", "get", "kinds", "log_uniform", "register",
           "simulate", "uniform", "unregister"]
