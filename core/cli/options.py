"""The options several commands share: their help and the checks of their values (named after the
flag)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime.workers import EVERY_CORE

# One knob with one default in every command: -1, every core, as the library's `workers`
# (`quakescan.runtime.workers`); outputs are the same bytes whatever it is, so the fastest is the default.
THREADS_HELP = "worker threads, >= 1, or -1 for every core (default: -1); the results do not depend on it"
PROGRESS_HELP = ("show progress (done/total, %%, elapsed, ETA) even when stderr is not a terminal; "
                 "on a terminal it is shown unless -q")
QUIET_HELP = "no progress or stage messages on stderr (warnings and errors stay)"


def add_dask_options(parser, workers_help: str, scheduler_help: str) -> None:
    """--workers N | --scheduler ADDRESS: the command's work as Dask tasks on a LocalCluster of N
    single-threaded worker processes, or on an existing cluster."""
    dask = parser.add_mutually_exclusive_group()
    dask.add_argument("--workers", type=int, metavar="N", help=workers_help)
    dask.add_argument("--scheduler", metavar="ADDRESS", help=scheduler_help)


@contextlib.contextmanager
def dask_client_for(args, memory_limit: str | None = "auto"):
    """The Dask client of --workers/--scheduler, its line (where the tasks run, the dashboard)
    printed before the work starts; the LocalCluster closed on leaving."""
    from ..distributed.cluster import dask_client, describe_cluster

    with dask_client(n_workers=args.workers, scheduler=args.scheduler, memory_limit=memory_limit) as client:
        print(describe_cluster(client, args.workers, args.scheduler), flush=True)
        yield client


def csv_list(text: str | None) -> tuple | None:
    return None if text is None else tuple(t.strip() for t in text.split(",") if t.strip())


def check_cloud_output(out: Path, src: Path) -> None:
    """A point cloud output that is neither an existing folder nor the input, named .las/.laz
    (its suffix decides the format: anything else would get LAS bytes under a wrong name)."""
    if out.suffix.lower() not in (".las", ".laz"):
        raise QuakeScanError(f"{out}: -o must name a .las or .laz file (the suffix decides the format)")
    if out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing folder; give a .las or .laz file name")
    if out.exists() and src.exists() and os.path.samefile(out, src):
        raise QuakeScanError(f"{out}: -o is the input file; write the features to another file")


def check_folder_output(out: Path) -> None:
    """A report folder that is not an existing file."""
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing file; give a folder for the report")


def check_file_output(out: Path, inputs) -> None:
    """An output file that is not an existing folder and not one of the inputs."""
    if out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing folder; give a file name")
    for p in inputs:
        if p is not None and out.exists() and Path(p).exists() and os.path.samefile(out, p):
            raise QuakeScanError(f"{out}: -o is the input file {p}; write to another file")


def check_number(flag: str, value, low=None, high=None, *, low_open=False, high_open=False,
                  integer=False) -> None:
    """Refuse a flag's value outside its range, naming the flag (argparse checks types only)."""
    if value is None:
        return
    bad = isinstance(value, float) and not np.isfinite(value)
    if low is not None:
        bad |= value <= low if low_open else value < low
    if high is not None:
        bad |= value >= high if high_open else value > high
    if bad:
        lo = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
        hi = "" if high is None else f"{'<' if high_open else '<='} {high:g}"
        what = "an integer" if integer else "a number"
        raise QuakeScanError(f"{flag}: expected {what} {' and '.join(t for t in (lo, hi) if t)}, got {value}")


SEED_MAX = 2 ** 32 - 1  # numpy and scikit-learn take seeds in [0, 2**32)


def check_seed(value) -> None:
    check_number("--seed", value, 0, SEED_MAX, integer=True)


def check_threads(value) -> None:
    """--threads: the library's `workers` (`quakescan.runtime.workers`), a count >= 1 or -1 for every core."""
    if value != EVERY_CORE and value < 1:
        raise QuakeScanError(f"--threads: expected a number of worker threads >= 1 (or -1: every core), got {value}")
