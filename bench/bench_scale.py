#!/usr/bin/env python3
"""Classification beyond one process: `quakescan classify` alone, on a Dask LocalCluster of 1
and 2 workers, and on a pair too large for one process, measured side by side in one run.

    .venv/bin/python bench/bench_scale.py [--rows single,cluster,large,trainset,graded,copc] [--work out/bench_scale]

Rows (issue 16's table):

- single: the issue's 2 x 75 M-point pair (`bench_pipeline`'s generic city of 480 buildings,
  the paper's survey, pre-event vs post_destruction, 37.4 M points an epoch, copied twice side
  by side: 74.9 M points an epoch), `quakescan classify` in one process: wall time and peak
  RSS (target <= 3 min, <= 8 GB);
- cluster: the same pair with `--workers 1` and `--workers 2` (LocalCluster, one thread a
  worker): wall time of each, speed-up (target >= 1.8x), the client's and the largest
  worker's peak RSS; `--pairs` (3) runs of 1 and 2 workers in turn, the speed-up the median
  of the pair-by-pair ratios (the machine's drift cancels in a pair), the row that pair's;
- half: single and cluster on the city itself (2 x 37 M points, half the issue's pair: the
  rows this benchmark measured before it measured the issue's pair);
- large: the pair copied side by side (each copy 600 m east of the last, building IDs
  offset) to >= 2 x 250 M points on disk, `--workers 2 --memory-limit 4GB`: it finishes, the
  largest worker's peak (target <= 4 GB), and throughput per worker (points of both epochs
  per second per worker) against the single process's (target >= 0.9x): per core of the
  single run (its two threads on the same two cores), against the one-thread run (one
  core, the other idle) and against a one-thread run beside another (both cores busy);
- single also runs the pair with `--threads 1`: one core's throughput, the like-for-like
  reference of a one-thread worker; and two such processes at once (their mean wall time):
  a core's throughput while the other core works too, as each of two workers' does;
- copc: the half pair rewritten as COPC files (compressed, octree nodes of ~100 k points) on 2
  workers: tiles and densities read by bounds from the files, no block files;
- graded: the half pair classified with the graded cloud (post_grades.las) written, in one
  process and on 2 workers (whose tasks make its records in parts): the time to write it;
- model: the shipped model loaded in a fresh process through skops (the cache off) and from
  the model cache (`quakescan.learning.model_cache`), `--pairs` runs of each in turn;
- trainset: the paper's four states (pre, heavy, extreme, destruction) of 1,000 generic
  buildings generated, acquired and described (`quakescan.learning.trainset.build` on a
  LocalCluster of 2 workers; target <= 30 min on 2 cores), and the time to resume it.

Peak RSS per process is sampled every 0.2 s over the command's process tree (psutil): the
client is the command's own process, the workers are its other descendants. Every run is a
fresh process writing into an emptied output folder: nothing is skipped as up to date or
resumed. The commands keep models in WORK/cache (`QUAKESCAN_CACHE_DIR`), filled with the
shipped model before the first row: every command loads it as a user's second command does. Writes the table to stdout and to BENCHMARKS.md (section "bench_scale"), the raw
figures to WORK/results.json.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, table, write_section  # noqa: E402

WORK = ROOT / "out" / "bench_scale"
LARGE_POINTS = 250_000_000  # per epoch, at least
COPY_STEP_M = 600.0  # the big city is 576 m wide: copies 600 m apart never share a building
ID_STEP = 100_000  # building IDs of copy k: k * ID_STEP + the source's
ISSUE_PAIR_COPIES = 2  # the city's 37.4 M points an epoch twice: issue 16's "2 x 75 M-point pair"
ROWS = ("single", "cluster", "half", "large", "trainset", "graded", "copc", "model")
LOAD_MODEL = ("import time; from quakescan.learning.default_model import default_model_path; "
              "from quakescan.learning.model import load_model; t = time.perf_counter(); "
              "load_model(default_model_path()); print(time.perf_counter() - t)")


class TreeSampler:
    """Peak RSS of a process and of each of its descendants, sampled while it runs."""

    def __init__(self, pid: int, every_s: float = 0.2):
        import psutil

        self.root = psutil.Process(pid)
        self.every = every_s
        self.peaks: dict[int, int] = {}
        self.names: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        import psutil

        while not self._stop.is_set():
            try:
                procs = [self.root] + self.root.children(recursive=True)
            except psutil.Error:
                break
            for p in procs:
                try:
                    rss = p.memory_info().rss
                    if p.pid not in self.names:
                        self.names[p.pid] = " ".join(p.cmdline())[:200]
                except psutil.Error:
                    continue
                self.peaks[p.pid] = max(self.peaks.get(p.pid, 0), rss)
            self._stop.wait(self.every)

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join()
        client = self.peaks.get(self.root.pid, 0)
        # a worker is a spawned Python (multiprocessing); its nanny is the small one above it
        workers = [v for pid, v in self.peaks.items() if pid != self.root.pid and "multiprocessing" in
                   self.names.get(pid, "")]
        return {"client_mb": client / 2 ** 20, "worker_mb": max(workers, default=0) / 2 ** 20,
                "workers_seen": len(workers)}


def run_classify(pre: Path, post: Path, out: Path, extra: list, las: bool = False) -> dict:
    return run_side_by_side([(pre, post, out, extra)], las)[0]


def run_side_by_side(runs: list, las: bool = False) -> list[dict]:
    """`quakescan classify` of each (pre, post, out, extra) in `runs`, all started at once: one
    run alone, or several sharing the machine's cores as a cluster's workers do."""
    procs = []
    for pre, post, out, extra in runs:
        # --force redoes a finished run but resumes an interrupted one: a bench killed mid-row
        # left its checkpoint, and the next run measured 260 of 480 buildings as resumed
        shutil.rmtree(out, ignore_errors=True)
        cmd = [str(Path(sys.executable).with_name("quakescan")), "classify", "--pre", str(pre), "--post",
               str(post), "-o", str(out), "--force", *([] if las else ["--no-las"]), *extra]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=bench_env())
        procs.append((cmd, out, proc, TreeSampler(proc.pid), time.perf_counter()))
    return [_finished_run(*p) for p in procs]


def bench_env(cache: str | None = None) -> dict | None:
    """A command's environment: this one's (the model cache in WORK/cache, set by `main`), or
    with the cache `cache` ("off")."""
    return None if cache is None else {**os.environ, "QUAKESCAN_CACHE_DIR": cache}


def model_load_s(cache: str | None = None) -> float:
    """Seconds a fresh process takes to load the shipped model (imports of QuakeScan's
    classification module not counted: every command makes them before)."""
    out = subprocess.run([sys.executable, "-c", LOAD_MODEL], capture_output=True, text=True, check=True,
                         env=bench_env(cache))
    return float(out.stdout.split()[-1])


def model_row(pairs: int) -> dict:
    """The shipped model loaded through skops and from the cache, `pairs` times each in turn."""
    model_load_s()  # the cache filled
    skops, cached = [], []
    for _ in range(pairs):
        skops.append(model_load_s("off"))
        cached.append(model_load_s())
    return {"at": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "skops_s": skops, "cache_s": cached}


def _finished_run(cmd: list, out: Path, proc, sampler, t0: float) -> dict:
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    mem = sampler.stop()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{stderr[-3000:]}")
    summary = json.loads((out / "summary.json").read_text())
    if summary.get("resumed_buildings"):
        raise SystemExit(f"{' '.join(cmd)}: resumed {summary['resumed_buildings']} buildings; not a measurement")
    points = summary["points"]["pre"] + summary["points"]["post"]
    r = {"at": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "cmd": " ".join(cmd[1:]), "wall_s": wall, "points": points, "buildings": summary["buildings"],
         "seconds": summary["seconds"], "dask": summary.get("dask"), **mem}
    print(json.dumps({k: v for k, v in r.items() if k != "cmd"}), flush=True)
    return r


def big_pair() -> tuple[Path, Path]:
    from bench_pipeline import ensure_big_pair

    return ensure_big_pair()


def copc_pair(work: Path, pre: Path, post: Path) -> tuple[Path, Path]:
    """The big pair rewritten as COPC files (`tests/copc_files.py`, the specification's layout:
    octree levels down to ~100 k points a node), kept when already there and newer."""
    import os

    import laspy

    from tests.copc_files import write_copc

    out = []
    for src in (pre, post):
        dst = work / f"{src.stem}.copc.laz"
        if not dst.is_file() or dst.stat().st_mtime < src.stat().st_mtime:
            with laspy.open(src) as f:
                n = f.header.point_count
            depth = max(1, int(np.ceil(np.log(max(n, 1) / 100_000) / np.log(4))))
            tmp = dst.with_name(dst.name + ".part")
            write_copc(src, tmp, max_level=depth)
            os.replace(tmp, dst)
        out.append(dst)
    return out[0], out[1]


def large_pair(work: Path, pre: Path, post: Path) -> tuple[Path, Path, int]:
    """The big pair copied side by side until each epoch holds >= LARGE_POINTS."""
    import laspy

    with laspy.open(pre) as f:
        copies = int(np.ceil(LARGE_POINTS / f.header.point_count))
    return copied_pair(work, pre, post, copies, "large")


def copied_pair(work: Path, pre: Path, post: Path, copies: int, prefix: str) -> tuple[Path, Path, int]:
    """The big pair copied `copies` times side by side (WORK/PREFIX_NAME.las), written chunk by
    chunk (never whole in memory); kept when already there with the right count."""
    import laspy

    out = []
    for src in (pre, post):
        dst = work / f"{prefix}_{src.stem}.las"
        with laspy.open(src) as f:
            want = f.header.point_count * copies
            header = f.header
        if dst.is_file():
            with laspy.open(dst) as f:
                if f.header.point_count == want:
                    out.append(dst)
                    continue
        tmp = dst.with_suffix(".part.las")
        t = time.perf_counter()
        with laspy.open(src) as reader:
            step = int(round(COPY_STEP_M / header.scales[0]))
            # the source's header (point format, scales, offsets, CRS and extra-bytes VLRs) as it
            # is: the writer counts the points and grows the bounds as they are written
            with laspy.open(tmp, mode="w", header=copy.deepcopy(header)) as writer:
                for k in range(copies):
                    reader.seek(0)
                    for chunk in reader.chunk_iterator(5_000_000):
                        chunk.array["X"] += k * step
                        ids = np.asarray(chunk["building_id"])
                        chunk["building_id"] = np.where(ids > 0, ids + k * ID_STEP, ids)
                        writer.write_points(chunk)
        tmp.replace(dst)
        print(f"{dst}: {want:,} points ({copies} copies) in {time.perf_counter() - t:.0f} s", flush=True)
        out.append(dst)
    return out[0], out[1], copies


def paper_plan(buildings: int, per_city: int = 112, seed: int = 0):
    """Generic cities of the paper's design (pre-event and the three post-event states) with at
    least `buildings` buildings in all, each state paired with the pre-event scene by two random
    ULS acquisitions."""
    from quakescan.acquisition.acquire import random_acquisition
    from quakescan.learning.trainset import CitySpec, PairSpec, TrainingPlan

    rng = np.random.default_rng([seed, 16])
    cities = [CitySpec(f"paper_g{k}", "generic", "paper", 16_000 + k, per_city)
              for k in range(int(np.ceil(buildings / per_city)))]
    pairs = []
    for city in cities:
        for scene in city.post_scenes:
            a, b = random_acquisition("uls", rng), random_acquisition("uls", rng)
            s1, s2 = (int(v) for v in rng.integers(1, 2 ** 31 - 1, 2))
            pairs.append(PairSpec(city.name, scene, a.to_json(), b.to_json(), s1, s2))
    return TrainingPlan(cities, pairs, seed, f"bench-scale-paper-{buildings}")


def trainset_row(work: Path, buildings: int = 1000) -> dict:
    """The paper's design (pre + three post-event states, generic city, paper ULS survey) for
    `buildings` buildings in cities of 112, generated, acquired and described on 2 workers;
    then the same call again (everything on disk: the resume)."""
    from quakescan.distributed.cluster import dask_client
    from quakescan.learning.default_model import TABLE_SETTINGS
    from quakescan.learning.trainset import build

    plan = paper_plan(buildings)

    folder = work / "trainset"
    shutil.rmtree(folder, ignore_errors=True)  # the first build measured from nothing, not resumed
    t = time.perf_counter()
    with dask_client(n_workers=2, memory_limit="6GB") as client:
        table1 = build(folder, plan, TABLE_SETTINGS, client=client)
        first = time.perf_counter() - t
        t = time.perf_counter()
        table2 = build(folder, plan, TABLE_SETTINGS, client=client)
        again = time.perf_counter() - t
    assert np.array_equal(table1.x, table2.x, equal_nan=True)
    r = {"at": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "buildings": sum(c.buildings for c in plan.cities), "pairs": len(plan.pairs), "rows": int(len(table1.y)),
         "wall_s": first, "resume_s": again}
    print(json.dumps(r), flush=True)
    return r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", default=",".join(ROWS), help=f"which rows, comma-separated ({', '.join(ROWS)})")
    ap.add_argument("--work", type=Path, default=WORK)
    ap.add_argument("--pairs", type=int, default=3,
                    help="runs of 1 and 2 workers in turn for the cluster rows (the median ratio is quoted)")
    a = ap.parse_args(argv)
    rows_wanted = [r.strip() for r in a.rows.split(",") if r.strip()]
    bad = sorted(set(rows_wanted) - set(ROWS))
    if bad:
        ap.error(f"--rows: unknown {bad}; choose from {', '.join(ROWS)}")
    work = a.work
    work.mkdir(parents=True, exist_ok=True)
    results_path = work / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    t_all = time.perf_counter()
    os.environ["QUAKESCAN_CACHE_DIR"] = str(work / "cache")  # this process's and every command's
    model_load_s()  # the cache filled before the first row: every command loads the model as a second one does
    pre, post = big_pair()

    def single_rows(p, q, suffix=""):
        results["single" + suffix] = run_classify(p, q, work / f"single{suffix}", [])
        results["single1" + suffix] = run_classify(p, q, work / f"single1{suffix}", ["--threads", "1"])
        # two one-thread processes at once: each core busy, as under two one-thread workers
        both = run_side_by_side([(p, q, work / f"single1_{k}{suffix}", ["--threads", "1"]) for k in (0, 1)])
        results["single1x2" + suffix] = {**both[0], "walls_s": [r["wall_s"] for r in both],
                                         "wall_s": float(np.mean([r["wall_s"] for r in both]))}

    def cluster_rows(p, q, suffix=""):  # 1 and 2 workers in turn, the ratio pair by pair: the drift cancels
        runs: dict[int, list] = {1: [], 2: []}
        for _ in range(a.pairs):
            for n in (1, 2):
                runs[n].append(run_classify(p, q, work / f"cluster{n}{suffix}", ["--workers", str(n)]))
        ratios = [r1["wall_s"] / r2["wall_s"] for r1, r2 in zip(runs[1], runs[2])]
        middle = int(np.argsort(ratios)[len(ratios) // 2])  # the pair of the median ratio is the row
        for n in (1, 2):
            results[f"cluster{n}{suffix}"] = {**runs[n][middle], "walls_s": [r["wall_s"] for r in runs[n]]}
        results[f"cluster2{suffix}"]["ratios"] = ratios

    if "single" in rows_wanted or "cluster" in rows_wanted:
        ipre, ipost, _ = copied_pair(work, pre, post, ISSUE_PAIR_COPIES, "x2")
        if "single" in rows_wanted:
            single_rows(ipre, ipost)
        if "cluster" in rows_wanted:
            cluster_rows(ipre, ipost)
    if "half" in rows_wanted:
        single_rows(pre, post, "_half")
        cluster_rows(pre, post, "_half")
    if "large" in rows_wanted:
        lpre, lpost, copies = large_pair(work, pre, post)
        results["large"] = {**run_classify(lpre, lpost, work / "large", ["--workers", "2", "--memory-limit", "4GB"]),
                            "copies": copies}
    if "trainset" in rows_wanted:
        results["trainset"] = trainset_row(work)
    if "copc" in rows_wanted:  # the same pair as COPC files: tiles read by bounds from the files, no blocks
        cpre, cpost = copc_pair(work, pre, post)
        results["copc2"] = run_classify(cpre, cpost, work / "copc2", ["--workers", "2"])
    if "model" in rows_wanted:
        results["model"] = model_row(max(a.pairs, 5))
    if "graded" in rows_wanted:  # the graded cloud written too: one process, and made in parts by 2 workers
        results["graded1"] = run_classify(pre, post, work / "graded1", [], las=True)
        results["graded2"] = run_classify(pre, post, work / "graded2", ["--workers", "2"], las=True)
    results_path.write_text(json.dumps(results, indent=1))

    def mb(v):
        return f"{v:,.0f}"

    rows: dict[str, tuple] = {}  # slot (a results.json key) -> its row

    def pair_rows(suffix, label, targets):
        s, s1 = results.get("single" + suffix), results.get("single1" + suffix)
        if s:
            rows["single" + suffix] = ((f"{label}, one process", "<= 180 s, <= 8,192 MiB" if targets else "", f"{s['points']:,}",
                         f"{s['wall_s']:.0f}", f"{s['seconds']['read']:.0f} / {s['seconds']['describe']:.0f}",
                         mb(s["client_mb"]), "—", f"{s['points'] / s['wall_s'] / 1e6:.3f}", "", s.get("at", "")))
        if s1:
            rows["single1" + suffix] = (("same pair, one process, one thread (`--threads 1`)", "", f"{s1['points']:,}",
                         f"{s1['wall_s']:.0f}", f"{s1['seconds']['read']:.0f} / {s1['seconds']['describe']:.0f}",
                         mb(s1["client_mb"]), "—", f"{s1['points'] / s1['wall_s'] / 1e6:.3f}",
                         "one core's throughput: the like-for-like reference of a one-thread worker",
                         s1.get("at", "")))
        s2 = results.get("single1x2" + suffix)
        if s2:
            rows["single1x2" + suffix] = (("same pair, two one-thread processes at once (each as above)", "", f"{s2['points']:,}",
                         f"{s2['wall_s']:.0f}", f"{s2['seconds']['read']:.0f} / {s2['seconds']['describe']:.0f}",
                         mb(s2["client_mb"]), "—", f"{s2['points'] / s2['wall_s'] / 1e6:.3f}",
                         "a core's throughput with the other core busy too, as beside a second worker; wall s of "
                         "each: " + ", ".join(f"{w:.0f}" for w in s2["walls_s"]), s2.get("at", "")))
        c1, c2 = results.get("cluster1" + suffix), results.get("cluster2" + suffix)
        for c, n in ((c1, 1), (c2, 2)):
            if c:
                speed = f"speed-up {c1['wall_s'] / c2['wall_s']:.2f}x" if (n == 2 and c1) else ""
                if n == 2 and len(c.get("ratios", [])) > 1:
                    r = sorted(c["ratios"])
                    speed = (f"speed-up {r[len(r) // 2]:.2f}x, the median of {len(r)} pairs run in turn "
                             f"({r[0]:.2f}-{r[-1]:.2f}x)")
                if len(c.get("walls_s", [])) > 1:
                    speed += ("; " if speed else "") + "wall s of each run: " + ", ".join(
                        f"{w:.0f}" for w in c["walls_s"])
                stages = c["seconds"].get("stages", {})
                if stages:
                    speed += "; stages s: " + ", ".join(f"{k} {v:.0f}" for k, v in stages.items())
                rows[f"cluster{n}{suffix}"] = ((f"same pair, LocalCluster {n} worker{'s' if n > 1 else ''}",
                             ">= 1.8x (2 vs 1)" if (n == 2 and targets) else "", f"{c['points']:,}",
                             f"{c['wall_s']:.0f}", f"{c['seconds']['read']:.0f} / {c['seconds']['describe']:.0f}",
                             mb(c["client_mb"]), mb(c["worker_mb"]), f"{c['points'] / c['wall_s'] / n / 1e6:.3f}",
                             speed, c.get("at", "")))

    pair_rows("", "2 x 75 M-point pair (the city copied twice, 74.9 M points an epoch)", True)
    pair_rows("_half", "2 x 37 M-point pair (the city itself: half the issue's pair)", False)
    s, s1 = results.get("single"), results.get("single1")
    lg = results.get("large")
    if lg:
        ratio = ""
        per_worker = lg["points"] / lg["wall_s"] / 2
        if s:  # a worker has one core: the single process's throughput per core, its 2 threads on the same 2 cores
            ratio = f"{per_worker / (s['points'] / s['wall_s'] / 2):.2f}x the single process per core (2 threads); "
        if s1:  # one thread with the other core idle: no neighbour shares its memory bandwidth
            ratio += f"{per_worker / (s1['points'] / s1['wall_s']):.2f}x the one-thread process; "
        s2 = results.get("single1x2")
        if s2:  # both cores busy, as under the two workers
            ratio += f"{per_worker / (s2['points'] / s2['wall_s']):.2f}x a one-thread process beside another; "
        ratio += f"tiles split {lg['dask'].get('tiles_split', 0)}"
        rows["large"] = ((f"2 x {lg['points'] // 2 / 1e6:.0f} M points ({lg['copies']} copies), 2 workers, 4 GB each",
                     "finishes; worker <= 4,096 MiB; >= 0.9x per worker", f"{lg['points']:,}", f"{lg['wall_s']:.0f}",
                     f"{lg['seconds']['read']:.0f} / {lg['seconds']['describe']:.0f}", mb(lg["client_mb"]),
                     mb(lg["worker_mb"]), f"{lg['points'] / lg['wall_s'] / 2 / 1e6:.3f}", ratio, lg.get("at", "")))
    cp = results.get("copc2")
    if cp:
        rows["copc2"] = (("2 x 37 M-point pair as COPC files (LAZ), LocalCluster 2 workers", "", f"{cp['points']:,}",
                     f"{cp['wall_s']:.0f}", f"{cp['seconds']['read']:.0f} / {cp['seconds']['describe']:.0f}",
                     mb(cp["client_mb"]), mb(cp["worker_mb"]), f"{cp['points'] / cp['wall_s'] / 2 / 1e6:.3f}",
                     "tiles read by bounds from the files, no block files; stages s: " + ", ".join(
                         f"{k} {v:.0f}" for k, v in cp["seconds"].get("stages", {}).items()), cp.get("at", "")))
    md = results.get("model")
    if md:
        k, c = float(np.median(md["skops_s"])), float(np.median(md["cache_s"]))
        rows["model"] = (("the shipped model loaded in a fresh process: through skops / from the model cache", "",
                          "—", f"{k:.2f} / {c:.2f}", "—", "—", "—", "—",
                          f"{k / c:.1f}x faster from the cache (medians of {len(md['cache_s'])} in turn; skops "
                          f"{min(md['skops_s']):.2f}-{max(md['skops_s']):.2f} s, cache {min(md['cache_s']):.2f}-"
                          f"{max(md['cache_s']):.2f} s)", md.get("at", "")))
    ts = results.get("trainset")
    if ts:
        rows["trainset"] = ((f"training set: {ts['buildings']:,} buildings x 4 states ({ts['pairs']} pairs), 2 workers",
                     "<= 1,800 s, resumable", f"{ts['rows']:,} rows", f"{ts['wall_s']:.0f}", "—", "—", "—", "—",
                     f"resumed in {ts['resume_s']:.0f} s", ts.get("at", "")))
    for key, label in (("graded1", "one process"), ("graded2", "LocalCluster 2 workers")):
        g = results.get(key)
        if g:
            rows[key] = ((f"2 x 37 M-point pair with the graded cloud (post_grades.las), {label}", "", f"{g['points']:,}",
                         f"{g['wall_s']:.0f}", f"{g['seconds']['read']:.0f} / {g['seconds']['describe']:.0f}",
                         mb(g["client_mb"]), mb(g["worker_mb"]) if g.get("dask") else "—",
                         f"{g['points'] / g['wall_s'] / (2 if g.get('dask') else 1) / 1e6:.3f}",
                         f"graded cloud written in {g['seconds'].get('graded_cloud', float('nan')):.0f} s",
                         g.get("at", "")))
    text = "\n\n".join([
        "## Beyond one process: Dask (`bench/bench_scale.py`)",
        f"Machine: {machine()}. Command: `.venv/bin/python bench/bench_scale.py`; "
        f"the last run: rows {', '.join(rows_wanted) or 'none (the table rewritten)'}, "
        f"{time.perf_counter() - t_all:.0f} s (rows of earlier runs "
        "are kept from WORK/results.json, or, where it lacks them, as BENCHMARKS.md had them, with the time "
        "each was measured). `quakescan classify "
        "--no-las --force` in a fresh process each (the graded LAS left out but in the rows that say so); \"read\" is reading the epochs and the registration check (one process) or streaming them "
        "into blocks (Dask: the workers, a part of the file each, while the client reads the model), \"describe\" "
        "the descriptors (with Dask: the densities and the registration check as tasks in the workers, the check beside the tiles from 2026-11-28 07:11 (in the client before 04:00), then "
        "the tiles). Peak RSS sampled every 0.2 s: "
        "the command's own process (client) and the largest of its worker processes. Throughput: points of both "
        "epochs per second per worker (per process for the single run).",
        SINCE_OPENINGS,
        with_earlier_rows(table(["case", "target", "points", "wall s", "read / describe s", "client peak MiB",
                                 "worker peak MiB", "M points/s per worker", "result", "measured (UTC)"],
                                [rows[k] for k in SLOTS if k in rows]), rows),
    ])
    print("\n" + text)
    write_section("bench_scale", text)


# Why the rows of 2026-12-07 are slower than those of 2026-11-29, measured on the same machine
SINCE_OPENINGS = (
    "Rows measured from 2026-12-07 on read the openings per return (`o_fallen*`, descriptors version 17, "
    "2026-12-01), which the shipped model reads; rows before do not. On this pair (pre-event vs destruction: nearly "
    "every post-event return lies below the old roof, so every one is a candidate) they double the time to "
    "describe. The one-thread row on the code of 2026-11-29 (47d3887), on this machine right after the run of "
    "2026-12-07: 203 s (describe 164 s), where 2026-11-29 recorded 121 s (104 s): the machine is ~1.7x slower "
    "than then, and today's code 1.7x slower than that code on it (343 s, describe 325 s). The openings were "
    "compiled on 2026-12-07 (the same bits; a dense destroyed crop's openings 5.1 -> 2.4 s): the one-worker tiles "
    "436 s before, 323 s after. The one-process target (<= 180 s) is not met: 210 s.")


# The table's rows in order, by their key in results.json
SLOTS = ("single", "single1", "single1x2", "cluster1", "cluster2", "single_half", "single1_half", "single1x2_half",
         "cluster1_half", "cluster2_half", "large", "copc2", "model", "trainset", "graded1", "graded2")


def slot_of(case: str, suffix: str) -> tuple[str | None, str]:
    """(slot, pair suffix) of a row of the table in BENCHMARKS.md, from its case and the pair
    its "same pair" rows follow."""
    if case.startswith("2 x 75 M-point pair"):
        return "single", ""
    if case.startswith("2 x 37 M-point pair (the city itself"):
        return "single_half", "_half"
    for head, slot in (("same pair, one process, one thread", "single1"), ("same pair, two one-thread", "single1x2"),
                       ("same pair, LocalCluster 1 worker", "cluster1"), ("same pair, LocalCluster 2", "cluster2")):
        if case.startswith(head):
            return slot + suffix, suffix
    if "copies)" in case:
        return "large", suffix
    if "as COPC" in case:
        return "copc2", suffix
    if case.startswith("training set"):
        return "trainset", suffix
    if case.startswith("the shipped model loaded"):
        return "model", suffix
    if "graded cloud" in case:
        return ("graded1" if "one process" in case else "graded2"), suffix
    return None, suffix


def with_earlier_rows(new_table: str, rows: dict) -> str:
    """`new_table` with the rows this run and WORK/results.json lack taken from the section in
    BENCHMARKS.md (each keeps its measured time): a fresh checkout reruns some rows only."""
    from _report import BENCHMARKS

    text = BENCHMARKS.read_text() if BENCHMARKS.exists() else ""
    section = text[text.find("<!-- bench_scale start -->"):text.find("<!-- bench_scale end -->")]
    earlier, suffix = {}, ""
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("| case |"):
            slot, suffix = slot_of(line[2:].split(" | ")[0], suffix)
            if slot:
                earlier[slot] = line
    lines = new_table.splitlines()
    head, fresh = lines[:2], iter(lines[2:])
    return "\n".join(head + [next(fresh) if k in rows else earlier[k] for k in SLOTS if k in rows or k in earlier])


if __name__ == "__main__":
    main()
