"""The transfer training set as Dask tasks (`build(..., client=)`, `training-set --workers N |
--scheduler ADDRESS`): on a 2-worker LocalCluster the same table and manifest as one process,
a resumed or interrupted build redoes only what is missing, a worker killed mid-task has its
task redone with the same result.

The plan is small enough to run for real (two cities of four and three buildings, airborne
and photogrammetric clouds of them: seconds a pair), so the workers run the real generator,
scanners and descriptors: fakes patched into this process would not reach them."""
import gc
import json
import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from quakescan.acquisition.acquire import random_acquisition
from quakescan.learning.default_model import TABLE_SETTINGS
from quakescan.learning.trainset import CitySpec, PairSpec, TrainingPlan, build

distributed = pytest.importorskip("distributed")
slow = pytest.mark.slow  # a LocalCluster starts in seconds; every build generates, acquires and describes

CITIES = (CitySpec("generic_t0", "generic", "mixed", 7, 4, {0: 2, 3: 1, 5: 1}),
          CitySpec("region_t0", "region", "mixed", 8, 3, {0: 1, 4: 1, 5: 1}))


def tiny_plan() -> TrainingPlan:
    """Four pairs: cross- and same-source, a no-change pair, and one whose pre-event cloud is
    another pair's (the same scene, acquisition and seed: one file, written by one task)."""
    rng = np.random.default_rng(5)

    def draw(kind):
        return random_acquisition(kind, rng).to_json()

    g, r = CITIES[0].name, CITIES[1].name
    first = PairSpec(g, "post", draw("als"), draw("dim"), 11, 12)
    pairs = [first, PairSpec(r, "post", draw("als"), draw("als"), 21, 22),
             PairSpec(r, "pre", draw("dim"), draw("als"), 23, 24),  # no change: every building grade 0
             PairSpec(g, "post", first.pre, draw("als"), first.pre_seed, 13)]
    return TrainingPlan(list(CITIES), pairs, 0, "tiny")


def _same_tables(a, b):
    for name in ("x", "y", "building_id", "city", "pair", "density", "cells"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.names, a.cities, a.pairs, a.sensors) == (b.names, b.cities, b.pairs, b.sensors)


def _manifest(folder: Path) -> dict:
    """The manifest without its timings (seconds differ between any two runs)."""
    doc = json.loads((folder / "manifest.json").read_text())
    doc.pop("seconds")
    for p in doc["pairs"]:
        p.pop("acquire_s"), p.pop("describe_s")
    return doc


@pytest.fixture(scope="module")
def plan():
    return tiny_plan()


@pytest.fixture(scope="module")
def sequential(plan, tmp_path_factory):
    out = tmp_path_factory.mktemp("sequential")
    calls = []
    # two threads here, one in each task: the tables must not depend on it
    table = build(out, plan, TABLE_SETTINGS, workers=2, progress=lambda done, total: calls.append((done, total)))
    assert len(table.y) >= 10 and set(table.pairs) == {p.name for p in plan.pairs}
    assert set(table.y[table.pair == 2]) == {0} and set(table.y) == {0, 3, 4, 5}
    assert calls == [(k, 6) for k in range(1, 7)]
    return out, table


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        yield client


def _tables(folder: Path) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in (folder / "tables").glob("*.npz")}


@slow
def test_tasks_on_two_workers_give_the_table_and_manifest_of_one_process(plan, sequential, cluster, tmp_path):
    seq_out, seq = sequential
    calls = []
    table = build(tmp_path, plan, TABLE_SETTINGS, client=cluster,
                  progress=lambda done, total: calls.append((done, total)))
    _same_tables(table, seq)
    assert _manifest(tmp_path) == _manifest(seq_out)
    assert calls == [(k, 6) for k in range(1, 7)]  # two cities and four pairs, counted as they finish
    assert _tables(tmp_path).keys() == _tables(seq_out).keys()
    # the shared pre-event cloud is one file; every other cloud its pair's own
    assert len(list((tmp_path / "clouds").rglob("*.las"))) == 7


