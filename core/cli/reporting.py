"""What the command line shows: the progress reporter, stage messages and printed lines that
survive a closed pipe."""
from __future__ import annotations

import contextlib
import logging
import os
import sys
import time


class Progress:
    """The one progress reporter of the command line: `label  done/total  pct  elapsed  ETA`
    on stderr, at most every `every_s` seconds or 5 %, and always at the end.

    Called as progress(done, total, stage=""), the one shape of `quakescan.runtime.progress`. The
    line's label is the reporter's label followed by the stage; a new stage starts a new
    count: its own first report, its elapsed time from that report, its own line. Elapsed
    time of the first stage counts from the reporter's creation (the command's start). The
    ETA assumes the remaining steps go at the rate since the first report, (t1, d1):

        ETA = (now − t1) × (total − done) / (done − d1)

    so that what comes before the first step (reading the input, compiling kernels, checking
    the registration: 26 of classify's 36 s on an AHN3 tile) and a burst of steps that finish
    together (a tile's buildings) do not skew it; it is unknown ("?") until `min_basis_s` have
    passed since the first report. On a terminal a line overwrites itself; elsewhere (a log,
    `--progress` in a pipe) each report is a line of its own. `clock` and `stream` are for
    the tests."""

    def __init__(self, label: str, enabled: bool, *, clock=time.monotonic, stream=None, every_s: float = 2.0,
                 min_basis_s: float = 1.0):
        self.base, self.enabled = label, enabled
        self.clock, self.every_s, self.min_basis_s = clock, every_s, min_basis_s
        self.stream = stream
        self.stage = ""
        self._start(clock())

    def _start(self, now: float) -> None:
        self.label = " ".join(p for p in (self.base, self.stage) if p)
        self.t0 = now
        self.first = None  # (time, done) of the first report
        self.last_t, self.last_f = -float("inf"), -1.0
        self.open_line = False  # a terminal line not yet ended by its last report

    def eta_s(self, done: int, total: int, now: float) -> float | None:
        """Seconds left at the rate since the first report; None while that rate is unknown."""
        if done >= total:
            return 0.0
        if self.first is None:
            return None
        t1, d1 = self.first
        if done <= d1 or now - t1 < self.min_basis_s:
            return None
        return (now - t1) * max(total - done, 0) / (done - d1)

    def line(self, done: int, total: int, now: float) -> str:
        eta = self.eta_s(done, total, now)
        return (f"{self.label}  {done:,}/{total:,}  {100 * done / total:3.0f} %  {clock_time(now - self.t0)}  "
                f"ETA {'?' if eta is None else clock_time(eta)}")

    def __call__(self, done: int, total: int, stage: str = "") -> None:
        if not self.enabled or total <= 0:
            return
        stream = self.stream or sys.stderr
        now = self.clock()
        if stage != self.stage:
            if self.open_line:
                print(file=stream, flush=True)
            self.stage = stage
            self._start(now)
        if self.first is None:
            self.first = (now, done)
        f = done / total
        step = f - self.last_f >= 0.05 - 1e-9  # 1e-9: 0.06 - 0.01 is less than 0.05 in floats
        if f >= 1 or step or now - self.last_t >= self.every_s:
            tty = stream.isatty()
            end = "\n" if f >= 1 or not tty else ""
            print(("\r" if tty else "") + self.line(done, total, now), end=end, file=stream, flush=True)
            self.last_t, self.last_f = now, f
            self.open_line = not end


def clock_time(seconds: float) -> str:
    """m:ss, or h:mm:ss from an hour."""
    s = int(round(seconds))
    h, m = divmod(s, 3600)
    return f"{h}:{m // 60:02d}:{m % 60:02d}" if h else f"{m // 60}:{m % 60:02d}"


def reporter(args, label: str) -> Progress:
    """The reporter of a command: on a terminal by default, `--progress` forces it, `-q` silences it."""
    quiet = getattr(args, "quiet", False)
    return Progress(label, not quiet and (getattr(args, "progress", False) or sys.stderr.isatty()))


@contextlib.contextmanager
def stage_messages(args):
    """Stage messages of the multi-step commands (experiment, training-set, demo; the library logs
    them to `quakescan.stages`): plain lines on stderr, unless `-q`. The logger is as it was
    once the command ends (tests run many commands in one process)."""
    stages = logging.getLogger("quakescan.stages")
    level, propagate = stages.level, stages.propagate
    handler = None
    if getattr(args, "quiet", False):
        stages.setLevel(logging.WARNING)
    else:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        stages.addHandler(handler)
        stages.setLevel(logging.INFO)
        stages.propagate = False  # shown once, plain, also under -v
    try:
        yield
    finally:
        if handler is not None:
            stages.removeHandler(handler)
        stages.setLevel(level)
        stages.propagate = propagate


def echo(*args, **kwargs) -> None:
    """print() that survives a closed stdout (`quakescan scan … | head -1`): the command goes on
    and finishes its files, its remaining messages are dropped."""
    try:
        print(*args, **kwargs)
        if kwargs.get("file") is None:
            sys.stdout.flush()
    except BrokenPipeError:
        drop_stdout()


def drop_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's flush at exit does not fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
