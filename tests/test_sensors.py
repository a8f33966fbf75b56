"""The sensor registry (core/acquisition/sensors.py): a sensor defined here, registered like a built-in
one, runs through `acquire` to a LAS epoch that reads back as what it sampled."""
import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass

import numpy as np
import pytest

from quakescan.acquisition import sensors
from quakescan.acquisition.acquire import Acquisition, acquire, random_acquisition, sidecar_path
from quakescan.acquisition.survey import preset
from quakescan.errors import QuakeScanError, SurveyError
from quakescan.formats.pointcloud import (BUILDING_CLASS, GROUND_CLASS, UNCLASSIFIED, LasChunkWriter, PointChunk,
                                          read_epoch)
from quakescan.formats.scene import GROUND, Scene
from quakescan.formats.synthetic import box_city

UTM = (500000.0, 5000000.0, 0.0)


@dataclass(frozen=True)
class FaceCentres:
    """Settings of the toy sensor: every `step`-th face's centroid becomes a point."""

    name: str = "centres"
    step: int = 1
    acquisition_date: str = "2021-06-01"

    def __post_init__(self):
        if not isinstance(self.step, int) or isinstance(self.step, bool) or self.step < 1:
            raise SurveyError(f"face centres: step must be an integer >= 1, got {self.step!r}")

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


@dataclass
class CentresSummary:
    output: str
    points: int
    wall_time_s: float

    def to_json(self) -> dict:
        return dict(self.__dict__)


def _centres(scene: Scene, step: int):
    faces = np.arange(0, len(scene.faces), step)
    return scene.vertices[scene.faces[faces]].mean(axis=1), faces


def simulate_centres(scene: Scene, settings: FaceCentres, out_path, *, seed, workers, progress, source):
    started = time.perf_counter()
    xyz, faces = _centres(scene, settings.step)
    building = scene.face_building[faces].astype(np.uint32)
    surface = scene.face_surface[faces].astype(np.uint8)
    cls = np.where(building > 0, BUILDING_CLASS, np.where(surface == GROUND, GROUND_CLASS, UNCLASSIFIED))
    n = len(xyz)
    with LasChunkWriter(out_path, scene.origin, scene.crs, settings.acquisition_date) as writer:
        writer.write(PointChunk(xyz=xyz, gps_time=np.zeros(n), scan_angle_deg=np.zeros(n),
                                return_number=np.ones(n, np.uint8), number_of_returns=np.ones(n, np.uint8),
                                classification=cls.astype(np.uint8), building_id=building,
                                grade=np.zeros(n, np.uint8), surface=surface,
                                point_source_id=np.ones(n, np.uint16)))
    if progress:
        progress(1, 1)
    return CentresSummary(str(out_path), n, time.perf_counter() - started)


@pytest.fixture
def centres_sensor():
    sensor = sensors.register(sensors.Sensor(
        "centres", FaceCentres, simulate_centres, preset=lambda name: FaceCentres(name=name),
        label=lambda s: f"centres every {s.step} faces", default_preset="centres", settings_name="face centres"))
    yield sensor
    sensors.unregister("centres")


def test_a_registered_sensor_acquires_a_readable_epoch_and_resumes(tmp_path, centres_sensor):
    import quakescan.acquisition.acquire

    scene = box_city(rows=1, cols=2, origin=UTM)
    assert "centres" in sensors.kinds() and "centres" in quakescan.acquisition.acquire.KINDS
    acq = Acquisition("centres", FaceCentres(step=3))
    out = tmp_path / "toy" / "centres.las"
    first = acquire(scene, acq, out, seed=2)
    assert not first.resumed and first.record["summary"]["points"] == len(scene.faces[::3])

    epoch = read_epoch(out)
    xyz, faces = _centres(scene, 3)
    # offset = scene origin (the LAS contract): the points come back at 1 mm
    assert np.array_equal(epoch.origin, np.asarray(UTM))
    assert np.abs(epoch.xyz - xyz).max() <= 0.0005 + 1e-9
    assert np.array_equal(epoch.building_id, scene.face_building[faces])
    assert np.array_equal(epoch.surface, scene.face_surface[faces])
    assert set(np.unique(epoch.classification)) == {BUILDING_CLASS, GROUND_CLASS}

    record = json.loads(sidecar_path(out).read_text())
    assert record["acquisition"]["kind"] == "centres" and record["acquisition"]["label"] == "centres every 3 faces"
    assert Acquisition.from_json(record["acquisition"]) == acq
    assert acquire(scene, acq, out, seed=2).resumed
    assert not acquire(scene, Acquisition("centres", FaceCentres(step=4)), out, seed=2).resumed
    assert len(read_epoch(out)) == len(scene.faces[::4])

    # sensors.simulate runs it without a sidecar
    summary = sensors.simulate("centres", scene, centres_sensor.default(), tmp_path / "plain.las")
    assert summary.points == len(scene.faces) and not sidecar_path(tmp_path / "plain.las").exists()


