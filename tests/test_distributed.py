"""classify as Dask tasks (`quakescan.distributed`): the same files as one process, byte for
byte, on a 2-worker LocalCluster; a worker killed mid-task; an interrupted client resumed."""
import filecmp
import json
import os
from pathlib import Path

import laspy
import numpy as np
import pytest

from quakescan.assessment.run import classify
from quakescan.learning.default_model import DEFAULT_MODEL
from quakescan.learning.model import load_model, save_model
from tests.scenes import scan_box_pair

distributed = pytest.importorskip("distributed")
slow = pytest.mark.slow  # a LocalCluster starts in seconds; each run classifies the box city twice

SAME_FILES = ["buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.html"]
BLOCK_CELLS = 7  # 7 m blocks: every building and tile spans several, so block edges are crossed everywhere


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        yield client


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The box city (buildings 2 and 4 collapsed) and the shipped model with 25 m tiles: six
    tiles, one per building (the street pitch is 22 m)."""
    d = tmp_path_factory.mktemp("dask_pair")
    scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    m = load_model(DEFAULT_MODEL)
    m.split = {**m.split, "tile_m": 25.0}
    save_model(m, d / "model.skops")
    return d


def _same_outputs(a: Path, b: Path, las: str | None = "post_grades.las"):
    for name in SAME_FILES:
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    if las:
        x, y = laspy.read(a / las), laspy.read(b / las)
        assert x.header.point_count == y.header.point_count
        for dim in x.points.array.dtype.names:
            np.testing.assert_array_equal(x.points.array[dim], y.points.array[dim], err_msg=dim)


def _run(pair, out, client, **kw):
    from quakescan.distributed.engine import classify_distributed

    return classify_distributed(pair / "pre.las", pair / "post.las", out, client, model_path=pair / "model.skops",
                                block_cells=BLOCK_CELLS, chunk_points=50_000, **kw)


@pytest.fixture(scope="module")
def single(pair, tmp_path_factory):
    out = tmp_path_factory.mktemp("single")
    summary = classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")
    return out, summary


@slow
def test_two_workers_write_the_files_one_process_writes(pair, single, cluster, tmp_path):
    out, s1 = single
    s2 = _run(pair, tmp_path / "dask", cluster)
    _same_outputs(out, tmp_path / "dask")
    assert s2["dask"]["workers"] == 2 and s2["points"] == s1["points"]
    assert s2["registration"] == s1["registration"]
    assert not (tmp_path / "dask" / ".blocks").exists()  # the blocks go when the results are written
    rows = (out / "buildings.csv").read_text().splitlines()
    assert len(rows) == 7  # six buildings, described, not all "not assessable"
    assert sum(",model," in r or ",no change," in r for r in rows) >= 4


@slow
def test_no_align_submits_no_registration_check_and_says_so(pair, cluster, tmp_path):
    summary = _run(pair, tmp_path / "dask", cluster, align=False, write_las=False)
    assert summary["registration"] == {"mode": "off", "checked": False}
    single = classify(pair / "pre.las", pair / "post.las", tmp_path / "one", model_path=pair / "model.skops",
                      align=False, write_las=False)
    assert single["registration"] == summary["registration"]
    for name in SAME_FILES:
        assert filecmp.cmp(tmp_path / "one" / name, tmp_path / "dask" / name, shallow=False), name


@slow
def test_an_offset_post_epoch_is_aligned_as_one_process_aligns_it(pair, cluster, tmp_path, caplog):
    """0.5 m up (the flat ground shows a vertical offset, not a horizontal one): beyond the
    model's tolerance, so both runs align it; the workers move the points and count the
    densities in the moved frame. The check runs in a worker; its warning reaches the
    client's log all the same."""
    las = laspy.read(pair / "post.las")
    las.z = np.asarray(las.z) + 0.5
    las.write(tmp_path / "post_shifted.las")
    single = classify(pair / "pre.las", tmp_path / "post_shifted.las", tmp_path / "single",
                      model_path=pair / "model.skops")
    assert single["registration"]["applied"]
    from quakescan.distributed.engine import classify_distributed

    caplog.clear()
    with caplog.at_level("INFO", logger="quakescan"):
        dask = classify_distributed(pair / "pre.las", tmp_path / "post_shifted.las", tmp_path / "dask", cluster,
                                    model_path=pair / "model.skops", block_cells=BLOCK_CELLS, chunk_points=50_000)
    assert any(r.levelname == "WARNING" and "aligned the post-event epoch" in r.getMessage() for r in caplog.records)
    assert dask["registration"] == single["registration"]
    assert dask["alignment"]["transform"] == single["alignment"]["transform"]  # ICP rounded: the same in every run
    assert dask["alignment"]["rmse_after_m"] == pytest.approx(single["alignment"]["rmse_after_m"], rel=1e-9)
    # the tiles started unmoved before the check answered were described again, moved
    _same_outputs(tmp_path / "single", tmp_path / "dask")
    assert not list((tmp_path / "dask").glob(".checkpoint*"))


class _DieOnce(distributed.WorkerPlugin):
    """Kills its worker's process the first time any worker starts a task whose key begins
    with `prefix` (a marker file makes it once across processes): the nanny starts a new
    worker and the scheduler gives the lost task to a live one."""

    def __init__(self, marker: str, prefix: str = "tile-"):
        self.marker, self.prefix = marker, prefix

    def setup(self, worker):
        self.worker = worker

    def transition(self, key, start, finish, **kwargs):
        name = key if isinstance(key, str) else str(key)
        if finish == "executing" and name.startswith(self.prefix) and not os.path.exists(self.marker):
            Path(self.marker).write_text(str(os.getpid()))
            os._exit(1)


@slow
@pytest.mark.parametrize("prefix", ["stream-", "group_roof_cells-", "registration_task-", "tile-", "graded-"])
def test_a_worker_killed_mid_task_has_its_task_redone_and_the_result_is_the_same(pair, single, tmp_path, prefix):
    # every kind of task the run submits: streaming a part, counting densities, the
    # registration check (it reads its samples from the tiling's files: data scattered to a
    # worker would die with it, and the check's future with it, "already forgotten"), a tile,
    # a part of the graded cloud
    marker = tmp_path / "killed"
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        pids = set(client.run(os.getpid).values())
        client.register_plugin(_DieOnce(str(marker), prefix))
        _run(pair, tmp_path / "dask", client)
        assert marker.is_file() and int(marker.read_text()) in pids  # a worker did die mid-task
    _same_outputs(single[0], tmp_path / "dask")


