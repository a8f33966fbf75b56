"""The one resume rule (quakescan.runtime.fingerprint) in every resumable command: an output made with the
same inputs and settings is reused, one made with other settings is made again, never reused.
(classify: tests/test_classify.py; robustness: tests/test_robustness.py; the scan checkpoint:
tests/test_scan_resume.py; generation end to end: tests/addon/test_addon_generate.py.)"""
import importlib.util
import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from quakescan.acquisition.acquire import Acquisition, acquire
from quakescan.acquisition.survey import als_for_density
from quakescan.cli import main
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city
from quakescan.runtime import fingerprint

REPO = Path(__file__).resolve().parents[1]
SMALL_SURVEY = {"format": "quakescan-survey", "version": 1, "pulse_rate_hz": 50_000.0}


class Boom(Exception):
    pass


# the rule -------------------------------------------------------------------------------------

def test_a_fingerprint_is_its_inputs_settings_and_code_in_any_order():
    a = fingerprint.make("k", inputs={"x": 1, "y": [1, 2]}, settings={"s": 0.5, "t": None})
    b = fingerprint.make("k", inputs={"y": (1, 2), "x": 1}, settings={"t": None, "s": 0.5})
    assert a.digest == b.digest
    others = [fingerprint.make("other", inputs=a.inputs, settings=a.settings),
              fingerprint.make("k", inputs={"x": 2, "y": [1, 2]}, settings=a.settings),
              fingerprint.make("k", inputs=a.inputs, settings={"s": 0.25, "t": None}),
              fingerprint.make("k", inputs=a.inputs, settings=a.settings, code={"format": 2})]
    assert len({a.digest, *(o.digest for o in others)}) == 5
    assert a.code["quakescan"]  # another QuakeScan may compute differently


def test_only_an_output_with_the_same_fingerprint_and_size_is_current(tmp_path):
    out = tmp_path / "table.npz"
    fp = fingerprint.make("table", settings={"radius": 1.0})
    made = []

    def make():
        made.append(1)
        out.write_bytes(b"rows")

    assert fingerprint.state(out, fp) == "missing"
    assert fingerprint.reuse_or_make(out, fp, make) is False
    assert fingerprint.reuse_or_make(out, fp, make) is True and len(made) == 1
    assert fingerprint.state(out, fp) == "current"
    assert fingerprint.state(out, fingerprint.make("table", settings={"radius": 2.0})) == "other"
    out.write_bytes(b"rows, cut")  # replaced or cut: redone
    assert fingerprint.state(out, fp) == "changed" and not fingerprint.is_current(out, fp)
    assert fingerprint.reuse_or_make(out, fp, make) is False and len(made) == 2
    fingerprint.forget(out)  # about to be made again: no longer current
    assert fingerprint.state(out, fp) == "unrecorded" and out.is_file()
    fingerprint.sidecar_path(out).write_text("{cut")
    assert not fingerprint.is_current(out, fp)


def test_a_file_s_identity_by_content_or_by_path_size_and_time(tmp_path):
    p = tmp_path / "a.las"
    p.write_bytes(b"abc")
    by_content, by_stat = fingerprint.content(p), fingerprint.stat(p)
    os.utime(p, ns=(1, 1))
    assert fingerprint.content(p) == by_content and fingerprint.stat(p) != by_stat
    assert fingerprint.content(None) is None and fingerprint.stat(None) is None


# scan and dim (the summary beside the cloud holds the fingerprint) ----------------------------

@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_scene(box_city(rows=1, cols=1), tmp_path_factory.mktemp("scene") / "city")


def test_scan_reuses_a_cloud_of_the_same_settings_only(tmp_path, scene_dir, capsys):
    survey = tmp_path / "survey.json"
    survey.write_text(json.dumps(SMALL_SURVEY))
    out = tmp_path / "a.las"
    args = ["scan", str(scene_dir), "-o", str(out), "--survey", str(survey), "--seed", "1"]
    assert main(args) == 0
    first = out.read_bytes()
    capsys.readouterr()
    assert main(args) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(args[:-1] + ["2"]) == 0  # another seed
    assert "up to date" not in capsys.readouterr().out and out.read_bytes() != first
    survey.write_text(json.dumps({**SMALL_SURVEY, "pulse_rate_hz": 40_000.0}))  # the same file, other settings
    assert main(args[:-1] + ["2"]) == 0
    assert "up to date" not in capsys.readouterr().out
    assert main(args[:-1] + ["2"]) == 0
    assert "up to date" in capsys.readouterr().out


