"""One progress shape and one parallelism knob (issue 15, item 7): every library function that
reports progress takes `progress: ProgressCallback | None = None`, called (done, total[, stage]);
every one that runs in parallel takes `workers` (-1: every core); stage messages are log
records, never prints; every command's --threads has one default and one meaning."""
import argparse
import importlib
import inspect
import io
import logging
import pkgutil
import re

import numpy as np
import pytest

import quakescan
from quakescan.cli import build_parser
from quakescan.cli.options import THREADS_HELP
from quakescan.cli.reporting import Progress
from tests.test_cli_progress import LINE, _Clock, _Stream


def _library_functions():
    """(module.qualname, function) of every public function and method defined in the library's
    public modules (the command line, which renders progress, and quakescan.runtime.progress, which
    defines it, left out)."""
    for info in pkgutil.walk_packages(quakescan.__path__, "quakescan."):
        last = info.name.rpartition(".")[2]
        if (info.ispkg or info.name.startswith("quakescan.cli.") or info.name == "quakescan.runtime.progress"
                or last.startswith("_")):
            continue
        module = importlib.import_module(info.name)
        for _, obj in vars(module).items():
            candidates = [obj] + ([v for v in vars(obj).values() if inspect.isfunction(v)] if inspect.isclass(obj)
                                  else [])
            for fn in candidates:
                fn = inspect.unwrap(fn) if callable(fn) else fn
                if (inspect.isfunction(fn) and fn.__module__ == module.__name__
                        and not any(part.startswith("_") for part in fn.__qualname__.split("."))):
                    yield f"{module.__name__}.{fn.__qualname__}", fn


FUNCTIONS = dict(_library_functions())


def test_every_progress_parameter_has_the_one_shape():
    with_progress = {name: inspect.signature(fn).parameters["progress"] for name, fn in FUNCTIONS.items()
                     if "progress" in inspect.signature(fn).parameters}
    # the long functions of every kind: scanning, DIM, features, description, training, experiments
    for expected in ("quakescan.acquisition.scan.scan", "quakescan.acquisition.dim.simulate_dim", "quakescan.change.features.compute_features",
                     "quakescan.change.pipeline.describe_pair", "quakescan.learning.training.training_table",
                     "quakescan.learning.trainset.build", "quakescan.demo.run_demo", "quakescan.assessment.run.classify",
                     "quakescan.change.lod.calibrate", "quakescan.studies.robustness.run.run_experiment",
                     "quakescan.studies.experiment.run_paper_experiment", "quakescan.acquisition.acquire.acquire"):
        assert expected in with_progress
    wrong = {name: (str(p.annotation), p.default) for name, p in with_progress.items()
             if p.annotation != "ProgressCallback | None" or p.default is not None}
    assert wrong == {}


def test_no_other_progress_or_message_callback_is_left():
    """No signature takes `say(str)` (stage messages are log records) or the demo's
    `progress_factory(label)` (progress is `progress(done, total, stage)`)."""
    old = {name: sorted({"say", "progress_factory", "on_progress"} & set(inspect.signature(fn).parameters))
           for name, fn in FUNCTIONS.items()}
    assert {k: v for k, v in old.items() if v} == {}


def test_every_parallel_function_takes_workers_defaulting_to_every_core():
    knobs = {name: inspect.signature(fn).parameters for name, fn in FUNCTIONS.items()}
    assert {name for name, p in knobs.items() if "threads" in p} == set()
    defaults = {name: p["workers"].default for name, p in knobs.items()
                if "workers" in p and p["workers"].default is not inspect.Parameter.empty}
    assert len(defaults) >= 15 and set(defaults.values()) == {-1}


def test_the_api_takes_workers(tmp_path):
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.errors import QuakeScanError
    from tests.scenes import box_city

    for fn in (quakescan.acquire, quakescan.describe, quakescan.train, quakescan.classify):
        assert inspect.signature(fn).parameters["workers"].default == -1
    scene = box_city(rows=1, cols=1)
    with pytest.raises(QuakeScanError, match="workers: the number of worker threads must be an integer >= 1"):
        scan(scene, preset("paper"), tmp_path / "a.las", workers=0)
    with pytest.raises(TypeError, match="threads"):  # its old name is gone
        scan(scene, preset("paper"), tmp_path / "a.las", threads=2)
    assert not (tmp_path / "a.las").exists()


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from tests.scenes import scan_box_pair

    d = tmp_path_factory.mktemp("pair")
    scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    return d / "pre.las", d / "post.las"


