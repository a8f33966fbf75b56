"""The `quakescan` command line: main job, scan, survey files, errors and exit codes."""
import json

import laspy
import numpy as np
import pytest

from quakescan.acquisition.survey import Survey, load_survey, preset
from quakescan.cli import main
from quakescan.errors import SurveyError
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city


@pytest.mark.slow
def test_demo_runs_the_whole_chain(tmp_path, capsys):
    """generate → scan both epochs → classify with the shipped model → evaluate → map."""
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--buildings", "6", "--seed", "3"]) == 0
    text = capsys.readouterr().out
    res = out / "result"
    for name in ("buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.png", "damage_map.html",
                 "post_grades.las", "confusion.png", "evaluation.json", "summary.json"):
        assert (res / name).is_file(), name
    # the demo city stands in L'Aquila, UTM 33N: the GeoJSON lands there in QGIS
    gj = json.loads((res / "buildings.geojson").read_text())
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32633"
    xy = np.array([c for f in gj["features"] for c in f["geometry"]["coordinates"][0]])
    assert len(gj["features"]) == 6 and np.abs(xy - [367000.0, 4690000.0]).max() < 500
    scene = json.loads((out / "city" / "post" / "scene.json").read_text())
    assert scene["crs"] == "EPSG:32633" and scene["origin"] == [367000.0, 4690000.0, 0.0]
    ev = json.loads((res / "evaluation.json").read_text())
    assert ev["n"] + ev["not_assessable"] == 6 and "overall accuracy" in text
    pre = laspy.read(out / "pre.las")
    assert pre.header.parse_crs().to_epsg() == 32633 and abs(float(np.mean(pre.x)) - 367000.0) < 500
    assert len(pre.x) > 100_000 and set(np.unique(pre["building_id"])) == {0, 1, 2, 3, 4, 5, 6}
    mtime = (out / "pre.las").stat().st_mtime_ns
    assert main(["demo", "-o", str(out), "--buildings", "6", "--seed", "3"]) == 0  # resumes: no rescan
    assert (out / "pre.las").stat().st_mtime_ns == mtime


def test_scan_writes_summary_and_resumes(tmp_path, capsys):
    scene_dir = write_scene(box_city(rows=1, cols=2), tmp_path / "scene")
    out = tmp_path / "pre.laz"
    args = ["scan", str(scene_dir), "-o", str(out), "--seed", "3", "--trajectory", str(tmp_path / "traj.csv")]
    assert main(args) == 0
    first = out.read_bytes()
    summary = json.loads((tmp_path / "pre.laz.summary.json").read_text())
    assert summary["seed"] == 3 and summary["survey"]["pulse_rate_hz"] == 300000
    assert (tmp_path / "traj.csv").read_text().startswith("gps_time_s,x_m,y_m,z_m")
    capsys.readouterr()
    assert main(args) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(args + ["--force"]) == 0
    assert out.read_bytes() == first