def test_dim_reuses_a_cloud_of_the_same_settings_only(tmp_path, scene_dir, capsys):
    survey = tmp_path / "photo.json"
    assert main(["dim-survey-template", "-o", str(survey)]) == 0
    small = json.loads(survey.read_text())
    small.update(margin_m=40.0, point_step_px=16.0)  # a quick flight
    survey.write_text(json.dumps(small))
    out = tmp_path / "d.las"
    args = ["dim", str(scene_dir), "-o", str(out), "--survey", str(survey), "--seed", "1"]
    assert main(args) == 0
    first = out.read_bytes()
    summary = json.loads((tmp_path / "d.las.summary.json").read_text())
    assert summary["output_file"]["bytes"] == len(first) and summary["fingerprint"]
    capsys.readouterr()
    assert main(args) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(args + ["--force"]) == 0
    assert "up to date" not in capsys.readouterr().out and out.read_bytes() == first  # same seed, same bytes
    assert main(args[:-1] + ["2"]) == 0
    assert "up to date" not in capsys.readouterr().out and out.read_bytes() != first
    out.write_bytes(out.read_bytes()[:-8])  # cut: made again
    assert main(args[:-1] + ["2"]) == 0
    assert "up to date" not in capsys.readouterr().out


# acquisition --------------------------------------------------------------------------------

def test_acquire_redoes_a_cloud_of_other_settings_or_another_size(tmp_path):
    scene = box_city(rows=1, cols=1)
    out = tmp_path / "a.las"
    assert not acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1).resumed
    assert acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1).resumed
    assert not acquire(scene, Acquisition("als", als_for_density(5.0)), out, seed=1).resumed
    assert not acquire(scene, Acquisition("als", als_for_density(5.0)), out, seed=2).resumed
    out.write_bytes(out.read_bytes() + b"\0")
    assert not acquire(scene, Acquisition("als", als_for_density(5.0)), out, seed=2).resumed


def test_an_acquisition_record_without_the_output_s_digest_is_acquired_again_once(tmp_path):
    """A record of an older QuakeScan (no fingerprint, size or SHA-256 of its cloud) is not
    trusted: the cloud is made again once, with a record a rerun reuses."""
    scene = box_city(rows=1, cols=1)
    out = tmp_path / "a.las"
    acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1)
    sidecar = out.with_name(out.name + ".acquisition.json")
    record = json.loads(sidecar.read_text())
    for key in ("fingerprint", "output_file"):
        del record[key]
    sidecar.write_text(json.dumps(record))
    assert not acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1).resumed
    assert acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1).resumed


def test_acquire_redoes_a_cloud_of_the_recorded_size_but_other_bytes(tmp_path):
    scene = box_city(rows=1, cols=1)
    out = tmp_path / "a.las"
    acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1)
    data = bytearray(out.read_bytes())
    data[-1] ^= 0xFF  # replaced by a file of the same size
    out.write_bytes(bytes(data))
    assert not acquire(scene, Acquisition("als", als_for_density(4.0)), out, seed=1).resumed
    assert out.read_bytes()[-1] != data[-1]


# experiment ---------------------------------------------------------------------------------

def test_experiment_clouds_are_reacquired_when_their_scene_changed(tmp_path, caplog):
    from quakescan.studies.experiment import _acquire

    scene = tmp_path / "scene"
    write_scene(box_city(rows=1, cols=1), scene)

    def said():  # an acquisition's stage message, one per cloud made
        return [r for r in caplog.records if r.name == "quakescan.stages" and "DIM in" in r.getMessage()]

    caplog.set_level("INFO", logger="quakescan.stages")
    path = _acquire("dim", scene, tmp_path / "c", 4)
    assert path.name == "c.seed4.las" and len(said()) == 1
    assert _acquire("dim", scene, tmp_path / "c", 4) == path and len(said()) == 1  # reused
    write_scene(box_city(rows=1, cols=1, height=12.0), scene)  # regenerated in place, same name and seed
    _acquire("dim", scene, tmp_path / "c", 4)
    assert len(said()) == 2


def test_experiment_tables_and_levels_of_detection_follow_their_inputs_and_settings(tmp_path, monkeypatch):
    import quakescan.formats.pair
    import quakescan.change.lod
    import quakescan.change.pipeline
    from quakescan.change.lod import LevelsOfDetection
    from quakescan.change.pipeline import BuildingRow
    from quakescan.change.settings import PipelineSettings
    from quakescan.studies.experiment import ExperimentSettings, _levels_of_detection, _table

    for name in ("pre.las", "post.las", "rescan.las"):
        (tmp_path / name).write_bytes(b"a cloud")
    described, calibrated = [], []
    names = PipelineSettings().descriptor_names()

    def describe_pair(pre, post, settings, workers=None):
        described.append(1)
        return [BuildingRow(1, 50, 50, True, "", {n: 0.5 for n in names}, (0.0, 0.0), {})]

    def calibrate(a, b, seed=0, workers=None):
        calibrated.append(seed)
        return LevelsOfDetection(lod_height_m=0.3, lod_curvature=0.2, height_at_quantile_m=0.1,
                                 curvature_at_quantile=0.1, quantile=0.999, points=5000, radius_m=1.0)

    monkeypatch.setattr(quakescan.formats.pair, "load_pair", lambda pre, post: type("P", (), {"pre": pre, "post": post}))
    monkeypatch.setattr(quakescan.change.pipeline, "describe_pair", describe_pair)
    monkeypatch.setattr(quakescan.change.lod, "calibrate", calibrate)
    monkeypatch.setattr("quakescan.formats.pointcloud.read_epoch", lambda p, origin=None: type("E", (), {"origin": None}))
    posts = [(tmp_path / "post.las", 5)]
    cache = tmp_path / "table"
    _table(tmp_path / "pre.las", posts, cache, PipelineSettings(), 1)
    _table(tmp_path / "pre.las", posts, cache, PipelineSettings(), 1)
    assert len(described) == 1
    _table(tmp_path / "pre.las", [(tmp_path / "post.las", 4)], cache, PipelineSettings(), 1)  # other grades
    assert len(described) == 2
    os.utime(tmp_path / "post.las", ns=(1, 1))  # the cloud was acquired again
    _table(tmp_path / "pre.las", posts, cache, PipelineSettings(), 1)
    assert len(described) == 3
    lod_cache = tmp_path / "lod.json"
    for seed in (0, 0, 1):
        _levels_of_detection(ExperimentSettings(buildings=4, seed=seed), tmp_path / "pre.las",
                             tmp_path / "rescan.las", lod_cache, 1)
    assert calibrated == [0, 1]