@slow
def test_an_interrupted_client_resumes_from_its_finished_tiles_and_blocks(pair, single, cluster, tmp_path,
                                                                         monkeypatch):
    from quakescan.distributed import tasks

    out = tmp_path / "dask"
    calls = []

    def stop_after_two(done, total, stage=""):
        if stage:  # the tiling's points: streamed whole before the first tile
            assert stage in ("tiling pre", "tiling post") and 0 < done <= total
            return
        calls.append(done)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _run(pair, out, cluster, progress=stop_after_two)
    assert (out / ".blocks" / "manifest.json").is_file() and (out / ".checkpoint.jsonl").is_file()

    def no_streaming(*a, **k):  # submitted to the workers in its place, where it would raise
        raise AssertionError("the blocks of the interrupted run are valid: no streaming again")

    monkeypatch.setattr(tasks, "stream_part", no_streaming)
    summary = _run(pair, out, cluster)
    assert summary["resumed_buildings"] >= 2
    _same_outputs(single[0], out)


class _SlowRegistration(distributed.WorkerPlugin):
    """Makes the registration check of its workers answer `seconds` late."""

    def __init__(self, seconds: float):
        self.seconds = seconds

    def setup(self, worker):
        import time

        from quakescan.distributed import tasks

        check, seconds = tasks.registration_task, self.seconds
        if getattr(check, "slowed", False):
            return

        def late(*a, **k):
            time.sleep(seconds)
            return check(*a, **k)
        late.slowed = True
        tasks.registration_task = late  # a task names its function: the workers look it up here


@slow
def test_tiles_finished_before_the_registration_check_answers_are_kept_for_a_resumed_run(pair, single, tmp_path):
    """The tiles start unmoved while the check runs. A client interrupted before it answers
    keeps their rows (a checkpoint of their own), and the resumed run uses them once its own
    check finds no alignment: the files one process writes."""
    from quakescan.distributed.engine import UNMOVED_CHECKPOINT

    out = tmp_path / "dask"
    calls = []

    def stop_after_two(done, total, stage=""):
        if not stage:
            calls.append(done)
            if len(calls) == 2:
                raise KeyboardInterrupt

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        client.register_plugin(_SlowRegistration(60.0))
        with pytest.raises(KeyboardInterrupt):
            _run(pair, out, client, progress=stop_after_two)
    lines = (out / UNMOVED_CHECKPOINT).read_text().splitlines()
    assert len(lines) >= 3  # the fingerprint and the rows of two buildings
    assert len((out / ".checkpoint.jsonl").read_text().splitlines()) == 1  # no row: the check had not answered
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        summary = _run(pair, out, client)
    assert summary["resumed_buildings"] >= 2
    _same_outputs(single[0], out)
    assert not list(out.glob(".checkpoint*"))


@slow
def test_a_paper_descriptor_tile_whose_nearest_points_lie_beyond_its_halo_is_widened(tmp_path, cluster):
    """Building 2 loses all but a 2 m strip at one end: its query points' nearest post-event
    points lie up to ~12 m away, beyond the first halo (radius + 10 m) from the far end."""
    from quakescan.change.settings import PipelineSettings
    from quakescan.distributed.engine import classify_distributed
    from quakescan.learning.training import TrainingPair, train

    scan_box_pair(tmp_path, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    post = laspy.read(tmp_path / "post.las")
    ids = np.asarray(post["building_id"])
    b2 = ids == 2
    x = np.asarray(post.x)
    strip = b2 & (x <= x[b2].min() + 2.0)
    post.points = post.points[~b2 | strip]
    post.write(tmp_path / "post_strip.las")
    model, _, _ = train([TrainingPair(str(tmp_path / "pre.las"), str(tmp_path / "post.las"))],
                        PipelineSettings(tile_m=25.0), n_estimators=5, test_size=0.0)
    save_model(model, tmp_path / "paper.skops")
    single = classify(tmp_path / "pre.las", tmp_path / "post_strip.las", tmp_path / "single",
                      model_path=tmp_path / "paper.skops", write_las=False)
    dask = classify_distributed(tmp_path / "pre.las", tmp_path / "post_strip.las", tmp_path / "dask", cluster,
                                model_path=tmp_path / "paper.skops", block_cells=BLOCK_CELLS, write_las=False)
    assert dask["dask"]["tiles_widened"] >= 1
    _same_outputs(tmp_path / "single", tmp_path / "dask", las=None)
    assert single["buildings"] == dask["buildings"] == 6


@slow
def test_the_cli_runs_on_a_local_cluster_and_names_its_dashboard(pair, single, tmp_path, capsys):
    """... and keeps Dask's housekeeping (scheduler started, workers registered, closed: INFO
    records of the `distributed` logger, which writes them to stderr with a handler of its
    own) out of the run unless -v asks for details."""
    import logging

    from quakescan.cli import main

    class Keep(logging.Handler):
        def __init__(self):
            super().__init__(logging.DEBUG)
            self.records = []

        def emit(self, record):
            self.records.append(record)

    keep, dask_log = Keep(), logging.getLogger("distributed")
    level = dask_log.level
    dask_log.addHandler(keep)
    try:
        out = tmp_path / "cli"
        assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "--model",
                     str(pair / "model.skops"), "--workers", "2", "--memory-limit", "1GB", "-o", str(out)]) == 0
    finally:
        dask_log.removeHandler(keep)
    printed = capsys.readouterr().out
    assert "Dask: a LocalCluster of 2 workers; dashboard http" in printed
    assert [r.getMessage() for r in keep.records if r.levelno < logging.WARNING] == []
    assert dask_log.level == level  # as it was, once the command ends
    _same_outputs(single[0], out)


@slow
def test_the_graded_cloud_is_made_in_parts_by_the_workers_and_compressed_as_one_process_compresses(
        pair, cluster, tmp_path, monkeypatch):
    """The workers make the graded cloud's records of the post-event file's parts; the client
    puts them behind one header: the .laz one process writes, byte for byte but the header's
    creation day."""
    from quakescan.distributed import engine as dc

    made = []
    real = dc.part_bounds
    monkeypatch.setattr(dc, "part_bounds", lambda *a: made.append(real(*a)) or made[-1])
    single = classify(pair / "pre.las", pair / "post.las", tmp_path / "single", model_path=pair / "model.skops",
                      laz=True)
    dask = _run(pair, tmp_path / "dask", cluster, laz=True)
    assert single["post_grades"].endswith(".laz") and dask["post_grades"].endswith(".laz")
    assert len(made[-1]) - 1 >= 4  # the graded cloud's parts: two a worker at least
    _same_outputs(tmp_path / "single", tmp_path / "dask", las="post_grades.laz")
    a, b = ((tmp_path / d / "post_grades.laz").read_bytes() for d in ("single", "dask"))
    assert len(a) == len(b) and sum(x != y for x, y in zip(a, b)) <= 4  # at most the creation day and year
    assert not (tmp_path / "dask" / ".graded").exists()


