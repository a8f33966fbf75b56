"""The one parallelism knob of the library: `workers`, the number of worker threads.

Every function that runs in parallel takes `workers: int = -1`: a number of threads >= 1, or
-1 for every core (scipy's and scikit-learn's convention; None is taken as -1, every core).
Outputs never depend on it.
"""
from __future__ import annotations

import contextlib

from ..errors import QuakeScanError

EVERY_CORE = -1


def check_workers(workers, where: str = "") -> int:
    """`workers` as an int (-1 for None), or QuakeScanError naming `where`."""
    if workers is None:
        return EVERY_CORE
    if isinstance(workers, bool) or not isinstance(workers, int) or (workers < 1 and workers != EVERY_CORE):
        raise QuakeScanError(f"{where + ': ' if where else ''}workers: the number of worker threads must be an "
                             f"integer >= 1 (or -1: every core), got {workers!r}")
    return workers


@contextlib.contextmanager
def kernel_threads(workers):
    """The numba kernels called inside run on at most `workers` threads (-1 or None: every
    core); the calling thread's setting is restored after. numba's thread count is per
    calling thread, so tiles described in parallel threads each keep their own."""
    from numba import get_num_threads, set_num_threads

    old = get_num_threads()
    if workers is not None and workers > 0:
        set_num_threads(min(int(workers), old))
    try:
        yield
    finally:
        set_num_threads(old)
