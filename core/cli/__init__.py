"""`quakescan` command line: `main` and the parser, one module per family of commands
(scenes, acquisition, analysis, training, studies). Argument parsing, progress and messages
live in this package only."""
from __future__ import annotations

import argparse
import functools
import logging
import sys

from .. import __version__
from ..errors import QuakeScanError
from ..runtime.allocator import tune_allocator
from . import acquisition, analysis, injection, scenes, studies, training
from .options import QUIET_HELP
from .reporting import drop_stdout, stage_messages


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quakescan", description="Virtual UAV laser scanning of damaged buildings.")
    p.add_argument("--version", action="version", version=f"quakescan {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    p.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    sub = p.add_subparsers(dest="command", required=True)

    studies.add_demo(sub)
    acquisition.add_acquire(sub)
    acquisition.add_scan(sub)
    scenes.add_import_cityjson(sub)
    scenes.add_validate(sub)
    scenes.add_footprints(sub)
    acquisition.add_survey_template(sub)
    acquisition.add_dim(sub)
    acquisition.add_dim_survey_template(sub)
    studies.add_robustness(sub)
    training.add_training_set(sub)
    studies.add_experiment(sub)
    analysis.add_features(sub)
    analysis.add_calibrate_lod(sub)
    training.add_train(sub)
    analysis.add_classify(sub)
    analysis.add_evaluate(sub)
    injection.add_inject(sub)
    for command in sub.choices.values():  # `quakescan CMD … -q` as well as `quakescan -q CMD …`
        command.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
    return p


@functools.cache  # once a process, however often `main` runs
def skip_exit_collection() -> None:
    """Have the process leave without Python's last garbage collections (once per process).

    Python 3.11 clears a module at a time on exit and collects after each: with the modules
    a command imports (numpy, scipy, sklearn, numba, dask) that was 0.8-0.9 s of one core
    after a classify had written everything (perf: gc_collect_main, 0.8 s of 1.0 s between
    the last exit handler and the process's end). Objects left then are moved where the
    collector never looks (`gc.freeze`); memory goes back with the process. At exit, not at
    return: tests call `main` many times in one process, whose cycles must still be freed.
    Nothing left to write depends on it: the outputs are closed (atomic renames) before
    `main` returns, the exit handlers still run (logging's flush, temporary folders), and
    Python flushes stdout and stderr itself."""
    import atexit
    import gc

    atexit.register(gc.freeze)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # Freed scan batches (~100 MB a thread) and tile arrays stay in the heap instead of being
    # faulted back in: see quakescan.runtime.allocator. BENCHMARKS.md (bench_scan) compares
    # the scan with and without it in one run.
    tune_allocator()
    skip_exit_collection()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        if isinstance(getattr(args, "output", None), str):  # `-o ''` would write into the current folder
            from ..runtime.output_folder import check_output_path

            check_output_path(args.output, "-o")
        with stage_messages(args):
            code = args.func(args)
    except QuakeScanError as e:
        print(f"quakescan: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("quakescan: interrupted; nothing partial was left under the output names (a rerun of scan or "
              "classify continues from its finished flight lines or tiles)", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `quakescan … | head -1`: the reader left while the command still printed
        drop_stdout()
        print("quakescan: the output pipe closed before the command finished", file=sys.stderr)
        return 141  # as a shell reports a command ended by SIGPIPE
    try:
        sys.stdout.flush()  # a closed pipe shows here, at the last buffered line, not at exit
    except BrokenPipeError:
        drop_stdout()  # the command finished; only its messages went unread
    return code
