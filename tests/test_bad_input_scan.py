"""Bad input to scan, scenes, surveys, import-cityjson and demo: every case ends as a clear
error (exit 2, the file or flag named, what is wrong) or a correct result (issue 13)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from quakescan.cli import main
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city

REPO = Path(__file__).resolve().parents[1]
# a small, quick survey (50 kHz): the demo's paper survey at a sixth of its pulse rate
SMALL = {"format": "quakescan-survey", "version": 1, "pulse_rate_hz": 50_000.0}


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_scene(box_city(rows=1, cols=2), tmp_path_factory.mktemp("scene") / "city")


@pytest.fixture(scope="module")
def survey_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("survey") / "small.json"
    p.write_text(json.dumps(SMALL))
    return p


def _error(capsys, argv) -> str:
    """Run the command; it must exit 2 with one `quakescan: error:` line and no traceback."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("quakescan: error: ") and "Traceback" not in err
    return err


def _scan(scene_dir, survey_file, out, *extra):
    return ["scan", str(scene_dir), "-o", str(out), "--survey", str(survey_file), *extra]


# ---------------------------------------------------------------- scan flags


@pytest.mark.parametrize("flag, value, text", [("--seed", "-1", "--seed: expected an integer >= 0"),
                                               ("--threads", "-4", "--threads: expected a number of worker threads"),
                                               ("--threads", "0", "--threads: expected a number of worker threads")])
def test_scan_flags_out_of_range(tmp_path, capsys, scene_dir, survey_file, flag, value, text):
    assert text in _error(capsys, _scan(scene_dir, survey_file, tmp_path / "a.las", flag, value))
    assert not (tmp_path / "a.las").exists()


def test_threads_minus_one_is_all_cores(tmp_path, scene_dir, survey_file):
    assert main(_scan(scene_dir, survey_file, tmp_path / "a.las", "--threads", "-1")) == 0


@pytest.mark.parametrize("name, text", [("a.txt", "must end in .las or .laz"), ("folder.las", "is a folder")])
def test_scan_output_names(tmp_path, capsys, scene_dir, survey_file, name, text):
    (tmp_path / "folder.las").mkdir()
    err = _error(capsys, _scan(scene_dir, survey_file, tmp_path / name))
    assert f"-o {tmp_path / name}" in err and text in err


