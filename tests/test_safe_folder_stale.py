"""A rerun never leaves a previous run's results beside its own as if they were current (issue
45): what the previous summary records writing and this run does not write is removed, and a
folder stopped half-way no longer claims to hold finished results."""
import json
import logging

import pytest

from quakescan.assessment.run import classify
from tests.safe_folder_pair import RESULTS, names, pair  # noqa: F401  (a fixture)

WITHOUT_LAS = [n for n in RESULTS if n != "post_grades.las"]


def _classify(pair, out, **kw):  # noqa: F811
    return classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops", **kw)


def test_no_las_then_laz_then_las_leave_only_this_runs_graded_cloud(pair, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    s = _classify(pair, out)
    recorded = ["buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.png", "damage_map.html",
                "post_grades.las", "summary.json"]
    assert names(out) == RESULTS and s["outputs"] == recorded
    assert json.loads((out / "summary.json").read_text())["outputs"] == recorded
    _classify(pair, out, write_las=False)
    assert names(out) == WITHOUT_LAS
    _classify(pair, out, laz=True)
    assert names(out) == sorted(WITHOUT_LAS + ["post_grades.laz"])
    _classify(pair, out)
    assert names(out) == RESULTS


def test_a_summary_written_before_the_outputs_list_still_retires_its_graded_cloud(pair, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    _classify(pair, out)
    summary = json.loads((out / "summary.json").read_text())
    del summary["outputs"]
    (out / "summary.json").write_text(json.dumps(summary))
    _classify(pair, out, write_las=False)
    assert names(out) == WITHOUT_LAS


def test_a_graded_cloud_nobody_recorded_is_kept_and_said(pair, tmp_path, caplog):  # noqa: F811
    out = tmp_path / "out"
    out.mkdir()
    (out / "post_grades.laz").write_bytes(b"the user's")
    with caplog.at_level(logging.WARNING):
        _classify(pair, out, write_las=False)
    assert (out / "post_grades.laz").read_bytes() == b"the user's"
    assert "post_grades.laz: not written by this run nor recorded by an earlier one" in caplog.text


def test_a_run_stopped_half_way_leaves_no_summary_over_a_mix_of_two_runs(pair, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    _classify(pair, out)
    first = (out / "buildings.csv").read_bytes()

    class Stop(Exception):
        pass

    def stop(done, total, stage=""):
        raise Stop

    with pytest.raises(Stop):  # another run (other options) into the folder, stopped
        _classify(pair, out, unseen_damage=False, progress=stop)
    assert not (out / "summary.json").exists() and not (out / "post_grades.las").exists()
    again = _classify(pair, out)  # the first run's inputs: made again, not "up to date"
    assert not again.get("up_to_date") and (out / "buildings.csv").read_bytes() == first
    assert names(out) == RESULTS