def test_a_registered_sensor_s_settings_are_checked(centres_sensor):
    with pytest.raises(SurveyError, match="a 'centres' acquisition needs a FaceCentres, got Survey"):
        Acquisition("centres", preset("paper"))
    with pytest.raises(SurveyError, match="a 'uls' acquisition needs a Survey, got FaceCentres"):
        Acquisition("uls", FaceCentres())
    doc = Acquisition("centres", FaceCentres()).to_json()
    with pytest.raises(SurveyError, match=r"a.json: step must be an integer >= 1, got 0"):
        Acquisition.from_json({**doc, "settings": {"step": 0}}, source="a.json")
    with pytest.raises(SurveyError, match="unknown face centres fields"):
        Acquisition.from_json({**doc, "settings": {"steps": 2}}, source="a.json")
    with pytest.raises(SurveyError, match="'centres' has no random settings"):
        random_acquisition("centres", 0)


def test_the_registry_refuses_duplicate_and_malformed_kinds(centres_sensor):
    with pytest.raises(QuakeScanError, match="'centres' is already registered"):
        sensors.register(centres_sensor)
    with pytest.raises(QuakeScanError, match="lower-case letters"):
        sensors.register(dataclasses.replace(centres_sensor, kind="Toy Sensor"))
    with pytest.raises(SurveyError, match=r"kind must be one of \('uls', 'als', 'dim', 'centres'\), got 'lidar'"):
        sensors.get("lidar")


def test_the_built_in_sensors_and_their_defaults():
    assert sensors.kinds()[:3] == ("uls", "als", "dim")
    assert sensors.get("uls").default() == preset("paper")
    assert sensors.get("als").default() == preset("als")
    for kind in ("uls", "als", "dim"):
        sensor = sensors.get(kind)
        default = sensor.default()
        assert sensor.load_settings(sensor.default_preset) == default
        assert sensor.from_values(dataclasses.asdict(default), "x") == default


def test_a_registered_sensor_has_one_record_and_one_resume_rule(tmp_path, centres_sensor):
    """The record beside the cloud holds the fingerprint and the file's size and SHA-256: a
    second run reuses the cloud, a truncated one is acquired again, the same bytes."""
    scene = box_city(rows=1, cols=2, origin=UTM)
    acq = Acquisition("centres", FaceCentres(step=2))
    out = tmp_path / "c.las"
    first = acquire(scene, acq, out, seed=1)
    record = json.loads(sidecar_path(out).read_text())
    data = out.read_bytes()
    assert record["output_file"] == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    assert record["fingerprint"] == first.record["fingerprint"] and first.summary.points == len(scene.faces[::2])
    again = acquire(scene, acq, out, seed=1)
    assert again.resumed and again.summary is None and again.record == record
    out.write_bytes(data[:-10])
    cut = acquire(scene, acq, out, seed=1)
    assert not cut.resumed and out.read_bytes() == data


