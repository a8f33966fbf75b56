"""The Dask cluster a command runs its tasks on: a LocalCluster it starts and closes, or an
existing scheduler's cluster; shared by `classify` and `training-set` (`--workers N |
--scheduler ADDRESS`)."""
from __future__ import annotations

import contextlib
import gc
import socket
import struct
import time

from ..errors import QuakeScanError
from ..runtime.allocator import ENVIRON


class ClusterError(QuakeScanError):
    """A Dask cluster cannot be started or reached as asked."""


# Dask starts its workers with MALLOC_TRIM_THRESHOLD_=65536 so that freed memory goes back
# to the system at once. Setting it also fixes glibc's mmap threshold at 128 KiB: every
# array above that is mapped and unmapped anew, its pages faulted in again, and the
# descriptor kernels' tile (many arrays of a few MB) ran 14 % slower in a worker than in a
# plain process (bench_scale). Our workers allocate as the command does instead
# (`quakescan.runtime.allocator`): left to glibc's defaults, the arrays above 32 MiB of a
# tile were still mapped anew each time, and 10 of the pair's tiles took 29.7-31.4 s
# in one thread (380,000-400,000 page faults, 2.5-4.1 s in the kernel) against 27.9-28.1 s
# (61,000 faults, 1.0-1.3 s) with the command's settings, peak 1.20-1.24 against 1.25 GB
# (three alternating runs each). A worker keeps no more than its peak, which the tile
# budget holds at half its memory limit: below Dask's pause at 80 %.
TRIM_VARIABLE = "MALLOC_TRIM_THRESHOLD_"
DASK_TRIM_VALUE = "65536"
WORKER_ENVIRON = {f"distributed.nanny.pre-spawn-environ.{name}": value for name, value in ENVIRON.items()}
# Every event loop (the scheduler's in this process, each worker's) wakes every 20 ms by
# default to measure how long it was blocked. On a laptop's cores that is CPU taken from the
# workers: the client's threads used 0.92 s of CPU over 20 s of tasks on two workers, 0.58 s
# with a 500 ms tick (measured side by side). The tick only times the loop; it schedules
# nothing.
LOOP_TICK = {"distributed.admin.tick.interval": "500ms"}
# Dask's statistical profiler walks each worker's task thread's stack every 10 ms for the
# dashboard's Profile page. On two workers of two cores that thread's CPU is taken from the
# other worker: 10 tiles of the 2 x 37 M pair on 2 workers took 3.0 s of CPU outside the task
# threads with it and 0.55 s without (task CPU 70 s; wall 38.4 / 37.5 s against 36.7 /
# 35.8 s, in turn; scratch harness of 2026-11-28). The task stream, progress and memory
# pages stay; a cluster the user starts (`--scheduler`) keeps its own configuration.
NO_WORKER_PROFILER = {"distributed.worker.profile.enabled": False}
# A scheduler answers a new connection at once with its handshake (one frame of some hundred
# bytes). A server that says nothing, or not that, is not one: Dask's client would wait for
# the handshake without end (its timeout covers the connection only), so it is asked here first.
SCHEDULER_ANSWER_S = 20.0
MAX_HANDSHAKE_BYTES = 1 << 20
# What a worker holds before its first tile: Python, numpy, laspy, Dask and the kernels took
# 140 MB in a bare process, a worker at rest after tiles ~0.5 GB (bench_pipeline). Below this
# limit its nanny restarts it at rest for ever ("exceeded 95% memory budget"): refused up front.
MIN_WORKER_MEMORY = 512 * 2 ** 20
# Ctrl-C reaches every process of the terminal's group: each worker printed two tracebacks of
# its own (77 lines under --workers 2) before the command's one line. Workers ignore it (this
# module's `dask_setup`, a preload); the command stops and closes its cluster, which ends them.
IGNORE_CTRL_C = "quakescan.distributed.cluster"


@contextlib.contextmanager
def _dask_logs_at_warning():
    """Dask's own INFO lines (scheduler and nanny start, workers registered, closed: some 30
    a run) are the cluster's housekeeping, not the user's: with distributed 2026.8 they reach
    stderr from this process whatever LocalCluster's `silence_logs` says, even under `-q`.
    Shown with `-v` (the root logger at INFO); warnings and errors (a worker lost, memory)
    always. The level is put back on leaving: tests run many commands in one process."""
    import logging

    dask_log = logging.getLogger("distributed")
    level = dask_log.level
    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        dask_log.setLevel(logging.WARNING)
    try:
        yield
    finally:
        dask_log.setLevel(level)