@slow
def test_bad_cluster_options_are_named(tmp_path, pair, capsys):
    from quakescan.cli import main

    args = ["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "-o", str(tmp_path / "o")]
    assert main(args + ["--workers", "0"]) != 0
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err
    assert main(args + ["--scheduler", "tcp://127.0.0.1:9"]) != 0
    assert "--scheduler tcp://127.0.0.1:9: cannot reach the Dask scheduler" in capsys.readouterr().err


def test_blocks_hold_every_point_once_and_read_back_in_file_order(pair, tmp_path):
    from quakescan.distributed.block_store import stored_points, stored_record
    from quakescan.distributed.reading import read_box, read_records
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch

    f = open_epoch_file(pair / "pre.las")
    origin = default_origin(f)
    stats = stream_epoch(f, origin, tmp_path / "pre", block_cells=BLOCK_CELLS, chunk_points=33_333)
    rec = read_records(tmp_path / "pre", [tuple(k) for k in stats.blocks])
    np.testing.assert_array_equal(rec["index"], np.arange(f.n))
    from quakescan.formats.pointcloud import read_epoch

    e = read_epoch(pair / "pre.las")
    np.testing.assert_array_equal(f.local_xyz(rec["X"], rec["Y"], rec["Z"], origin), e.xyz)
    np.testing.assert_array_equal(rec["building_id"], e.building_id)
    ids, counts = np.unique(e.building_id[e.building_id > 0], return_counts=True)
    assert stats.counts == dict(zip(ids.tolist(), counts.tolist()))
    assert stats.n == f.n
    # building points have files of their own: the densities read them alone
    keys = [tuple(k) for k in stats.blocks]
    only = read_records(tmp_path / "pre", keys, buildings_only=True)
    np.testing.assert_array_equal(only, rec[rec["building_id"] > 0])
    assert 0 < len(only) < len(rec)
    # one file for the epoch streamed whole; each block's two kinds are runs of their own in it
    assert sorted(p.name for p in (tmp_path / "pre").iterdir()) == ["blocks.index.npy", "part0.bin", "record.json"]
    index = np.load(tmp_path / "pre" / "blocks.index.npy")
    assert index.flags.f_contiguous and (np.diff(index[:, 0]) > 0).all()  # one run a block and kind
    assert index[:, 3].sum() == f.n and stored_points(tmp_path / "pre", keys) == f.n
    # the pair's IDs are uint32 (as QuakeScan writes them): 21-byte records, the IDs' bits kept
    record = stored_record(tmp_path / "pre")
    assert record.itemsize == 21 and record["building_id"] == np.uint32 and record["index"] == np.uint32
    stored = np.fromfile(tmp_path / "pre" / "part0.bin", dtype=record)
    assert (tmp_path / "pre" / "part0.bin").stat().st_size == 21 * f.n
    for key, _, offset, count in index.tolist():
        run = stored[offset:offset + count]
        assert ((run["building_id"] > 0) == bool(key % 2)).all() and (np.diff(run["index"]) > 0).all()
    # a box read (what a tile task reads): exactly the points inside it, edges included, in file order
    box = np.array([np.quantile(e.xyz[:, :2], 0.3, axis=0), np.quantile(e.xyz[:, :2], 0.6, axis=0)])
    box[0, 0] = e.xyz[123, 0]  # a point on the edge is kept
    inside = np.all((e.xyz[:, :2] >= box[0]) & (e.xyz[:, :2] <= box[1]), axis=1)
    rec, xyz = read_box(tmp_path / "pre", f, origin, box, BLOCK_CELLS)
    np.testing.assert_array_equal(rec["index"], np.flatnonzero(inside))
    np.testing.assert_array_equal(xyz, e.xyz[inside])
    rec, xyz = read_box(tmp_path / "pre", f, origin, box + 1e6, BLOCK_CELLS)
    assert len(rec) == 0 and xyz.shape == (0, 3)


@slow
def test_local_cluster_workers_allocate_like_one_process_run_no_profiler_and_close_quietly_and_quickly(monkeypatch):
    """Our workers allocate as the command does (`quakescan.runtime.allocator`), not with
    Dask's MALLOC_TRIM_THRESHOLD_ (which fixes glibc's mmap threshold at 128 KiB and made
    tiles 14 % slower in a worker), even where an earlier LocalCluster of this process left
    Dask's value in the environment: a 100 MB array lands in the heap and stays there once
    freed; and no worker samples its task's stack for Dask's profiler (CPU taken
    from the other worker on two cores): a task of half a second leaves no sample (some 50
    with the profiler on) once the profile's 1 s cycle has passed."""
    import time

    import logging

    from quakescan.distributed.cluster import dask_client, quiet_workers_for_shutdown
    from quakescan.runtime.allocator import ENVIRON, where_an_array_lands

    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    with dask_client(1, memory_limit="1GB") as client:
        seen = client.run(lambda: {name: os.environ.get(name) for name in ENVIRON})
        landed = client.run(where_an_array_lands)
        landed_in_a_task = client.submit(where_an_array_lands, pure=False).result()  # the task thread's arena
        client.submit(time.sleep, 0.5, pure=False).result()
        time.sleep(1.2)
        samples = client.profile()["count"]
        still_collecting = client.run(lambda: __import__("gc").get_freeze_count() == 0)
        quiet_workers_for_shutdown(client)
        levels = client.run(lambda: logging.getLogger("distributed").level)
        frozen = client.run(lambda: __import__("gc").get_freeze_count() > 0)
    assert list(seen.values()) == [ENVIRON]
    mb = 100 << 20  # in the heap, not a mapping of its own, and still there once freed
    assert list(landed.values()) == [{"mapped": 0, "kept": pytest.approx(mb, rel=0.05)}]
    assert landed_in_a_task["mapped"] == 0
    assert samples == 0
    # the cluster's closing says nothing: no worker logs even an error once it is asked to close
    assert set(levels.values()) == {logging.CRITICAL + 1}
    # and its workers end without Python's last collections (0.5 s of each one's core)
    assert list(still_collecting.values()) == [True] and list(frozen.values()) == [True]


def test_an_array_is_mapped_anew_by_default_and_kept_in_the_heap_once_tuned():
    """The measure the worker test relies on, in fresh processes: glibc's defaults map a 100 MB
    array on its own and give it back when freed; the command's settings put it in the heap
    and keep it there, but not in a thread (its own arena), unless all threads share one
    arena (`MALLOC_ARENA_MAX=1`, as the workers do)."""
    import subprocess
    import sys

    probe = ("import threading; from quakescan.runtime import allocator as a; {tune}out = {{}}; "
             "t = threading.Thread(target=lambda: out.update(a.where_an_array_lands())); t.start(); t.join(); "
             "print(dict(main=a.where_an_array_lands(), thread=out))")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    landed = {}
    for name, tune, extra in (("default", "", {}), ("tuned", "a.tune_allocator(); ", {}),
                              ("one arena", "a.tune_allocator(); ", {"MALLOC_ARENA_MAX": "1"})):
        out = subprocess.run([sys.executable, "-c", probe.format(tune=tune)], capture_output=True, text=True,
                             env={**env, **extra}, timeout=120)
        assert out.returncode == 0, out.stderr
        landed[name] = json.loads(out.stdout.strip().replace("'", '"'))
    mb = 100 << 20
    default, tuned, one_arena = landed["default"], landed["tuned"], landed["one arena"]
    assert default["main"]["mapped"] == pytest.approx(mb, rel=0.05) and default["main"]["kept"] < mb / 100
    # run by the thread first, the heap of the main thread still takes it whole
    assert tuned["main"] == {"mapped": 0, "kept": pytest.approx(mb, rel=0.05)}
    # a thread's own arena cannot hold it whatever the thresholds: mapped anew, as in a worker's task
    assert tuned["thread"]["mapped"] == pytest.approx(mb, rel=0.05) and tuned["thread"]["kept"] < mb / 100
    # with one arena (the workers' `MALLOC_ARENA_MAX`), the thread's array is in the heap and kept
    assert one_arena["thread"] == {"mapped": 0, "kept": pytest.approx(mb, rel=0.05)}


def test_a_tile_over_the_memory_budget_is_split_into_quarters_by_building_centre():
    from quakescan.distributed.engine import MAX_SPLIT_DEPTH, split_tile

    # a 100 m tile (1, 2) holding four buildings, one in each quarter, and 100 bytes a building
    centres = {1: (110.0, 210.0), 2: (160.0, 210.0), 3: (110.0, 260.0), 4: (190.0, 290.0)}

    def estimate(key, bids):
        return 100.0 * len(bids)

    assert split_tile((1, 2), [1, 2, 3, 4], centres.get, 100.0, estimate, 400.0) == [((1, 2), [1, 2, 3, 4])]
    assert split_tile((1, 2), [1, 2, 3, 4], centres.get, 100.0, estimate, 250.0) == [
        ((1, 2, 0, 0), [1]), ((1, 2, 0, 1), [3]), ((1, 2, 1, 0), [2]), ((1, 2, 1, 1), [4])]
    # two buildings in one quarter: only that quarter is split again, into its own quarters
    centres[2] = (135.0, 215.0)
    parts = split_tile((1, 2), [1, 2, 3, 4], centres.get, 100.0, estimate, 150.0)
    assert parts == [((1, 2, 0, 0, 0, 0), [1]), ((1, 2, 0, 0, 1, 0), [2]), ((1, 2, 0, 1), [3]), ((1, 2, 1, 1), [4])]
    assert sorted(b for _, bids in parts for b in bids) == [1, 2, 3, 4]  # every building in exactly one part
    # buildings sharing one centre cannot be parted: the split stops at its depth limit
    same = split_tile((1, 2), [5, 6], lambda b: (150.0, 250.0), 100.0, estimate, 50.0)
    assert len(same) == 1 and same[0][1] == [5, 6] and len(same[0][0]) == 2 + 2 * MAX_SPLIT_DEPTH


@slow
def test_tiles_too_large_for_the_workers_memory_are_split_and_give_the_same_files(tmp_path, monkeypatch):
    """The shipped model's 150 m tiles hold all six buildings of the box city together; with a
    per-point cost that puts every tile over a 1 GB worker's budget the client splits them down
    to one building a task, and the files are those of one process with whole tiles."""
    from quakescan.distributed import engine as dc

    scan_box_pair(tmp_path, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    single = classify(tmp_path / "pre.las", tmp_path / "post.las", tmp_path / "single")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="1GB") as c, distributed.Client(c) as client:
        assert dc.tile_memory_budget(client) == pytest.approx(dc.TILE_MEMORY_SHARE * 1e9, rel=0.01)
        monkeypatch.setattr(dc, "DESCRIBE_BYTES_PER_POINT", 10 ** 6)  # every tile over the budget
        summary = dc.classify_distributed(tmp_path / "pre.las", tmp_path / "post.las", tmp_path / "dask", client,
                                          block_cells=BLOCK_CELLS, chunk_points=50_000)
    assert summary["dask"]["tiles_split"] >= 4
    assert summary["buildings"] == single["buildings"] == 6
    _same_outputs(tmp_path / "single", tmp_path / "dask")


def test_block_runs_read_back_exactly_and_a_cut_stream_leaves_nothing(pair, tmp_path):
    """Runs of two parts read in any grouping give the records at their offsets; runs that
    follow on in a file are one read. A part file shorter than its index is named, and a
    stream cut mid-way leaves neither a part file nor an index."""
    from quakescan.distributed.block_store import (
        INDEX_NAME,
        block_runs,
        join_part_indexes,
        part_path,
        read_runs,
        stored_record,
    )
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch
    from quakescan.formats.pointcloud import PointCloudError

    f = open_epoch_file(pair / "pre.las")
    origin = default_origin(f)
    folder = tmp_path / "parts"
    half = f.n // 2
    for part, (a, b) in enumerate(((0, half), (half, f.n))):
        stream_epoch(f, origin, folder, block_cells=BLOCK_CELLS, chunk_points=25_000, part=part,
                            start=a, stop=b, segment_points=60_000)
    join_part_indexes(folder, 2)
    index = np.load(folder / INDEX_NAME)
    record = stored_record(folder)
    files = [np.fromfile(part_path(folder, p), dtype=record) for p in (0, 1)]
    assert index[:, 3].sum() == f.n == sum(len(x) for x in files)
    rng = np.random.default_rng(3)
    for pick in (np.arange(len(index)), rng.choice(len(index), 9, replace=False), np.zeros(0, int)):
        runs = index[np.sort(pick)][:, 1:4]
        rec, starts = read_runs(folder, runs)
        assert len(starts) == len(runs) + 1 and starts[-1] == len(rec) == runs[:, 2].sum()
        for (part, offset, count), a in zip(runs.tolist(), starts[:-1].tolist()):
            np.testing.assert_array_equal(rec[a:a + count], files[part][offset:offset + count])
    # a part's file cut short (a disk that filled up behind the manifest): named, not read as garbage
    with open(part_path(folder, 1), "r+b") as fh:
        fh.truncate(record.itemsize * (len(files[1]) - 5))
    ones = index[index[:, 1] == 1]
    last = ones[np.argmax(ones[:, 2])][None, 1:4]  # the run at the file's end
    with pytest.raises(PointCloudError, match=r"part1\.bin: block file ends 105 bytes early"):
        read_runs(folder, last)
    with pytest.raises(FileNotFoundError, match="no block index"):
        block_runs(tmp_path / "nowhere", [(0, 0)])

    def cut(done, total):
        if done > 50_000:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        stream_epoch(f, origin, tmp_path / "cut", block_cells=BLOCK_CELLS, chunk_points=25_000, on_chunk=cut)
    assert list((tmp_path / "cut").iterdir()) == []


def test_an_epoch_streamed_in_parts_is_the_epoch_streamed_whole(pair, tmp_path):
    """Three ranges of the file's points, each into its own part file of several segments:
    the same records in every block, in the same order, and the same stats (counts, boxes,
    samples, map, hulls)."""
    from quakescan.distributed.block_store import block_runs, join_part_indexes
    from quakescan.distributed.engine import part_bounds
    from quakescan.distributed.reading import read_records
    from quakescan.distributed.streaming import default_origin, merge_stats, open_epoch_file, stream_epoch

    f = open_epoch_file(pair / "pre.las")
    origin = default_origin(f)
    kw = dict(block_cells=BLOCK_CELLS, chunk_points=20_000, with_hulls=True, sample=(f.n, 5_000), map_step=7)
    whole = stream_epoch(f, origin, tmp_path / "whole", **kw)
    bounds = part_bounds(f.n, 1, 40_000)
    assert bounds[0] == 0 and bounds[-1] == f.n and len(bounds) >= 3
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "epoch.json").write_text('{"parts": %d}' % (len(bounds) - 1))
    # parts of several segments each (a segment every two chunks): a block has runs in several places
    parts = [stream_epoch(f, origin, tmp_path / "parts", part=k, start=a, stop=b, segment_points=30_000, **kw)
             for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))]
    join_part_indexes(tmp_path / "parts", len(parts))
    assert len(block_runs(tmp_path / "parts", [tuple(k) for k in whole.blocks])) > 2 * len(
        block_runs(tmp_path / "whole", [tuple(k) for k in whole.blocks]))
    merged = merge_stats(parts)
    assert merged.n == whole.n == f.n and merged.counts == whole.counts
    assert merged.lo == whole.lo and merged.hi == whole.hi and merged.bounds == whole.bounds
    assert merged.blocks == whole.blocks
    np.testing.assert_array_equal(merged.stable_sample, whole.stable_sample)
    np.testing.assert_array_equal(merged.map_xy, whole.map_xy)
    assert set(merged.hulls) == set(whole.hulls)
    for b in whole.hulls:
        np.testing.assert_array_equal(merged.hulls[b], whole.hulls[b])
    for key in whole.blocks:
        a = read_records(tmp_path / "whole", [tuple(key)])
        b = read_records(tmp_path / "parts", [tuple(key)])
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not hasattr(os, "POSIX_FADV_DONTNEED"), reason="a system without posix_fadvise drops nothing")
def test_streamed_pages_are_dropped_exactly_once_each_and_change_nothing_stored(pair, tmp_path, monkeypatch):
    """A pair too large for the page cache: each part tells the kernel to drop exactly the
    byte range of its points (offset + index x record size), chunk after chunk, and stores
    the records and stats it stores without. A compressed copy drops nothing: its points'
    bytes are not a range of their index."""
    from quakescan.distributed.streaming import default_origin, open_epoch_file
    from quakescan.distributed.tasks import stream_part

    f = open_epoch_file(pair / "pre.las")
    origin = default_origin(f)
    with laspy.open(pair / "pre.las") as reader:
        header = reader.header
    calls = []
    monkeypatch.setattr(os, "posix_fadvise", lambda fd, offset, length, advice: calls.append((offset, length, advice)),
                        raising=False)
    (a, b) = (f.n // 3, f.n - 7)
    args = (origin.tolist(), 0, a, b, BLOCK_CELLS, None, True, (f.n, 5_000), 7, 9_999)
    kept = stream_part(str(tmp_path / "kept"), f.to_json(), *args)
    assert calls == []  # the box city's few MB: the cache holds them
    dropped = stream_part(str(tmp_path / "dropped"), f.to_json(), *args, pair_bytes=10 ** 15)
    size, first = header.point_format.size, header.offset_to_point_data
    assert {c[2] for c in calls} == {os.POSIX_FADV_DONTNEED}
    assert [c[0] for c in calls] == [first + a * size + sum(c[1] for c in calls[:i]) for i in range(len(calls))]
    assert sum(c[1] for c in calls) == (b - a) * size and len(calls) == -(-(b - a) // 9_999)
    assert dropped.counts == kept.counts and dropped.lo == kept.lo and dropped.bounds == kept.bounds
    np.testing.assert_array_equal(dropped.stable_sample, kept.stable_sample)
    assert (tmp_path / "kept" / "part0.bin").read_bytes() == (tmp_path / "dropped" / "part0.bin").read_bytes()
    np.testing.assert_array_equal(np.load(tmp_path / "kept" / "part0.index.npy"),
                                  np.load(tmp_path / "dropped" / "part0.index.npy"))
    laz = tmp_path / "pre.laz"
    laspy.read(pair / "pre.las").write(laz)
    calls.clear()
    stream_part(str(tmp_path / "laz"), open_epoch_file(laz).to_json(), *args, pair_bytes=10 ** 15)
    assert calls == []


def test_the_page_cache_is_said_to_hold_a_pair_up_to_half_the_machines_memory():
    from quakescan.distributed.streaming import PAGE_CACHE_SHARE, page_cache_cannot_hold

    assert PAGE_CACHE_SHARE == 0.5
    assert not page_cache_cannot_hold(None) and not page_cache_cannot_hold(0)
    assert not page_cache_cannot_hold(12, memory_bytes=24) and page_cache_cannot_hold(13, memory_bytes=24)
    # this machine's memory when not given: a pair of a petabyte does not fit, of a byte it does
    assert page_cache_cannot_hold(10 ** 15) and not page_cache_cannot_hold(1)


def test_blocks_are_deleted_beside_the_results_their_manifest_first(tmp_path, monkeypatch):
    """Once every tile is described the store goes in a thread; its manifest is gone before
    the thread starts, so a run interrupted while the rest is deleted tiles again instead of
    reading blocks half deleted."""
    import threading

    from quakescan.distributed import engine as dc

    from quakescan.runtime.output_folder import own_subfolder

    store = own_subfolder(tmp_path / ".blocks")
    (store / "pre").mkdir(parents=True)
    (store / "pre" / "part0.bin").write_bytes(b"x" * 100)
    (store / dc.MANIFEST).write_text("{}")
    release, real = threading.Event(), dc.remove_own_subfolder

    def slow_remove(path):
        release.wait(10)
        return real(path)

    monkeypatch.setattr(dc, "remove_own_subfolder", slow_remove)
    thread = dc._delete_store(store)
    assert not (store / dc.MANIFEST).exists() and (store / "pre" / "part0.bin").is_file()
    assert dc.kept_epochs(store, "any", 50) is None
    release.set()
    thread.join(10)
    assert not thread.is_alive() and not store.exists()


def test_blocks_of_an_interrupted_run_are_kept_only_for_the_same_inputs_and_layout(tmp_path):
    from quakescan.distributed.block_store import LAYOUT, save_arrays, write_manifest
    from quakescan.distributed.engine import MANIFEST, kept_epochs
    from quakescan.distributed.streaming import EpochStats
    from quakescan.runtime.output_folder import FOLDER_MARKER

    (tmp_path / FOLDER_MARKER).write_text("")  # the store is QuakeScan's (tests/test_safe_folder_deletes.py)
    stats = EpochStats(n=3, counts={7: 3}, lo={7: (0.0, 0.0)}, hi={7: (1.0, 1.0)}, blocks=[[0, 0]])
    for name in ("pre", "post"):
        save_arrays(tmp_path / f"{name}.npz", {"map_xy": np.zeros((1, 2))})
    manifest = {"fingerprint": "abc", "block_cells": 50, "layout": LAYOUT,
                "pre": stats.to_json(), "post": stats.to_json()}
    write_manifest(tmp_path / MANIFEST, manifest)
    pre, post = kept_epochs(tmp_path, "abc", 50)
    assert pre.counts == post.counts == {7: 3}
    assert kept_epochs(tmp_path, "other inputs", 50) is None
    assert kept_epochs(tmp_path, "abc", 25) is None
    # a store of the layout before building points had files of their own: its densities
    # would read no building point, so it is tiled again
    write_manifest(tmp_path / MANIFEST, {k: v for k, v in manifest.items() if k != "layout"})
    assert kept_epochs(tmp_path, "abc", 50) is None


def test_parts_are_two_a_worker_and_never_smaller_than_a_chunk():
    from quakescan.distributed.engine import PART_POINTS, part_bounds

    assert part_bounds(1_000, 2, 100) == [0, 250, 500, 750, 1000]  # two a worker
    assert part_bounds(1_000, 2, 400) == [0, 333, 667, 1000]  # no part under a chunk: 3, not 4
    assert part_bounds(10, 4, 2_000_000) == [0, 10]
    n = 5 * PART_POINTS + 1  # more than PART_POINTS a part otherwise: six parts
    assert len(part_bounds(n, 1, 1_000)) - 1 == 6


def test_a_model_file_that_does_not_load_stops_the_tiling_and_is_named(pair, cluster, tmp_path):
    """The model is read while the workers stream the epochs: a file that is not a model stops
    the run with its name, and its streaming tasks are cancelled."""
    from quakescan.distributed.engine import classify_distributed
    from quakescan.errors import QuakeScanError

    bad = tmp_path / "not_a_model.skops"
    bad.write_bytes(b"not a zip archive")
    with pytest.raises(QuakeScanError, match="not_a_model.skops"):
        classify_distributed(pair / "pre.las", pair / "post.las", tmp_path / "o", cluster, model_path=bad,
                             block_cells=BLOCK_CELLS, chunk_points=50_000)
    import time

    deadline = time.monotonic() + 60  # cancelled: a part being streamed finishes, no other starts
    while any(cluster.processing().values()) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(cluster.processing().values())
    assert not (tmp_path / "o" / ".blocks" / "manifest.json").exists()


@pytest.mark.parametrize("cells", [7, 50])
def test_block_densities_merged_are_the_whole_epochs_density_to_the_last_bit(pair, tmp_path, cells, monkeypatch):
    """Each block's roof cells counted on its own (a dense grid, neighbours by shifting it),
    merged by the client: the planimetric density one process computes from every building
    point at once, exactly."""
    from quakescan.distributed.block_store import stored_points
    from quakescan.distributed.reading import read_records
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch
    from quakescan.distributed.tasks import _roof_cells, block_roof_cells, group_roof_cells, merge_roof_cells
    from quakescan.formats.pointcloud import read_epoch
    from quakescan.grid.density import planimetric_density

    for name in ("pre", "post"):
        f = open_epoch_file(pair / f"{name}.las")
        origin = default_origin(f)
        folder = tmp_path / f"{name}{cells}"
        stats = stream_epoch(f, origin, folder, block_cells=cells, chunk_points=50_000)
        (folder / "epoch.json").write_text(json.dumps({"file": f.to_json(), "origin": origin.tolist(), "parts": 0}))
        parts = [block_roof_cells(str(folder), k, cells) for k in stats.blocks]
        merged = merge_roof_cells(parts)
        e = read_epoch(pair / f"{name}.las", origin=origin)
        assert merged == planimetric_density(e.xyz, e.building_id > 0) > 0
        # the compiled cells of the records: each block's share as numpy's coordinates give it
        for k, part in zip(stats.blocks, parts):
            rec = read_records(folder, [tuple(k)], buildings_only=True)
            assert part == _roof_cells(f.local_xyz(rec["X"], rec["Y"], rec["Z"], origin), tuple(k), cells)
        # a square of 3 × 3 blocks counted as one part (as the client groups them): the same density,
        # unmoved and moved by an alignment (the blocks around the epoch's asked too, as the client does)
        a = np.deg2rad(0.7)
        moved = [[np.cos(a), -np.sin(a), 0, 1.3], [np.sin(a), np.cos(a), 0, -2.1], [0, 0, 1, 0.2], [0, 0, 0, 1]]
        for transform in (None, moved):
            keys = {tuple(k) for k in stats.blocks}
            if transform is not None:
                keys = {(i + di, j + dj) for i, j in keys for di in (-1, 0, 1) for dj in (-1, 0, 1)}
            squares: dict = {}
            for k in sorted(keys):
                squares.setdefault((k[0] // 3, k[1] // 3), []).append(k)
            by_block = [p for g in squares.values() for p in group_roof_cells(str(folder), g, cells, True, transform)]
            by_square = [p for g in squares.values()
                         for p in group_roof_cells(str(folder), g, cells, True, transform, 3 * cells)]
            assert len(by_square) == len(squares) < len(by_block)
            assert merge_roof_cells(by_square) == merge_roof_cells(by_block) > 0
            if transform is None:
                assert merge_roof_cells(by_square) == merged
        # a square denser than SQUARE_POINTS is counted a block at a time: the same density
        import quakescan.distributed.tasks as tasks

        squares = {}
        for k in stats.blocks:
            squares.setdefault((k[0] // 3, k[1] // 3), []).append(tuple(k))
        def stored(g):
            return stored_points(folder, g, buildings_only=True)

        moved_whole = merge_roof_cells([p for g in squares.values()
                                        for p in group_roof_cells(str(folder), g, cells, True, moved, 3 * cells)])
        monkeypatch.setattr(tasks, "SQUARE_POINTS", max(stored(g) for g in squares.values()) - 1)
        mixed = [p for g in squares.values() for p in group_roof_cells(str(folder), g, cells, square_cells=3 * cells)]
        assert len(squares) < len(mixed) and merge_roof_cells(mixed) == merged
        # moved: a square whose ring is over the bound is counted block by block, each with its own ring
        mixed = [p for g in squares.values() for p in group_roof_cells(str(folder), g, cells, True, moved, 3 * cells)]
        assert len(squares) < len(mixed) and merge_roof_cells(mixed) == moved_whole > 0
        monkeypatch.undo()
    with pytest.raises(ValueError, match="do not lie in one square"):
        group_roof_cells(str(folder), [(0, 0), (3, 0)], cells, square_cells=3 * cells)


def test_a_blocks_roof_cells_from_its_records_at_utm_offsets(tmp_path):
    """Cells and heights made from the stored records (one loop) give the counts numpy's
    coordinates give, at UTM offsets with cells of both signs, over two parts' files."""
    from quakescan.distributed.block_store import block_of, join_part_indexes, part_index_path, part_path, run_keys
    from quakescan.distributed.tasks import _roof_cells, block_roof_cells

    f, origin, rec = _utm_records(30_000, seed=11)
    rec["X"] = rec["X"] % 40_000 - 20_000  # local x in -9.75..30.25 m: cells of both signs, two blocks of 50 m
    rec["Y"] = rec["Y"] % 40_000 - 20_000  # local y in -29.5..10.5 m
    xyz = f.local_xyz(rec["X"], rec["Y"], rec["Z"], origin)
    key = tuple(block_of(xyz[:1, :2], 50)[0].tolist())
    inside = (block_of(xyz[:, :2], 50) == key).all(axis=1) & (rec["building_id"] > 0)
    assert inside.sum() > 1000
    folder = tmp_path / "pre"
    folder.mkdir()
    kept = rec[inside]
    for part, half in enumerate((kept[::2], kept[1::2])):
        half.tofile(part_path(folder, part))
        np.save(part_index_path(folder, part), np.array([[run_keys(*key, 1), part, 0, len(half)]]))
    join_part_indexes(folder, 2)
    (folder / "epoch.json").write_text(json.dumps({"file": f.to_json(), "origin": origin.tolist(), "parts": 2}))
    want = _roof_cells(xyz[inside], key, 50)
    assert want["cells"] > 100
    assert block_roof_cells(str(folder), key, 50) == want


@pytest.mark.parametrize("runs", [[5, 0, 7, 1], [1], [0, 0], [300] * 40, [2, 50_000, 3]])
def test_merged_runs_are_in_the_order_a_stable_argsort_gives(runs):
    """The k-way merge behind read_box: ascending runs (ties within and across runs, empty
    runs) in the order np.argsort(kind="stable") gives the joined values."""
    from quakescan.distributed._record_kernels import merged_order

    rng = np.random.default_rng(len(runs))
    parts = [np.sort(rng.integers(0, 60, n)) for n in runs]
    values = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    starts = np.cumsum([0] + runs)
    np.testing.assert_array_equal(merged_order(values, starts), np.argsort(values, kind="stable"))


def _utm_records(n=20_000, seed=3, record=None):
    """Records (RECORD, or `record`) of a file whose integers straddle zero about a UTM offset
    (local coordinates of both signs, block edges crossed), with points on whole metres."""
    from quakescan.distributed.block_store import RECORD
    from quakescan.distributed.streaming import EpochFile

    rng = np.random.default_rng(seed)
    rec = np.empty(n, RECORD if record is None else record)
    rec["index"] = np.sort(rng.choice(10 * n, n, replace=False))
    rec["X"], rec["Y"] = rng.integers(-90_000, 90_000, n), rng.integers(-90_000, 90_000, n)
    rec["X"][:50] = 7_000  # 7.000 m: on a block edge and on the box's edge below
    rec["Z"] = rng.integers(-5_000, 40_000, n)
    rec["classification"] = rng.integers(0, 7, n)
    rec["building_id"] = np.where(rng.random(n) < 0.4, rng.integers(1, 30, n), 0)
    f = EpochFile("utm.las", n, [0.001, 0.001, 0.001], [500_000.25, 5_200_000.5, 100.0], [0] * 3, [0] * 3,
                         None, [])
    return f, np.array([499_990.0, 5_200_010.0, 0.0]), rec


def test_chunk_frame_makes_the_coordinates_bounds_and_blocks_numpy_makes():
    """The streamed chunk's compiled frame: coordinates equal to EpochFile.local_xyz to the
    bit at UTM offsets, blocks as block_of floors them (negative cells included), the
    bounds, and block codes that order blocks, other points before building points."""
    from quakescan.distributed._record_kernels import block_codes, chunk_frame
    from quakescan.distributed.block_store import block_of

    f, origin, rec = _utm_records()
    n = len(rec)
    xyz, keys = np.empty((n, 3)), np.empty((n, 2), np.int64)
    scales, shifts = f.frame(origin)
    lo, hi, klo, khi = chunk_frame(rec["X"], rec["Y"], rec["Z"], scales, shifts, 1.0, BLOCK_CELLS, xyz, keys)
    want = f.local_xyz(rec["X"], rec["Y"], rec["Z"], origin)
    np.testing.assert_array_equal(xyz, want)
    want_keys = block_of(want[:, :2], BLOCK_CELLS)
    np.testing.assert_array_equal(keys, want_keys)
    assert (keys < 0).any() and (keys > 0).any()
    np.testing.assert_array_equal(lo, want.min(axis=0))
    np.testing.assert_array_equal(hi, want.max(axis=0))
    np.testing.assert_array_equal(klo, want_keys.min(axis=0))
    np.testing.assert_array_equal(khi, want_keys.max(axis=0))
    codes = block_codes(keys, klo, int(khi[1] - klo[1]) + 1, rec["building_id"])
    flat = (want_keys[:, 0] - klo[0]) * (khi[1] - klo[1] + 1) + (want_keys[:, 1] - klo[1])
    np.testing.assert_array_equal(codes, 2 * flat + (rec["building_id"] > 0))


def test_group_boxes_are_the_x_y_extent_of_each_group():
    from quakescan.change.tiling import grouped_by_id, id_counts
    from quakescan.distributed._record_kernels import group_boxes

    rng = np.random.default_rng(5)
    xyz = rng.normal(0, 1e5, (5_000, 3)) + [5e5, 5.2e6, 0]
    ids = rng.integers(0, 40, 5_000)
    u, counts = id_counts(ids)
    order, starts = grouped_by_id(ids, u)
    lo, hi = group_boxes(xyz, order, starts, starts + counts)
    for g, b in enumerate(u):
        np.testing.assert_array_equal(lo[g], xyz[ids == b, :2].min(axis=0))
        np.testing.assert_array_equal(hi[g], xyz[ids == b, :2].max(axis=0))


@pytest.mark.parametrize("narrow", [False, True])
def test_keep_in_box_keeps_what_the_numpy_mask_keeps_edges_included(narrow):
    """The compiled cut of a block file to a box: the records numpy's mask of local_xyz
    keeps (UTM offsets, points on the box's edge), appended after the rows already filled;
    from the widest record and from the 21-byte one (unaligned fields either way)."""
    from quakescan.distributed._record_kernels import keep_in_box
    from quakescan.distributed.block_store import RECORD, record_dtype

    record = record_dtype(20_000, "<u4") if narrow else RECORD
    f, origin, rec = _utm_records(record=record)
    want = f.local_xyz(rec["X"], rec["Y"], rec["Z"], origin)
    box = np.array([[want[0, 0], -20.0], [want[:50, 0].max() + 30.0, 35.5]])
    box[0, 0] = want[:50, 0].min()  # the 50 points on x = 7.000 m - the shift lie on the edge
    inside = np.all((want[:, :2] >= box[0]) & (want[:, :2] <= box[1]), axis=1)
    assert inside[:50].any()
    n = len(rec) + 7
    index, cls, bid, xyz = np.zeros(n, np.int64), np.zeros(n, np.uint8), np.zeros(n, np.int64), np.zeros((n, 3))
    scales, shifts = f.frame(origin)
    m = keep_in_box(rec, scales, shifts, box, index, cls, bid, xyz, 7)
    assert m == 7 + inside.sum()
    np.testing.assert_array_equal(xyz[7:m], want[inside])
    np.testing.assert_array_equal(index[7:m], rec["index"][inside])
    np.testing.assert_array_equal(cls[7:m], rec["classification"][inside])
    np.testing.assert_array_equal(bid[7:m], rec["building_id"][inside])
    assert not index[:7].any()
    assert keep_in_box(rec, scales, shifts, box + 1e6, index, cls, bid, xyz, 0) == 0
    assert rec.dtype.itemsize == (21 if narrow else 29)  # packed records: the kernel reads them unaligned


def test_records_are_as_narrow_as_the_file_allows():
    """A stored point's index and building ID take 4 bytes where every value fits: a file's
    point count up to 2^32 (an index is below it), building IDs of 4 bytes or fewer in the
    file (their signedness kept), footprint IDs in int32's range; 8 bytes otherwise."""
    from quakescan.distributed.block_store import RECORD, record_dtype

    def widths(d):
        return d["index"].str, d["building_id"].str, d.itemsize

    assert widths(record_dtype(75_000_000, "<u4")) == ("<u4", "<u4", 21)
    assert widths(record_dtype(2 ** 32, np.uint16)) == ("<u4", "<u4", 21)
    assert widths(record_dtype(2 ** 32 + 1, "<u4")) == ("<i8", "<u4", 25)  # LAS 1.4 counts go past 2^32
    assert widths(record_dtype(10, "<i2")) == ("<u4", "<i4", 21)
    assert widths(record_dtype(10, "<u8")) == ("<u4", "<i8", 25)
    assert widths(record_dtype(10, RECORD["building_id"])) == ("<u4", "<i8", 25)
    assert widths(record_dtype(10, np.array([-2 ** 31, 0, 2 ** 31 - 1]))) == ("<u4", "<i4", 21)
    assert widths(record_dtype(10, np.array([1, 2 ** 31]))) == ("<u4", "<i8", 25)  # e.g. OSM way IDs
    assert widths(record_dtype(10, np.array([-2 ** 31 - 1]))) == ("<u4", "<i8", 25)
    assert widths(record_dtype(0, np.zeros(0, np.int64))) == ("<u4", "<i4", 21)
    assert record_dtype(10, "<u4").names == RECORD.names


@pytest.mark.parametrize("ids_from", ["file", "footprints"])
def test_building_ids_beyond_int32_are_stored_and_read_back_exactly(tmp_path, ids_from):
    """IDs at the ends of what a file's uint32 holds (2^32 - 1 reads back as such, not -1)
    and footprint IDs past int32 (int64 records) come back from the blocks as one process
    reads them."""
    import shapely

    from quakescan.distributed.block_store import stored_record
    from quakescan.distributed.reading import read_box, read_records
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch
    from quakescan.formats.footprints import Footprints
    from quakescan.formats.pointcloud import read_epoch

    rng = np.random.default_rng(2)
    n = 4_000
    x, y = rng.uniform(0, 40, n), rng.uniform(0, 20, n)
    big = [2 ** 31 - 1, 2 ** 31, 2 ** 32 - 1] if ids_from == "file" else [7, 2 ** 31, 2 ** 40]
    ids = np.select([x < 10, x < 20, x < 30], big[:3], 0)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = [500_000.0, 5_200_000.0, 0.0], [0.001] * 3
    if ids_from == "file":
        header.add_extra_dim(laspy.ExtraBytesParams("building_id", np.uint32))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x + 500_000, y + 5_200_000, rng.uniform(0, 9, n)
    if ids_from == "file":
        las.building_id = ids.astype(np.uint32)
    las.write(tmp_path / "pre.las")
    fp = None
    if ids_from == "footprints":
        fp = Footprints(np.array(big, dtype=np.int64),
                        [shapely.box(500_000 + 10 * k, 5_200_000, 500_010 + 10 * k, 5_200_020) for k in range(3)])
    f = open_epoch_file(tmp_path / "pre.las")
    origin = default_origin(f)
    stats = stream_epoch(f, origin, tmp_path / "blocks", block_cells=7, chunk_points=999, footprints=fp)
    record = stored_record(tmp_path / "blocks")
    assert record["building_id"].str == ("<u4" if ids_from == "file" else "<i8")
    rec = read_records(tmp_path / "blocks", [tuple(k) for k in stats.blocks])
    want = read_epoch(tmp_path / "pre.las").building_id if ids_from == "file" else ids
    np.testing.assert_array_equal(rec["index"], np.arange(n))
    np.testing.assert_array_equal(rec["building_id"].astype(np.int64), want)
    assert set(stats.counts) == {b for b in big if (want == b).any()}
    box, xyz = read_box(tmp_path / "blocks", f, origin, np.array([[-1.0, -1.0], [50.0, 30.0]]), 7)
    np.testing.assert_array_equal(box["building_id"], want)


@slow
def test_the_registration_check_sends_its_samples_as_data_not_a_large_graph(pair, cluster, tmp_path, monkeypatch):
    """The registration check's samples (up to 500 k stable points an epoch, 2 x 12 MB) are
    scattered to the workers: passed inside the task, Dask warns of a large graph."""
    import warnings

    from quakescan.distributed.streaming import merge_stats

    real = merge_stats

    def big_sample(parts):  # in the client: the box city's stable sample made as large as a city's
        stats = real(parts)
        stats.stable_sample = np.tile(stats.stable_sample, (500_000 // len(stats.stable_sample) + 1, 1))
        return stats

    monkeypatch.setattr("quakescan.distributed.engine.merge_stats", big_sample)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _run(pair, tmp_path / "dask", cluster, write_las=False)
    assert not [w for w in caught if "large graph" in str(w.message)]