def test_a_multi_stage_function_names_its_stages(pair):
    """training_table counts each pair's buildings as a stage named after its post-event file
    (it took progress(name, done, total) before); a single-stage callee inside it reports
    (done, total) only and gets the stage filled in."""
    from quakescan.change.settings import PipelineSettings
    from quakescan.learning.training import TrainingPair, training_table

    calls = []
    table = training_table([TrainingPair(str(pair[0]), str(pair[1]))], PipelineSettings(),
                           progress=lambda done, total, stage="": calls.append((stage, done, total)))
    assert calls == [("post.las", k, 6) for k in range(1, 7)] and len(table.y) == 6
    from quakescan.runtime.progress import in_stage

    got = []
    in_stage(in_stage(lambda done, total, stage="": got.append((done, total, stage)), "demo"), "classify")(1, 2)
    assert got == [(1, 2, "demo classify")] and in_stage(None, "demo") is None


def test_the_cli_reporter_starts_a_line_and_a_clock_per_stage():
    """Stage b starts at 20 s: its elapsed time counts from its own first report; on a terminal
    the unfinished line of stage a is ended before b's begins."""
    clock, stream = _Clock(), _Stream(False)
    p = Progress("describe", True, clock=clock, stream=stream)
    clock.t += 5
    p(1, 2, "a.las")
    clock.t += 5
    p(2, 2, "a.las")
    clock.t += 10
    p(1, 4, "b.las")
    lines = stream.getvalue().splitlines()
    assert [LINE.match(x)["label"] for x in lines] == ["describe a.las", "describe a.las", "describe b.las"]
    assert lines[1] == "describe a.las  2/2  100 %  0:05  ETA 0:00"  # the first stage's clock: its first report
    assert lines[2] == "describe b.las  1/4   25 %  0:00  ETA ?"
    tty = _Stream(True)
    p = Progress("", True, clock=clock, stream=tty)
    p(1, 2, "scan pre")
    p(1, 2, "scan post")
    assert tty.getvalue() == "\rscan pre  1/2   50 %  0:00  ETA ?\n\rscan post  1/2   50 %  0:00  ETA ?"


def test_every_threads_flag_has_one_default_and_one_meaning():
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    flags = {name: next(a for a in cmd._actions if "--threads" in a.option_strings)
             for name, cmd in sub.choices.items() if any("--threads" in a.option_strings for a in cmd._actions)}
    assert set(flags) == {"acquire", "scan", "dim", "robustness", "training-set", "experiment", "features",
                          "calibrate-lod", "train", "classify"}
    assert {(a.default, a.type, a.help) for a in flags.values()} == {(-1, int, THREADS_HELP)}
    assert "-1 for every core (default: -1)" in THREADS_HELP


def _stage_plan(tmp_path, monkeypatch):
    """A quick plan whose every table is finished on disk: build only reads them."""
    import quakescan.learning.trainset as ts
    from quakescan.learning.default_model import TABLE_SETTINGS
    from tests.trainset_fakes import finished_tables

    return finished_tables(tmp_path, monkeypatch, ts.default_plan(0, "quick"), TABLE_SETTINGS), TABLE_SETTINGS


def test_stage_messages_are_log_records(tmp_path, monkeypatch, capsys, caplog):
    from quakescan.learning.trainset import build

    plan, settings = _stage_plan(tmp_path, monkeypatch)
    steps = []
    with caplog.at_level(logging.INFO, logger="quakescan.stages"):
        build(tmp_path, plan, settings, progress=lambda done, total, stage="": steps.append((done, total)))
    assert capsys.readouterr() == ("", "")  # the library prints nothing
    messages = [r.getMessage() for r in caplog.records if r.name == "quakescan.stages"]
    assert messages[0].startswith("training set 1/3:") and messages[-1].startswith("training set: ")
    n = len(plan.cities) + len(plan.pairs)
    assert steps == [(k, n) for k in range(1, n + 1)]


def test_the_cli_shows_stage_messages_on_stderr_unless_quiet(tmp_path, monkeypatch, capsys):
    from quakescan.cli import main

    plan, _ = _stage_plan(tmp_path / "ts", monkeypatch)
    monkeypatch.setattr("quakescan.learning.trainset.default_plan", lambda *a, **k: plan)
    assert main(["training-set", "-o", str(tmp_path / "ts"), "--size", "quick"]) == 0
    out, err = capsys.readouterr()
    assert err.splitlines()[0].startswith("training set 1/3: ") and "training set 1/3" not in out
    assert main(["-q", "training-set", "-o", str(tmp_path / "ts"), "--size", "quick", "--progress"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and re.search(r"\d+ building rows", out)
    assert main(["training-set", "-o", str(tmp_path / "ts"), "--size", "quick", "--progress"]) == 0
    err = capsys.readouterr().err
    assert any(LINE.match(x) and x.startswith("training set  ") for x in err.splitlines())
    assert "training set 1/3: " in err