def test_scan_into_a_closed_pipe_finishes_without_a_traceback(tmp_path, scene_dir, survey_file):
    out = tmp_path / "a.las"
    cmd = (f"set -o pipefail; {sys.executable} -m quakescan.cli scan {scene_dir} -o {out} --survey {survey_file} "
           "| head -1")
    res = subprocess.run(["bash", "-c", cmd], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.stdout.startswith("flight plan:") and len(res.stdout.splitlines()) == 1
    assert "Traceback" not in res.stderr and "BrokenPipe" not in res.stderr, res.stderr
    assert res.returncode == 0 and out.is_file()  # the scan went on and wrote its cloud


def test_a_truncated_output_is_not_up_to_date(tmp_path, capsys, scene_dir, survey_file):
    out = tmp_path / "a.las"
    assert main(_scan(scene_dir, survey_file, out)) == 0
    whole = out.read_bytes()
    capsys.readouterr()
    assert main(_scan(scene_dir, survey_file, out)) == 0
    assert "up to date" in capsys.readouterr().out
    out.write_bytes(whole[: len(whole) // 2])
    assert main(_scan(scene_dir, survey_file, out)) == 0
    assert "up to date" not in capsys.readouterr().out
    assert out.read_bytes() == whole
    out.write_bytes(whole[:-4] + b"\0\0\0\0")  # same size, other bytes
    assert main(_scan(scene_dir, survey_file, out)) == 0
    assert "up to date" not in capsys.readouterr().out and out.read_bytes() == whole


def test_trajectory_is_written_for_an_up_to_date_scan(tmp_path, capsys, scene_dir, survey_file):
    out = tmp_path / "a.las"
    assert main(_scan(scene_dir, survey_file, out)) == 0
    traj = tmp_path / "sub" / "trajectory.csv"  # into a folder that does not exist yet
    assert main(_scan(scene_dir, survey_file, out, "--trajectory", str(traj))) == 0
    assert "up to date" in capsys.readouterr().out
    rows = np.loadtxt(traj, delimiter=",", skiprows=1)
    assert rows.shape[1] == 6 and set(np.unique(rows[:, 5])) == {1.0, 2.0}


# ---------------------------------------------------------------- surveys


@pytest.mark.parametrize("field, value, text", [
    ("altitude_agl_m", True, "altitude_agl_m must be a finite number"),
    ("max_returns", True, "max_returns must be an integer 1..15"),
    ("pulse_rate_hz", 1e12, "pulse_rate_hz must lie in [1000, 1e+07]"),
    ("pulse_rate_hz", 1e9, "pulse_rate_hz must lie in [1000, 1e+07]"),
    ("strip_overlap_pct", 99.999, "strip_overlap_pct must lie in [0, 95]"),
    ("speed_m_s", 1e-6, "speed_m_s must lie in [0.5, 150]"),
    ("run_in_m", 1e7, "run_in_m must lie in [0, 5000]"),
    ("line_direction_deg", float("nan"), "line_direction_deg must be a finite number"),
    ("altitude_agl_m", 1e6, "altitude_agl_m must lie in [1, 6000]"),
    ("beam", 3, "beam must be a string"),
])
def test_survey_fields_are_range_checked(tmp_path, capsys, scene_dir, field, value, text):
    survey = tmp_path / "s.json"
    survey.write_text(json.dumps({**SMALL, field: value}))  # json writes NaN as NaN, and reads it
    err = _error(capsys, _scan(scene_dir, survey, tmp_path / "a.las"))
    assert f"{survey}: " in err and text in err
    assert not (tmp_path / "a.las").exists()


def test_a_plan_beyond_the_size_limit_needs_force(tmp_path, capsys, scene_dir, survey_file, monkeypatch):
    import quakescan.acquisition.scan

    monkeypatch.setattr(quakescan.acquisition.scan, "MAX_SCAN_POINTS", 1000)
    err = _error(capsys, _scan(scene_dir, survey_file, tmp_path / "a.las"))
    assert f"{survey_file} over {scene_dir}: the plan reaches" in err and "--force" in err
    assert not (tmp_path / "a.las").exists()
    assert main(_scan(scene_dir, survey_file, tmp_path / "a.las", "--force")) == 0


def test_a_plan_of_too_many_lines_is_refused_before_it_is_made(tmp_path, capsys):
    """A 1 m, 1° FOV survey over a 3 km scene would need 170 000 lines."""
    scene = box_city(rows=1, cols=2)
    scene.vertices[scene.vertices[:, 1] > 20, 1] += 3000.0
    write_scene(scene, tmp_path / "wide")
    survey = tmp_path / "s.json"
    survey.write_text(json.dumps({**SMALL, "altitude_agl_m": 1.0, "fov_deg": 1.0, "sweep_deg": 10.0}))
    err = _error(capsys, _scan(tmp_path / "wide", survey, tmp_path / "a.las", "--dry-run"))
    assert "flight lines" in err and "more than 10,000" in err


def test_library_scan_refuses_bad_seed_and_workers(tmp_path):
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.errors import QuakeScanError

    for kw, text in (({"seed": -1}, "seed must be an integer >= 0"), ({"seed": True}, "seed must be"),
                     ({"workers": -4}, "workers: the number of worker threads must be an integer >= 1")):
        with pytest.raises(QuakeScanError, match=text):
            scan(box_city(rows=1, cols=1), preset("paper"), tmp_path / "a.las", **kw)


# ---------------------------------------------------------------- photo surveys and templates


@pytest.mark.parametrize("field, value, text", [
    ("forward_overlap_pct", 99.999, "forward_overlap_pct must lie in [0, 95]"),
    ("point_step_px", 1e-6, "point_step_px must lie in [0.5, 1000]"),
    ("probe_spacing_m", 1e-9, "probe_spacing_m must lie in [0.01, 100]"),
    ("speed_m_s", 1e-6, "speed_m_s must lie in [0.5, 150]"),
    ("altitude_agl_m", True, "altitude_agl_m must be a finite number"),
])
def test_photo_survey_fields_are_range_checked(tmp_path, capsys, scene_dir, field, value, text):
    survey = tmp_path / "p.json"
    survey.write_text(json.dumps({"format": "quakescan-photo-survey", "version": 1, field: value}))
    err = _error(capsys, ["dim", str(scene_dir), "-o", str(tmp_path / "d.las"), "--survey", str(survey)])
    assert f"{survey}: " in err and text in err


@pytest.mark.parametrize("flag, value, text", [("--seed", "-1", "--seed: expected an integer >= 0"),
                                               ("--threads", "-4", "--threads: expected a number of worker threads")])
def test_dim_seed_and_threads(tmp_path, capsys, scene_dir, flag, value, text):
    assert text in _error(capsys, ["dim", str(scene_dir), "-o", str(tmp_path / "d.las"), flag, value])


@pytest.mark.parametrize("command", ["survey-template", "dim-survey-template"])
def test_templates_onto_a_folder_or_into_a_new_one(tmp_path, capsys, command):
    err = _error(capsys, [command, "-o", str(tmp_path)])
    assert f"{tmp_path}: is a folder" in err
    assert not list(tmp_path.parent.glob(tmp_path.name + ".part"))
    assert main([command, "-o", str(tmp_path / "new" / "s.json")]) == 0
    assert json.loads((tmp_path / "new" / "s.json").read_text())["version"] == 1


# ---------------------------------------------------------------- scenes


def _edit_manifest(scene_dir: Path, tmp_path: Path, change) -> Path:
    import shutil

    dst = tmp_path / "edited"
    shutil.copytree(scene_dir, dst)
    manifest = json.loads((dst / "scene.json").read_text())
    change(manifest)
    (dst / "scene.json").write_text(json.dumps(manifest))
    return dst


@pytest.mark.parametrize("change, text", [
    (lambda m: m.update(crs="EPSG:999999"), "crs 'EPSG:999999' is not a coordinate reference system PROJ knows"),
    (lambda m: m.update(crs="garbage"), "crs 'garbage' is not a coordinate reference system PROJ knows"),
    (lambda m: m.update(crs="EPSG:4326"), "has axes in ['degree']"),
    (lambda m: m.update(origin=[1e300, 0, 0]), "lies more than 1e+08 m from 0"),
    (lambda m: m.update(origin=[True, 0, 0]), "origin must be three finite numbers"),
    (lambda m: m["buildings"][0].update(grade=True), "grade must be an EMS-98 grade 0..5, got True"),
    (lambda m: m["buildings"][0].update(storeys=True), "storeys must be an integer >= 0, got True"),
    (lambda m: m["buildings"][0].update(seed=False), "seed must be an integer, got False"),
    (lambda m: m["buildings"][0].update(reflectance=2), "reflectance must be a number in (0, 1]"),
])
@pytest.mark.parametrize("command", ["validate", "scan"])
def test_bad_scene_manifests_are_refused_naming_scene_json(tmp_path, capsys, scene_dir, survey_file, change, text,
                                                          command):
    edited = _edit_manifest(scene_dir, tmp_path, change)
    argv = ["validate", str(edited)] if command == "validate" else _scan(edited, survey_file, tmp_path / "a.las")
    err = _error(capsys, argv)
    assert f"{edited / 'scene.json'}: " in err and text in err


def test_a_valid_crs_passes_validate(tmp_path, capsys, scene_dir):
    edited = _edit_manifest(scene_dir, tmp_path, lambda m: m.update(crs="EPSG:2056"))
    assert main(["validate", str(edited)]) == 0
    assert "crs EPSG:2056" in capsys.readouterr().out


def test_far_vertices_are_refused(tmp_path, capsys, survey_file):
    from quakescan.errors import SceneError
    from quakescan.formats.scene import validate_scene

    scene = box_city(rows=1, cols=1)
    scene.vertices[0] = [1e300, 0.0, 0.0]
    with pytest.raises(SceneError, match=r"1 vertices lie more than 1e\+08 m from the origin"):
        validate_scene(scene)


def test_scan_of_a_scene_object_with_a_bad_crs_names_its_source(tmp_path):
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.errors import SceneError

    scene = box_city(rows=1, cols=1)
    scene.crs = "EPSG:999999"
    with pytest.raises(SceneError, match=r"^my/scene: crs 'EPSG:999999'"):
        scan(scene, preset("paper"), tmp_path / "a.las", source="my/scene")


# ---------------------------------------------------------------- import-cityjson


def _cityjson(path: Path, version="2.0", transform=True, crs=None) -> Path:
    v = [[0, 0, 0], [10, 0, 0], [10, 8, 0], [0, 8, 0], [0, 0, 9], [10, 0, 9], [10, 8, 9], [0, 8, 9]]
    faces = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    doc = {"type": "CityJSON", "version": version,
           "CityObjects": {"B": {"type": "Building", "geometry": [{"type": "Solid", "lod": "2",
                                                                   "boundaries": [faces]}]}}}
    if transform:
        doc["vertices"] = [[c * 1000 for c in p] for p in v]
        doc["transform"] = {"scale": [0.001] * 3, "translate": [2600000.0, 1200000.0, 400.0]}
    else:
        doc["vertices"] = [[c * 1000 for c in p] for p in v]  # integers, as 1.1/2.0 store them
    if crs:
        doc["metadata"] = {"referenceSystem": crs}
    path.write_text(json.dumps(doc))
    return path


def test_import_cityjson_onto_an_existing_file(tmp_path, capsys):
    (tmp_path / "taken").write_text("x")
    err = _error(capsys, ["import-cityjson", str(_cityjson(tmp_path / "c.json")), "-o", str(tmp_path / "taken")])
    assert f"-o {tmp_path / 'taken'}: exists and is not a folder" in err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    err = _error(capsys, ["import-cityjson", str(tmp_path / "c.json"), "-o", str(tmp_path / "other")])
    assert "holds other files than a scene bundle" in err
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"
    # a scene bundle folder is written again (a rerun)
    for _ in range(2):
        assert main(["import-cityjson", str(tmp_path / "c.json"), "-o", str(tmp_path / "scene")]) == 0


def test_import_cityjson_without_transform(tmp_path, capsys):
    err = _error(capsys, ["import-cityjson", str(_cityjson(tmp_path / "c.json", transform=False)), "-o",
                          str(tmp_path / "s")])
    assert f"{tmp_path / 'c.json'}: CityJSON 2.0 requires 'transform'" in err


@pytest.mark.parametrize("crs, given, text", [
    ("EPSG:999999", None, "crs 'EPSG:999999' is not a coordinate reference system PROJ knows"),
    ("garbage", None, "metadata.referenceSystem 'garbage' is not an EPSG code"),
    ("urn:ogc:def:crs:EPSG::2056", "EPSG:28992", "the file names its CRS EPSG:2056"),
    (None, "garbage", "--crs 'garbage': expected an EPSG code"),
    (None, "EPSG:999999", "--crs EPSG:999999: crs 'EPSG:999999' is not a coordinate reference system"),
])
def test_import_cityjson_crs_errors(tmp_path, capsys, crs, given, text):
    argv = ["import-cityjson", str(_cityjson(tmp_path / "c.json", crs=crs)), "-o", str(tmp_path / "s")]
    err = _error(capsys, argv + (["--crs", given] if given else []))
    assert text in err
    assert not (tmp_path / "s").exists()


def test_import_cityjson_crs_and_material_give_the_scene(tmp_path, capsys):
    from quakescan.formats.scene import read_scene

    argv = ["import-cityjson", str(_cityjson(tmp_path / "c.json")), "-o", str(tmp_path / "s"), "--crs", "EPSG:2056",
            "--material", "reinforced_concrete"]
    assert main(argv) == 0
    scene = read_scene(tmp_path / "s")
    assert scene.crs == "EPSG:2056" and [b.material for b in scene.buildings] == ["reinforced_concrete"]


@pytest.mark.parametrize("buffer", ["-1", "nan", "1e9"])
def test_import_cityjson_buffer_out_of_range(tmp_path, capsys, buffer):
    err = _error(capsys, ["import-cityjson", str(_cityjson(tmp_path / "c.json")), "-o", str(tmp_path / "s"),
                          "--buffer", buffer])
    assert "--buffer" in err


# ---------------------------------------------------------------- demo


@pytest.mark.parametrize("flag, value", [("--buildings", "0"), ("--buildings", "100000"), ("--seed", "-1")])
def test_demo_argument_errors_name_quakescan_demo(tmp_path, capsys, flag, value):
    err = _error(capsys, ["demo", "-o", str(tmp_path / "d"), flag, value])
    assert f"demo {flag}: expected" in err and "generate_scenes.py" not in err


def test_the_demo_scans_again_a_cut_cloud(tmp_path, scene_dir):
    from quakescan.demo import las_is_complete, scan_scene

    out = tmp_path / "pre.las"
    scan_scene(scene_dir, out, seed=1)
    whole = out.read_bytes()
    assert las_is_complete(out)
    out.write_bytes(whole[:-100])
    assert not las_is_complete(out)
    scan_scene(scene_dir, out, seed=1)
    assert out.read_bytes() == whole
    out.write_bytes(b"LASF")
    assert not las_is_complete(out)


def test_the_generators_own_refusals_do_not_name_its_script(monkeypatch, tmp_path):
    import quakescan.generator
    from quakescan.errors import QuakeScanError

    class Refused:
        returncode = 2
        stderr = "usage: generate_scenes.py [-h]\ngenerate_scenes.py: error: argument --seed: seed must be in 0..2^32-1"

    monkeypatch.setattr(quakescan.generator, "generator_command", lambda args: ["generator", *args])
    monkeypatch.setattr(quakescan.generator.subprocess, "run", lambda *a, **k: Refused())
    with pytest.raises(QuakeScanError, match=r"the scene generator refused .*--seed: seed must be") as e:
        quakescan.generator.generate(quakescan.generator.GenerationSpec("generic", "mixed", 3, 5, tmp_path))
    assert "usage" not in str(e.value)



def test_any_command_into_a_closed_pipe_ends_without_a_traceback(tmp_path, scene_dir):
    """A reader that left before the first line (the pipe's read end closed): no BrokenPipeError
    traceback; the command says so and exits 141, as a shell reports a command ended by SIGPIPE
    (what it wrote before its message stays: footprints prints after writing its file)."""
    read, write = os.pipe()
    os.close(read)
    out = tmp_path / "fp.geojson"
    try:
        res = subprocess.run([sys.executable, "-m", "quakescan.cli", "footprints", str(scene_dir), "-o", str(out)],
                             cwd=REPO, stdout=write, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert "Traceback" not in res.stderr and "BrokenPipe" not in res.stderr, res.stderr
    assert res.returncode == 141 and "output pipe closed" in res.stderr and out.is_file()
