"""Progress of the long commands: one reporter (label done/total pct elapsed ETA) on stderr,
on a terminal by default, forced with --progress, silenced with -q; results stay on stdout."""
import io
import re

import numpy as np
import pytest

from quakescan.cli import main
from quakescan.cli.reporting import Progress
from tests.scenes import HEIGHTS, scan_box_pair

LINE = re.compile(r"^(?P<label>.+?)  (?P<done>[\d,]+)/(?P<total>[\d,]+)  +(?P<pct>\d+) %  (?P<elapsed>[\d:]+)  "
                  r"ETA (?P<eta>[\d:]+|\?)$")


class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self):
        return self.tty


def test_eta_is_the_rate_since_the_first_report_in_closed_form():
    """First report at 10 s with 5 of 100 done, then 25 done at 30 s: 20 steps in 20 s, 75 left:
    75 s. Unknown before a second report and within a second of the first (a burst of steps
    finishing together); the time before the first report (reading, set-up) does not count."""
    clock, stream = _Clock(), _Stream(False)
    p = Progress("classify", True, clock=clock, stream=stream)
    assert p.eta_s(5, 100, 110.0) is None
    clock.t = 110.0
    p(5, 100)
    assert p.first == (110.0, 5)
    assert p.eta_s(5, 100, 110.0) is None
    assert p.eta_s(60, 100, 110.5) is None  # a burst: no basis yet
    assert p.eta_s(25, 100, 130.0) == pytest.approx(75.0)
    assert p.eta_s(100, 100, 150.0) == 0.0
    assert p.line(25, 100, 130.0) == "classify  25/100   25 %  0:30  ETA 1:15"
    assert p.line(5, 100, 110.0) == "classify  5/100    5 %  0:10  ETA ?"
    assert p.line(1205, 4800, 100.0 + 3725.0) == "classify  1,205/4,800   25 %  1:02:05  ETA 3:05:30"
    assert stream.getvalue() == "classify  5/100    5 %  0:10  ETA ?\n"


def test_reports_are_throttled_and_the_last_one_always_shown():
    """Every 5 % or 2 s, whichever first, and the end: 100 steps at 0.01 s give 21 lines."""
    clock, stream = _Clock(), _Stream(False)
    p = Progress("scan", True, clock=clock, stream=stream)
    for k in range(1, 101):
        clock.t += 0.01
        p(k, 100)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 21 and all(LINE.match(x) for x in lines)
    assert [int(LINE.match(x)['done']) for x in lines] == [1, *range(6, 100, 5), 100]
    assert lines[-1].startswith("scan  100/100  100 %")
    stream = _Stream(False)
    p = Progress("scan", True, clock=clock, stream=stream)
    for k in range(1, 1001):  # 0.1 % steps of 3 s: each one is 2 s after the last report
        clock.t += 3.0
        p(k, 1000)
    assert len(stream.getvalue().splitlines()) == 1000


def test_on_a_terminal_a_report_overwrites_the_last_and_disabled_prints_nothing():
    clock, stream = _Clock(), _Stream(True)
    p = Progress("dim", True, clock=clock, stream=stream)
    clock.t += 1
    p(1, 2)
    clock.t += 1
    p(2, 2)
    assert stream.getvalue() == "\rdim  1/2   50 %  0:01  ETA ?\rdim  2/2  100 %  0:02  ETA 0:00\n"
    stream = _Stream(True)
    off = Progress("dim", False, clock=clock, stream=stream)
    off(1, 2)
    off(2, 2)
    assert stream.getvalue() == ""


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    return d / "pre.las", d / "post.las"


@pytest.fixture(scope="module")
def small_model(pair, tmp_path_factory):
    """A 10-tree model on the paper's descriptors: quicker to apply than the shipped one."""
    from quakescan.change.settings import PipelineSettings
    from quakescan.learning.model import save_model
    from quakescan.learning.training import TrainingPair, train

    model, _, _ = train([TrainingPair(str(pair[0]), str(pair[1]))], PipelineSettings(), n_estimators=10,
                        test_size=0.0)
    path = tmp_path_factory.mktemp("model") / "model.skops"
    save_model(model, path)
    return path


def _reports(err: str, label: str) -> list:
    return [m.groupdict() for m in map(LINE.match, err.splitlines()) if m and m["label"] == label]


def test_progress_forced_when_stderr_is_not_a_terminal_and_results_on_stdout(pair, capsys):
    pre, post = pair
    assert main(["calibrate-lod", "--pre", str(pre), "--post", str(post), "--progress"]) == 0
    out, err = capsys.readouterr()
    reports = _reports(err, "calibrate-lod")
    assert [(r["done"], r["total"]) for r in reports] == [("1", "3"), ("2", "3"), ("3", "3")]
    assert "levels of detection" in out and "calibrate-lod  " not in out
    assert main(["calibrate-lod", "--pre", str(pre), "--post", str(post)]) == 0  # not a tty: no progress
    assert capsys.readouterr().err == ""


def test_quiet_prints_nothing_on_stderr(pair, capsys, tmp_path):
    """-q before or after the command: no progress (even with --progress)."""
    pre, post = pair
    assert main(["-q", "calibrate-lod", "--pre", str(pre), "--post", str(post), "--progress"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and "levels of detection" in out
    assert main(["calibrate-lod", "--pre", str(pre), "--post", str(post), "--progress", "-q"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["-q", "survey-template", "-o", str(tmp_path / "s.json")]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.slow
def test_classify_reports_once_per_building(pair, small_model, tmp_path, capsys):
    """Six buildings: six reports, 1/6 … 6/6, whatever the tiling (the box city is one tile;
    each step is 17 %, so the reporter shows every one)."""
    pre, post = pair
    assert main(["classify", "--pre", str(pre), "--post", str(post), "--model", str(small_model), "--no-las",
                 "--no-align", "--progress", "-o", str(tmp_path / "cli")]) == 0
    out, err = capsys.readouterr()
    reports = _reports(err, "classify")
    assert [(r["done"], r["total"]) for r in reports] == [(str(k), "6") for k in range(1, 7)]
    assert reports[-1]["pct"] == "100" and reports[-1]["eta"] == "0:00"
    assert "classify: 6 buildings" in out and "classify: 6 buildings" not in err


def test_features_report_progress_with_the_same_results(pair):
    """The kernel run in 50 calls for progress gives the bytes of one call; the last report is all points."""
    from quakescan.change.features import compute_features
    from quakescan.formats.pointcloud import read_epoch

    xyz = read_epoch(pair[0]).xyz[::7]
    calls = []
    with_progress = compute_features(xyz, 1.0, ("planarity", "curvature", "point_density"),
                                     progress=lambda d, t: calls.append((d, t)))
    plain = compute_features(xyz, 1.0, ("planarity", "curvature", "point_density"))
    for name in plain:
        np.testing.assert_array_equal(with_progress[name], plain[name])
    assert 40 <= len(calls) <= 50 and calls[-1] == (len(xyz), len(xyz))
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