def test_quakescan_acquire_runs_a_registered_sensor(tmp_path, capsys, centres_sensor):
    """`quakescan acquire --kind K` reaches any kind registered in the process."""
    from quakescan.cli import main
    from quakescan.formats.scene import write_scene

    scene_dir = write_scene(box_city(rows=1, cols=2, origin=UTM), tmp_path / "scene")
    out = tmp_path / "c.las"
    args = ["acquire", str(scene_dir), "--kind", "centres", "-o", str(out), "--seed", "2"]
    assert main(args + ["--dry-run"]) == 0
    assert "centres: no estimate" in capsys.readouterr().out and not out.exists()
    assert main(args) == 0
    assert f"centres: {len(read_epoch(out))} points" in capsys.readouterr().out
    summary = json.loads((tmp_path / "c.las.summary.json").read_text())
    record = json.loads(sidecar_path(out).read_text())
    assert summary["face_centres"]["name"] == "centres" and summary["output_file"] == record["output_file"]
    assert record["acquisition"]["kind"] == "centres" and record["seed"] == 2
    data = out.read_bytes()
    assert main(args) == 0
    assert "up to date (same scene, face centres and seed)" in capsys.readouterr().out
    out.write_bytes(data[:-10])
    assert main(args) == 0
    assert "up to date" not in capsys.readouterr().out and out.read_bytes() == data
    assert main(["acquire", str(scene_dir), "--kind", "nope", "-o", str(out)]) == 2
    assert "kind must be one of" in capsys.readouterr().err


@dataclass(frozen=True)
class Estimate:
    points: int
    megabytes: float = 1.0
    large_points: int = 10
    max_points: int = 1000

    @property
    def large(self):
        return self.points > self.large_points

    @property
    def too_large(self):
        return self.points > self.max_points

    def describe(self):
        return f"toy plan: {self.points} points"


def test_a_sensor_s_estimate_and_checkpoint_are_hooks_acquire_uses(tmp_path, capsys, centres_sensor):
    """A sensor with an estimate and a checkpoint registers them; `acquire` and the command use
    them for any kind, as for the built-in laser scanners."""
    from quakescan.cli import main
    from quakescan.formats.scene import write_scene

    calls = []

    def simulate(scene, settings, out_path, *, seed, workers, progress, source, checkpoint=None, fingerprint=""):
        calls.append((checkpoint, fingerprint))
        return simulate_centres(scene, settings, out_path, seed=seed, workers=workers, progress=progress,
                                source=source)

    hooked = sensors.register(dataclasses.replace(
        centres_sensor, kind="hooked", simulate=simulate,
        estimate=lambda scene, settings, out: Estimate(len(scene.faces[::settings.step])),
        checkpoint=lambda out: out.with_name(out.name + ".part-done")))
    try:
        scene_dir = write_scene(box_city(rows=1, cols=2, origin=UTM), tmp_path / "scene")
        out = tmp_path / "h.las"
        got = acquire(scene_dir, Acquisition("hooked", FaceCentres()), tmp_path / "lib.las")
        assert calls == [(None, "")] and not got.resumed  # the library keeps no checkpoint unless asked
        args = ["acquire", str(scene_dir), "--kind", "hooked", "-o", str(out)]
        assert main(args + ["--dry-run"]) == 0
        n = len(box_city(rows=1, cols=2).faces)
        assert capsys.readouterr().out == f"toy plan: {n} points\n" and not out.exists()
        assert main(args) == 0
        assert "warning: a large acquisition" in capsys.readouterr().err
        record = json.loads(sidecar_path(out).read_text())
        assert calls[-1] == (tmp_path / "h.las.part-done", record["fingerprint"])
        hooked_big = dataclasses.replace(hooked, kind="hooked-big",
                                         estimate=lambda scene, settings, out: Estimate(10_000))
        sensors.register(hooked_big)
        assert main(["acquire", str(scene_dir), "--kind", "hooked-big", "-o", str(tmp_path / "big.las")]) == 2
        assert "beyond the limit of 0 M points" in capsys.readouterr().err and not (tmp_path / "big.las").exists()
        assert main(["acquire", str(scene_dir), "--kind", "hooked-big", "-o", str(tmp_path / "big.las"),
                     "--force"]) == 0
    finally:
        sensors.unregister("hooked")
        sensors.unregister("hooked-big")