@contextlib.contextmanager
def dask_client(n_workers: int | None = None, scheduler: str | None = None, memory_limit: str | None = "auto"):
    """A Dask client: on an existing scheduler's cluster, or on a LocalCluster of `n_workers`
    single-threaded processes started here and closed on leaving (Dask's name: `workers` is
    the library's thread count everywhere else)."""
    try:
        import dask.distributed  # noqa: F401
    except ImportError as e:  # pragma: no cover - dask is a dependency
        raise ClusterError(f"--workers/--scheduler need dask.distributed ({e})") from None
    with _dask_logs_at_warning(), _client(n_workers, scheduler, memory_limit) as client:
        yield client


@contextlib.contextmanager
def _client(n_workers, scheduler, memory_limit):
    """`dask_client` without its logging: the client, and the LocalCluster it may start."""
    from dask.distributed import Client, LocalCluster

    if scheduler:
        check_answers_as_dask(scheduler)
        why = None
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            why = f"--scheduler {scheduler}: cannot reach the Dask scheduler ({e})"
        except Exception as e:  # a malformed address (ValueError) or a host name that does not resolve
            why = (f"--scheduler {scheduler}: not a reachable Dask scheduler address, e.g. tcp://host:8786 "
                   f"({type(e).__name__}: {e})")
        if why:
            # The client that failed to connect stays "connecting" in a reference cycle (its
            # traceback). Collected later, while another client starts, its close() waits for
            # the lock that start holds (distributed 2026.8): collect it now, outside the
            # exception, and raise without it.
            gc.collect()
            raise ClusterError(why)
        try:
            yield client
        finally:
            client.close()
        return
    if n_workers is None or n_workers < 1:
        raise ClusterError(f"--workers must be at least 1, got {n_workers}")
    check_memory_limit(memory_limit)
    import os

    import dask

    # A nanny sets its pre-spawn variables in this process's os.environ before spawning, and
    # a value found there wins over the configuration: a LocalCluster of Dask's defaults
    # started earlier in this process would hand its MALLOC_TRIM_THRESHOLD_ to ours. Removed,
    # not put back: this process read it, if at all, when it started; only what it spawns sees it.
    if os.environ.get(TRIM_VARIABLE) == DASK_TRIM_VALUE:
        del os.environ[TRIM_VARIABLE]
    preload = [*dask.config.get("distributed.worker.preload", []), IGNORE_CTRL_C]
    with dask.config.set({**WORKER_ENVIRON, **LOOP_TICK, **NO_WORKER_PROFILER, "distributed.worker.preload": preload}):
        cluster = LocalCluster(n_workers=int(n_workers), threads_per_worker=1, processes=True,
                               memory_limit=memory_limit, dashboard_address=":0")
    client = Client(cluster)
    try:
        yield client
    finally:
        quiet_workers_for_shutdown(client)
        client.close()
        cluster.close()


def check_memory_limit(memory_limit) -> int | None:
    """The bytes each LocalCluster worker may hold (None: no limit), or a ClusterError for a
    limit that is not a size (`--memory-limit lots`) or below what a worker needs at rest."""
    import logging

    from distributed.worker_memory import parse_memory_limit

    try:  # as each worker will read it (one thread; "auto": the machine's memory over its cores)
        limit = parse_memory_limit(memory_limit, 1, logger=logging.getLogger("distributed"))
    except (ValueError, TypeError):
        raise ClusterError(f"--memory-limit {memory_limit}: not a size; give one such as 4GB or 800MB, or auto "
                           "(the machine's memory shared out)") from None
    if limit is not None and limit < MIN_WORKER_MEMORY:
        from dask.utils import format_bytes

        raise ClusterError(f"--memory-limit {memory_limit}: {format_bytes(limit)} a worker is below the "
                           f"{MIN_WORKER_MEMORY // 2 ** 20} MiB a worker holds before its first tile (its workers would "
                           "be restarted for ever); give more, or fewer --workers")
    return limit


