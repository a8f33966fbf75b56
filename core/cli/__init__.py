"""`quakescan` command line: `main` and the parser, one module per family of commands
(scenes, acquisition, analysis, training, studies). Argument parsing, progress and messages
live in this package only."""
from __future__ import annotations

import argparse
import logging
import sys

from .. import __version__
from ..errors import QuakeScanError
from . import acquisition, analysis, scenes, studies, training
from .options import QUIET_HELP
from .reporting import drop_stdout, stage_messages


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quakescan", description="Virtual UAV laser scanning of damaged buildings.")
    p.add_argument("--version", action="version", version=f"quakescan {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    p.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    sub = p.add_subparsers(dest="command", required=True)

    studies.add_demo(sub)
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
    for command in sub.choices.values():  # `quakescan CMD … -q` as well as `quakescan -q CMD …`
        command.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
    return p


def tune_allocator() -> None:
    """Keep freed batch buffers in the heap (glibc only).

    A scan allocates and frees ~100 MB per batch and thread; by default glibc returns such
    blocks to the OS and the next batch page-faults them back. BENCHMARKS.md compares the
    single-ray scan with and without it in the same run (the difference is within this
    machine's run-to-run noise for the fused single-ray loop; it mattered for the older,
    allocation-heavy path). Done here, in the command, not in the library: it is a
    process-wide setting."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 512 << 20)
        libc.mallopt(m_trim_threshold, 2 << 30)
    except (OSError, AttributeError, TypeError):
        pass  # not glibc: keep the default allocator


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    tune_allocator()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
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