def test_bad_scene_exits_2_naming_the_file(tmp_path, capsys):
    scene_dir = write_scene(box_city(rows=1, cols=1), tmp_path / "scene")
    (scene_dir / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    assert main(["scan", str(scene_dir), "-o", str(tmp_path / "x.las")]) == 2
    err = capsys.readouterr().err
    assert "quakescan: error:" in err and "mesh.ply" in err
    assert not (tmp_path / "x.las").exists()


def test_survey_template_round_trip(tmp_path):
    path = tmp_path / "survey.json"
    assert main(["survey-template", "-o", str(path)]) == 0
    data = json.loads(path.read_text())
    assert set(data["_doc"]) == {k for k in Survey.__dataclass_fields__ if k != "name"}
    assert all("[" in text for text in data["_doc"].values())  # every field documents its unit
    assert load_survey(path) == preset("paper")


def test_paper_preset_is_the_papers_table():
    s = preset("paper")
    assert (s.scan_rate_hz, s.pulse_rate_hz, s.strip_overlap_pct, s.fov_deg, s.altitude_agl_m,
            s.speed_m_s) == (89, 300_000, 60, 120, 100, 8)
    assert s.beam == "single"


@pytest.mark.parametrize("content, text", [
    ("{", "not valid JSON"),
    ('{"format": "x"}', "not a survey file"),
    ('{"format": "quakescan-survey", "version": 1, "speed": 3}', "unknown survey fields ['speed']"),
    ('{"format": "quakescan-survey", "version": 1, "speed_m_s": -3}', "speed_m_s must be a positive number [m/s]"),
    ('{"format": "quakescan-survey", "version": 1, "fov_deg": 200}', "fov_deg"),
    ('{"format": "quakescan-survey", "version": 1, "beam": "wide"}', "beam must be one of"),
    ('{"format": "quakescan-survey", "version": 2}', "version 2 not supported"),
])
def test_bad_survey_files_are_named(tmp_path, content, text):
    path = tmp_path / "s.json"
    path.write_text(content)
    with pytest.raises(SurveyError) as err:
        load_survey(path)
    assert text in str(err.value) and str(path) in str(err.value)


def test_a_survey_file_names_a_preset_and_changes_some_fields(tmp_path):
    path = tmp_path / "s.json"
    path.write_text('{"format": "quakescan-survey", "version": 1, "preset": "paper", "altitude_agl_m": 150}')
    assert load_survey(path) == preset("paper").replace(altitude_agl_m=150)
    path.write_text(b'{"format": "quakescan-survey", "version": 1, "_doc": "\xff"}'.decode("latin-1"),
                    encoding="latin-1")
    with pytest.raises(SurveyError, match="not valid JSON"):  # undecodable bytes: named, not a crash
        load_survey(path)


def test_unknown_preset():
    with pytest.raises(SurveyError, match="unknown survey preset 'fast'"):
        load_survey("fast")


def test_import_cityjson_then_scan(tmp_path, shared_data):
    scene_dir = tmp_path / "rdam"
    assert main(["import-cityjson", str(shared_data / "rotterdam_subset.json"), "-o", str(scene_dir)]) == 0
    assert main(["validate", str(scene_dir)]) == 0
    survey = tmp_path / "s.json"
    data = preset("paper").to_json()
    data["run_in_m"] = 0.0
    data["pulse_rate_hz"] = 30000.0  # a light scan: this test checks the path, not the density
    survey.write_text(json.dumps(data))
    out = tmp_path / "rdam.las"
    assert main(["scan", str(scene_dir), "-o", str(out), "--survey", str(survey)]) == 0
    las = laspy.read(out)
    assert set(range(1, 17)) <= set(int(b) for b in set(las.building_id))
    # real projected coordinates kept: the file's translate is the LAS offset
    meta = json.loads((scene_dir / "scene.json").read_text())
    assert list(las.header.offsets) == meta["origin"]


def test_features_command_adds_readable_dimensions(tmp_path, capsys):
    from quakescan.acquisition.scan import scan
    from quakescan.change.features import compute_features
    from quakescan.formats.pointcloud import read_epoch

    scan(box_city(rows=1, cols=2, origin=(500000.0, 5000000.0, 0.0)), preset("paper").replace(pulse_rate_hz=50_000.0),
         tmp_path / "in.las", seed=1)
    out = tmp_path / "feat.las"
    assert main(["features", str(tmp_path / "in.las"), "-o", str(out), "--radius", "1.5",
                 "--features", "planarity,z_rank,num_neighbours"]) == 0
    las = laspy.read(out)
    want = compute_features(read_epoch(tmp_path / "in.las").xyz, 1.5, ("planarity", "z_rank", "num_neighbours"))
    for name in ("planarity", "z_rank", "num_neighbours"):
        np.testing.assert_allclose(np.asarray(las[name], dtype=np.float64), want[name].astype(np.float32),
                                   rtol=0, atol=0, equal_nan=True)
    assert np.asarray(las["building_id"]).max() == 2  # the input's dimensions are kept
    assert "3 features of" in capsys.readouterr().out
    assert main(["features", str(out), "-o", str(tmp_path / "again.las"), "--radius", "1.5",
                 "--features", "planarity"]) == 2
    assert "already has dimensions ['planarity']" in capsys.readouterr().err
    assert main(["features", str(tmp_path / "in.las"), "-o", str(tmp_path / "x.las"), "--radius", "1.5",
                 "--features", "wetness"]) == 2
    assert "unknown features" in capsys.readouterr().err


def test_dim_command_writes_cloud_and_summary(tmp_path, capsys):
    scene_dir = write_scene(box_city(rows=1, cols=2), tmp_path / "scene")
    out = tmp_path / "dim.las"
    assert main(["dim", str(scene_dir), "-o", str(out), "--seed", "2"]) == 0
    las = laspy.read(out)
    summary = json.loads((tmp_path / "dim.las.summary.json").read_text())
    assert len(las.x) == summary["points"] > 10_000 and summary["photo_survey"]["min_views"] == 2
    assert set(np.unique(las["building_id"])) == {0, 1, 2}
    assert "dim:" in capsys.readouterr().out
    assert main(["dim-survey-template", "-o", str(tmp_path / "photo.json")]) == 0
    assert main(["dim", str(scene_dir), "-o", str(tmp_path / "x.las"), "--survey", str(tmp_path / "nope.json")]) == 2
    assert "nope.json" in capsys.readouterr().err


def test_robustness_command_writes_the_report(tmp_path, capsys):
    pre = write_scene(box_city(rows=1, cols=2, height=9.0), tmp_path / "pre")
    post = write_scene(box_city(rows=1, cols=2, height=(9.0, 4.0), epoch="post", grades=(0, 5)), tmp_path / "post")
    out = tmp_path / "rob"
    assert main(["robustness", "--pre", str(pre), "--post", str(post), "-o", str(out), "--radii", "1.0,2.0"]) == 0
    text = capsys.readouterr().out
    assert "best radius" in text
    report = json.loads((out / "robustness.json").read_text())
    assert report["radii_m"] == [1.0, 2.0] and report["best_radius_m"] in (1.0, 2.0)
    for name in ("README.md", "robustness.csv", "features_vs_threshold.png", "difference_heatmap.png"):
        assert (out / name).is_file(), name


def test_trajectory_lines_are_the_points_source_ids(tmp_path):
    import laspy

    from quakescan.formats.scene import write_scene
    from quakescan.formats.synthetic import box_city

    write_scene(box_city(rows=1, cols=2), tmp_path / "scene")
    out = tmp_path / "a.las"
    assert main(["scan", str(tmp_path / "scene"), "-o", str(out), "--survey", "als",
                 "--trajectory", str(tmp_path / "traj.csv")]) == 0
    traj = np.loadtxt(tmp_path / "traj.csv", delimiter=",", skiprows=1)
    las = laspy.read(out)
    assert set(np.unique(traj[:, 5]).astype(int)) == set(np.unique(np.asarray(las.point_source_id)).tolist())
    # and each point's GPS time lies within its line's stretch of the trajectory
    for line in np.unique(traj[:, 5]):
        t = np.asarray(las.gps_time)[np.asarray(las.point_source_id) == line]
        span = traj[traj[:, 5] == line, 0]
        assert t.min() >= span.min() - 0.11 and t.max() <= span.max() + 0.11


def test_demo_rescans_a_scene_regenerated_after_its_scan(tmp_path):
    """The demo skips a scan of the scene it was made from, even rewritten with the same
    content, and redoes one whose scene changed (a city regenerated, e.g. moved to the demo's
    CRS by a newer QuakeScan)."""
    from quakescan.demo import scan_scene

    scene_dir = write_scene(box_city(rows=1, cols=1), tmp_path / "scene")
    out = tmp_path / "pre.las"
    scan_scene(scene_dir, out, seed=1)
    first = out.stat().st_mtime_ns
    write_scene(box_city(rows=1, cols=1), scene_dir)  # regenerated, the same city
    scan_scene(scene_dir, out, seed=1)
    assert out.stat().st_mtime_ns == first
    write_scene(box_city(rows=1, cols=1, origin=(367000.0, 4690000.0, 0.0)), scene_dir)  # moved
    scan_scene(scene_dir, out, seed=1)
    assert out.stat().st_mtime_ns > first  # rescanned


def test_the_command_leaves_without_the_last_collections_and_loses_no_output(tmp_path):
    """At exit the process's objects are frozen (Python's collections while it clears the
    modules took 0.8-0.9 s after a classify had finished), once however often `main` ran;
    what the command wrote and printed is all there, and the other exit handlers still run."""
    import subprocess
    import sys

    survey = tmp_path / "survey.json"
    script = f"""
import atexit, gc, sys
from quakescan.cli import main
# exit handlers run last in, first out: this one after main's, the one below before it
atexit.register(lambda: print("frozen after", gc.get_freeze_count() > 0, file=sys.stderr))
assert main(["survey-template", "-o", {str(survey)!r}]) == 0
handlers = atexit._ncallbacks()
assert main(["survey-template", "-o", {str(survey)!r}, "--preset", "paper"]) == 0
print("one handler", atexit._ncallbacks() == handlers)
atexit.register(lambda: print("frozen before", gc.get_freeze_count() > 0, file=sys.stderr))
print("collecting after main", gc.get_freeze_count() == 0)
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "one handler True" in proc.stdout and "collecting after main True" in proc.stdout  # frozen at exit only: tests call main in one process
    assert "frozen before False" in proc.stderr and "frozen after True" in proc.stderr
    assert load_survey(survey) == preset("paper")