def check_answers_as_dask(scheduler: str, timeout_s: float | None = None) -> None:
    """A ClusterError when something listens at a tcp:// `scheduler` address but does not send
    a Dask handshake within `timeout_s` (default SCHEDULER_ANSWER_S): a web server, another
    service. An address nothing listens at, or of another scheme, is left to Dask's client."""
    from distributed.comm.addressing import parse_address, parse_host_port

    timeout_s = SCHEDULER_ANSWER_S if timeout_s is None else timeout_s
    try:
        scheme, location = parse_address(scheduler)
        if scheme != "tcp":
            return
        host, port = parse_host_port(location)
        conn = socket.create_connection((host, port), timeout=timeout_s)
    except Exception:  # a malformed address, a name that does not resolve, nothing listening: Dask says it
        return
    end = time.monotonic() + timeout_s
    with conn:
        try:
            header = _receive(conn, 8, end)
            size = struct.unpack("Q", header)[0] if len(header) == 8 else 0
            if not 0 < size <= MAX_HANDSHAKE_BYTES:
                raise ClusterError(f"--scheduler {scheduler}: the server there is not a Dask scheduler (it answered "
                                   f"{header!r}, not a Dask handshake)")
            _receive(conn, size, end)
        except (TimeoutError, socket.timeout):
            raise ClusterError(f"--scheduler {scheduler}: the server there did not answer as a Dask scheduler within "
                               f"{timeout_s:g} s (it accepts connections but sent no handshake); check the "
                               "address and port (the scheduler's, usually 8786)") from None
        except OSError as e:
            raise ClusterError(f"--scheduler {scheduler}: the server there closed the connection instead of answering "
                               f"as a Dask scheduler ({e.strerror or e})") from None


def _receive(conn, n: int, end: float) -> bytes:
    data = b""
    while len(data) < n:
        conn.settimeout(max(0.01, end - time.monotonic()))
        chunk = conn.recv(n - len(data))
        if not chunk:
            if not data:
                raise ConnectionResetError(0, "closed without a word")
            return data
        data += chunk
    return data


def dask_setup(worker) -> None:
    """Dask's preload hook, in each worker of a LocalCluster this module starts: Ctrl-C is the
    command's, not the worker's (see IGNORE_CTRL_C)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def quiet_workers_for_shutdown(client) -> None:
    """Silence the workers' Dask logs of a LocalCluster about to close: its scheduler may go
    before a worker's heartbeat lands, and that worker then prints a 30-line CommClosedError
    traceback ("Failed to communicate with scheduler during heartbeat") after the command's
    results are written (seen on a busy machine). Nothing a worker says while its cluster
    closes concerns the run; workers already gone are left as they are. Each worker's
    objects are frozen too (`_ready_for_exit`): its process then ends without collecting."""
    # a worker lost or a cluster already closing: nothing left to silence
    with contextlib.suppress(Exception):
        client.run(_ready_for_exit)


def _ready_for_exit() -> None:
    """In each worker about to close: no more Dask logs, and no last garbage collections
    when its process ends. Python's collections as it clears the worker's modules took
    ~0.5 s of each worker's core, and the cluster's close waited for them: 0.6 s against
    0.1 s with the worker's objects frozen (`gc.freeze`, where the collector never looks;
    a 2-worker run of 160 buildings, twice each). Only the workers of a LocalCluster this
    process started and is closing: an existing scheduler's workers live on."""
    import gc
    import logging

    logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)
    gc.freeze()


def describe_cluster(client, n_workers: int | None, scheduler: str | None) -> str:
    """The line a command prints before its tasks start: where they run, and the dashboard."""
    where = f"scheduler {scheduler}" if scheduler else f"a LocalCluster of {n_workers} workers"
    board = dashboard_address(client)
    return f"Dask: {where}" + (f"; dashboard {board}" if board else "")


def dashboard_address(client) -> str | None:
    try:
        return client.dashboard_link
    except Exception:  # no dashboard (bokeh missing): the run goes on without one
        return None


__all__ = ["WORKER_ENVIRON", "ClusterError", "check_answers_as_dask", "check_memory_limit", "dashboard_address",
           "dask_client", "describe_cluster", "quiet_workers_for_shutdown"]
