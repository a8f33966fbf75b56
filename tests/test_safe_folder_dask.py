"""Dask that cannot hang (issue 45): a server that does not answer as a Dask scheduler is an
error within a timeout, a memory limit that is not a size or below what a worker needs is
refused up front, and Ctrl-C under --workers gives one line and status 130."""
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from quakescan.cli import main
from quakescan.distributed import cluster
from tests.safe_folder_pair import names, pair  # noqa: F401  (a fixture)

distributed = pytest.importorskip("distributed")
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}


class PlainServer:
    """A TCP server that is not Dask: "silent" accepts and says nothing, "http" answers a
    request as a web server does, "banner" speaks first, in HTTP."""

    def __init__(self, mode):
        self.mode, self.sock = mode, socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]
        self.held = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            self.held.append(c)
            try:
                if self.mode == "http":
                    c.settimeout(30)
                    c.recv(65536)
                    c.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
                elif self.mode == "banner":
                    c.sendall(b"HTTP/1.0 200 OK\r\n\r\nhello")
            except OSError:
                pass

    def close(self):
        self.sock.close()
        for c in self.held:
            c.close()


@pytest.mark.parametrize("mode, said", [("silent", "did not answer as a Dask scheduler within 2 s"),
                                        ("http", "did not answer as a Dask scheduler within 2 s"),
                                        ("banner", "is not a Dask scheduler (it answered b'HTTP/1.0'")])
def test_a_server_that_is_not_a_scheduler_is_an_error_within_the_timeout(pair, tmp_path, capsys, monkeypatch,  # noqa: F811
                                                                          mode, said):
    monkeypatch.setattr(cluster, "SCHEDULER_ANSWER_S", 2.0)
    server = PlainServer(mode)
    try:
        t0 = time.monotonic()
        assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "--model",
                     str(pair / "model.skops"), "-o", str(tmp_path / "out"), "--scheduler",
                     f"tcp://127.0.0.1:{server.port}"]) == 2
        assert time.monotonic() - t0 < 15
    finally:
        server.close()
    err = capsys.readouterr().err
    assert f"quakescan: error: --scheduler tcp://127.0.0.1:{server.port}: the server there " in err and said in err
    assert not (tmp_path / "out").exists()


def test_a_real_scheduler_answers_the_check():
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as c:
        t0 = time.monotonic()
        cluster.check_answers_as_dask(c.scheduler_address, timeout_s=10)
        assert time.monotonic() - t0 < 5
        with cluster.dask_client(scheduler=c.scheduler_address) as client:
            assert client.scheduler_info()["address"] == c.scheduler_address


@pytest.mark.parametrize("workers, limit, said", [("1", "1MB", "--memory-limit 1MB: 0.95 MiB a worker is below"),
                                                  ("2", "60MB", "--memory-limit 60MB: 57.22 MiB a worker is below"),
                                                  ("1", "lots", "--memory-limit lots: not a size")])
def test_a_memory_limit_no_worker_can_run_in_is_refused_up_front(pair, tmp_path, capsys, workers, limit,  # noqa: F811
                                                                 said):
    t0 = time.monotonic()
    assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "--model",
                 str(pair / "model.skops"), "-o", str(tmp_path / "out"), "--workers", workers,
                 "--memory-limit", limit]) == 2
    assert time.monotonic() - t0 < 10  # no cluster started
    err = capsys.readouterr().err
    assert f"quakescan: error: {said}" in err and "Traceback" not in err and not (tmp_path / "out").exists()
    assert cluster.check_memory_limit("auto") is None or cluster.check_memory_limit("auto") > cluster.MIN_WORKER_MEMORY
    assert cluster.check_memory_limit(0) is None  # Dask's "no limit"


def test_ctrl_c_under_two_workers_is_one_line_and_status_130(pair, tmp_path):  # noqa: F811
    """SIGINT to the whole process group, as a terminal's Ctrl-C sends it: before, each worker
    printed its own tracebacks (77 lines) above the command's note."""
    cmd = [sys.executable, "-m", "quakescan.cli", "classify", "--pre", str(pair / "pre.las"), "--post",
           str(pair / "post.las"), "--model", str(pair / "model.skops"), "-o", str(tmp_path / "out"),
           "--workers", "2", "--memory-limit", "2GB", "--progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                         start_new_session=True)
    try:
        seen = []
        while not seen or "classify: tiling" not in seen[-1]:
            line = p.stdout.readline()
            assert line, "".join(seen) + p.stderr.read()
            seen.append(line)
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    if p.returncode == 0:
        pytest.skip("the run finished before the signal came")
    assert p.returncode == 130, err
    assert err.splitlines() == ["quakescan: interrupted; nothing partial was left under the output names (a rerun of "
                                "scan or classify continues from its finished flight lines or tiles)"]