@slow
@pytest.mark.parametrize("where", ["here", "dask"])
def test_clouds_dropped_once_described_give_the_same_table(where, plan, sequential, cluster, tmp_path, monkeypatch):
    """`keep_clouds=False` removes each cloud after the last pair that reads it: the shared
    pre-event cloud is still there for its second pair (acquired once), none is left after."""
    import quakescan.acquisition.acquire as acquisition

    seq_out, seq = sequential
    found = []
    real = acquisition.acquire

    def watched(scene, acq, out, **kw):
        found.append(Path(out).is_file())
        return real(scene, acq, out, **kw)

    monkeypatch.setattr(acquisition, "acquire", watched)  # seen in this process only (not in Dask workers)
    table = build(tmp_path, plan, TABLE_SETTINGS, workers=1, client=cluster if where == "dask" else None,
                  keep_clouds=False)
    _same_tables(table, seq)
    assert not list((tmp_path / "clouds").rglob("*.las")) and not list((tmp_path / "clouds").rglob("*.json"))
    if where == "here":
        assert found == [False] * 6 + [True, False]  # the last pair's pre-event cloud is the first pair's
    # a rerun reads the tables and acquires nothing
    found.clear()
    again = build(tmp_path, plan, TABLE_SETTINGS, workers=1, keep_clouds=False)
    _same_tables(again, seq)
    assert found == []


def _copy_scenes_and_tables(src: Path, dst: Path, pairs: list) -> None:
    """dst holds src's scenes and the finished tables (with their fingerprints) of `pairs` only."""
    shutil.copytree(src / "scenes", dst / "scenes")
    (dst / "tables").mkdir(parents=True)
    for path in (src / "tables").iterdir():
        if any(path.name.startswith(p.name + ".") for p in pairs):
            shutil.copy2(path, dst / "tables" / path.name)


@slow
@pytest.mark.parametrize("where", ["here", "dask"])
def test_a_resumed_build_makes_only_the_missing_pairs(where, plan, sequential, cluster, tmp_path, request):
    seq_out, seq = sequential
    done = [plan.pairs[0], plan.pairs[2]]
    _copy_scenes_and_tables(seq_out, tmp_path, done)
    before = _tables(tmp_path)
    table = build(tmp_path, plan, TABLE_SETTINGS, workers=1, client=cluster if where == "dask" else None)
    _same_tables(table, seq)
    after = _tables(tmp_path)
    assert {k: after[k] for k in before} == before  # the finished tables read, not written again
    assert len(after) == 4
    clouds = {p.relative_to(tmp_path / "clouds").as_posix() for p in (tmp_path / "clouds").rglob("*.las")}
    # only the two missing pairs were acquired (the last one's pre-event cloud is the first pair's)
    missing = [plan.pairs[1], plan.pairs[3]]
    assert clouds == {f"{p.city}/{scene}.{acq['kind']}.{seed}.las" for p in missing
                      for scene, acq, seed in (("pre", p.pre, p.pre_seed), (p.post_scene, p.post, p.post_seed))}


@slow
def test_an_interrupted_client_loses_no_finished_pair(plan, sequential, cluster, tmp_path):
    seq_out, seq = sequential

    def stop_after_the_first_pair(done, total):
        if done == len(plan.cities) + 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build(tmp_path, plan, TABLE_SETTINGS, client=cluster, progress=stop_after_the_first_pair)
    finished = _tables(tmp_path)
    assert finished  # written by its task, under its name, with its fingerprint
    table = build(tmp_path, plan, TABLE_SETTINGS, client=cluster)
    _same_tables(table, seq)
    again = _tables(tmp_path)
    assert {k: again[k] for k in finished} == finished