# training set -------------------------------------------------------------------------------

def test_training_set_tables_of_another_pair_are_described_again(tmp_path, monkeypatch):
    import quakescan.acquisition.acquire
    import quakescan.learning.trainset as ts
    from quakescan.learning.default_model import TABLE_SETTINGS
    from quakescan.learning.trainset import build, default_plan

    plan = default_plan(0, "quick")
    monkeypatch.setattr(ts, "generate_city", lambda city, folder: None)
    key = ts._settings_key(TABLE_SETTINGS, plan.labels)
    fake = {"x": np.zeros((1, len(TABLE_SETTINGS.descriptor_names()))), "y": np.array([0]),
            "building_id": np.array([1]), "density": np.ones((1, 2)), "cells": np.array([50]),
            "seconds": np.zeros(2)}
    for p in plan.pairs:
        for scene in ("pre", p.post_scene):
            (tmp_path / "scenes" / p.city / scene).mkdir(parents=True, exist_ok=True)
            (tmp_path / "scenes" / p.city / scene / "scene.json").write_text("{}")
    acquired = []

    def no_acquire(scene, acquisition, path, seed=0, **kw):
        acquired.append(Path(path).name)
        raise Boom

    monkeypatch.setattr(quakescan.acquisition.acquire, "acquire", no_acquire)
    with pytest.raises(Boom):  # no table yet: the first pair is acquired
        build(tmp_path, plan, TABLE_SETTINGS)
    for p in plan.pairs:  # finished tables, as build records them
        path = tmp_path / "tables" / f"{p.name}.{key}.npz"
        np.savez(path, **fake)
        fingerprint.record(path, ts._table_fingerprint(p, tmp_path / "scenes" / p.city, TABLE_SETTINGS, plan.labels))
    acquired.clear()
    assert len(build(tmp_path, plan, TABLE_SETTINGS).y) == len(plan.pairs)
    assert acquired == []
    first = plan.pairs[0]
    settings = dict(first.pre["settings"])
    field = next(k for k, v in settings.items() if isinstance(v, float) and v > 0)
    settings[field] *= 1.1
    changed = replace(plan, pairs=[replace(first, pre={**first.pre, "settings": settings}), *plan.pairs[1:]])
    assert changed.pairs[0].name == first.name
    with pytest.raises(Boom):  # the same pair name, another acquisition: not the table on disk
        build(tmp_path, changed, TABLE_SETTINGS)
    assert acquired == [f"pre.{first.pre['kind']}.{first.pre_seed}.las"]
    (tmp_path / "scenes" / plan.pairs[1].city / "pre" / "scene.json").write_text('{"regenerated": 1}')
    acquired.clear()
    with pytest.raises(Boom):  # the pair's scene changed: described again
        build(tmp_path, plan, TABLE_SETTINGS)


# generation ---------------------------------------------------------------------------------

def test_generated_bundles_are_reused_only_with_the_same_generator_record(tmp_path):
    spec = importlib.util.spec_from_file_location("generate_scenes", REPO / "blender_scripts" / "generate_scenes.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    job, _ = gen.parse_args(["--set", "generic", "--dataset", "mixed", "--buildings", "4", "--seed", "1",
                             "--out", str(tmp_path)])
    info = gen.addon_module("generation").generator_info(job, "pre")
    folder = tmp_path / "pre"
    assert gen.bundle_state(folder, info) == "missing"
    folder.mkdir()
    (folder / "scene.json").write_text(json.dumps({"format": "quakescan-scene", "generator": info}))
    assert gen.bundle_state(folder, info) == "done"
    assert gen.bundle_state(folder, {**info, "seed": 2}) == "different"
    assert gen.bundle_state(folder, {**info, "version": info["version"] + 1}) == "different"
    (folder / "scene.json").write_text("[]")
    assert gen.bundle_state(folder, info) == "different"
