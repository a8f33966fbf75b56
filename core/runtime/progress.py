"""How a long-running library function reports progress and its stage messages.

Progress is a callable taking `(done, total, stage="")`: `done` of `total` steps of the
function's own unit (pulses, buildings, chunks, steps); `stage` names the part being counted
where a function has several (the pairs of a training table, the scans and the classification
of the demo) and is left out where it has one, so a callable taking only `(done, total)` still
follows the single-stage functions. Every function that reports progress takes it as one keyword,
`progress: ProgressCallback | None = None`; the library never prints it: the command line
(`quakescan.cli.reporting.Progress`) renders it.

Stage messages ("experiment 2/5: acquiring the clouds") are log lines, not progress: they go
to the logger `quakescan.stages` at INFO, which the command line shows on stderr (unless `-q`)
and which a script shows with `logging.basicConfig(level=logging.INFO)`.
"""
from __future__ import annotations

import logging
from typing import Protocol

# One logger for the stage messages of every multi-step function: the command line shows it
# without showing the other modules' INFO details, which stay behind -v.
stage_log = logging.getLogger("quakescan.stages")


class ProgressCallback(Protocol):
    def __call__(self, done: int, total: int, stage: str = "") -> None: ...


def no_progress(done: int, total: int, stage: str = "") -> None:
    """The callback of a caller that does not follow progress."""


def in_stage(progress: ProgressCallback | None, stage: str) -> ProgressCallback | None:
    """`progress` with `stage` filled in, for a function called as one stage of a longer one
    (the demo's classification); the inner function's own stages, if any, follow it."""
    if progress is None:
        return None
    return lambda done, total, inner="": progress(done, total, f"{stage} {inner}" if inner else stage)