class _DieMidTask(distributed.WorkerPlugin):
    """Kills its worker's process in the middle of the first pair task any worker starts (a
    marker file makes it once across processes): as soon as a cloud is half written under
    `folder` by it (a .part file in its city's clouds), or after `limit_s`. The nanny starts a new worker and the
    scheduler gives the lost task to a live one, which finds the half-written file."""

    def __init__(self, marker: str, folder: str, limit_s: float = 3.0):
        self.marker, self.folder, self.limit_s = marker, folder, limit_s

    def setup(self, worker):
        self.worker = worker

    def transition(self, key, start, finish, **kwargs):
        name = key if isinstance(key, str) else str(key)
        if finish == "executing" and name.startswith("trainset-pair-") and not os.path.exists(self.marker):
            Path(self.marker).write_text(f"{os.getpid()} {name}")
            clouds = Path(self.folder) / "clouds" / name.removeprefix("trainset-pair-").split(".")[0]
            threading.Thread(target=self._die, args=(clouds,), daemon=True).start()

    def _die(self, clouds: Path):
        end = time.monotonic() + self.limit_s
        while time.monotonic() < end and not any(clouds.glob("*.part")):
            time.sleep(0.002)
        with open(self.marker, "a") as f:  # what the task run again finds
            f.write("".join(f"\n{p}" for p in clouds.glob("*.part")))
        os._exit(1)


@slow
def test_a_worker_killed_mid_task_has_its_pair_redone_with_the_same_table(plan, sequential, tmp_path):
    seq_out, seq = sequential
    marker = tmp_path / "killed"
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        pids = set(client.run(os.getpid).values())
        client.register_plugin(_DieMidTask(str(marker), str(tmp_path / "out")))
        table = build(tmp_path / "out", plan, TABLE_SETTINGS, client=client)
        assert marker.is_file() and int(marker.read_text().split()[0]) in pids  # a worker did die
        assert set(client.run(os.getpid).values()) != pids  # and was replaced
    _same_tables(table, seq)
    assert _manifest(tmp_path / "out") == _manifest(seq_out)


@slow
def test_the_cli_runs_on_a_local_cluster_and_names_its_dashboard(plan, sequential, tmp_path, monkeypatch, capsys):
    import quakescan.learning.trainset as ts
    from quakescan.cli import main

    seq_out, seq = sequential
    _copy_scenes_and_tables(seq_out, tmp_path / "ts", plan.pairs[:3])
    monkeypatch.setattr(ts, "default_plan", lambda *a, **k: plan)  # the command's plan, made tiny
    assert main(["training-set", "-o", str(tmp_path / "ts"), "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "Dask: a LocalCluster of 2 workers; dashboard http" in printed
    assert f"{len(seq.y)} building rows" in printed
    assert _manifest(tmp_path / "ts") == _manifest(seq_out)


def test_bad_cluster_options_are_named(tmp_path, capsys):
    from quakescan.cli import main

    args = ["training-set", "-o", str(tmp_path / "ts"), "--size", "quick"]
    assert main(args + ["--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(args + ["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"])
    assert e.value.code == 2
    assert "argument --scheduler: not allowed with argument --workers" in capsys.readouterr().err
    assert main(args + ["--scheduler", "tpc://127.0.0.1:8786"]) == 2  # a typo in the scheme: at once, not a traceback
    assert "--scheduler tpc://127.0.0.1:8786: not a reachable Dask scheduler address" in capsys.readouterr().err
    # the client that failed is closed now: left to the garbage collector, it would close
    # while the next client starts and hang it (the lock of distributed's loop runner)
    assert not [c for c in gc.get_objects() if isinstance(c, distributed.Client) and c.status == "connecting"]
    assert not (tmp_path / "ts" / "scenes").exists()  # nothing was started


@slow
def test_an_unreachable_scheduler_is_named(tmp_path, capsys):
    from quakescan.cli import main

    assert main(["training-set", "-o", str(tmp_path / "ts"), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "--scheduler tcp://127.0.0.1:9: cannot reach the Dask scheduler" in capsys.readouterr().err
