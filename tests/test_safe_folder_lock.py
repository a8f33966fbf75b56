"""One run per output folder at a time (issue 45): a second run into a folder another process
is writing gets a clear error naming that process; the lock a killed run leaves is taken
over; the folder keeps no lock file."""
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from quakescan.cli import main
from quakescan.assessment.run import classify
from quakescan.errors import ClassifyError
from quakescan.runtime.output_folder import LOCK_NAME, exclusive_run
from tests.safe_folder_pair import RESULTS, names, pair  # noqa: F401  (a fixture)

ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
HOLD = """
import sys
from quakescan.runtime.output_folder import exclusive_run
with exclusive_run(sys.argv[1], "classify"):
    print("held", flush=True)
    sys.stdin.read()
"""


def _holder(out):
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         env=ENV, text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def test_a_second_process_is_refused_naming_the_holder_and_a_killed_holders_lock_is_taken_over(
        pair, tmp_path, caplog):  # noqa: F811
    out = tmp_path / "out"
    holder = _holder(out)
    try:
        with pytest.raises(ClassifyError, match=rf"{out}: another run is writing into this output folder \(pid "
                                                rf"{holder.pid} on .*, quakescan classify, since "):
            classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")
        assert names(out) == [LOCK_NAME]  # nothing of this run written
    finally:
        holder.send_signal(signal.SIGKILL)  # a crash: its lock file stays, the system's lock goes
        holder.wait()
    assert names(out) == [LOCK_NAME]
    with caplog.at_level(logging.WARNING):
        classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")
    assert f"the lock of an earlier run that did not finish (pid {holder.pid} on" in caplog.text
    assert names(out) == RESULTS


def test_two_classify_processes_with_the_same_inputs_one_runs_the_other_is_told(pair, tmp_path):  # noqa: F811
    """Before, one of them failed with "cannot write (No such file or directory)" (the other
    had renamed its temporary file away)."""
    out = tmp_path / "out"
    args = ["--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "--model", str(pair / "model.skops"),
            "-o", str(out)]
    first = subprocess.Popen([sys.executable, "-m", "quakescan.cli", "classify", *args], env=ENV,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 120
    while not (out / LOCK_NAME).exists() and first.poll() is None and time.monotonic() < end:
        time.sleep(0.005)
    second = subprocess.run([sys.executable, "-m", "quakescan.cli", "classify", *args], env=ENV,
                            capture_output=True, text=True, timeout=300)
    stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert second.returncode == 2
    assert (f"quakescan: error: {out}: another run is writing into this output folder (pid {first.pid} on"
            in second.stderr)
    assert "cannot write" not in second.stderr and names(out) == RESULTS


def test_two_runs_in_one_process_are_two_runs(tmp_path):
    out = tmp_path / "out"
    inside, leave = threading.Event(), threading.Event()

    def hold():
        with exclusive_run(out, "classify"):
            inside.set()
            leave.wait(30)

    t = threading.Thread(target=hold)
    t.start()
    try:
        assert inside.wait(30)
        with pytest.raises(ClassifyError, match=f"pid {os.getpid()} on"):
            with exclusive_run(out, "classify", ClassifyError):
                pass
    finally:
        leave.set()
        t.join(30)
    with exclusive_run(out, "classify"):  # free again
        assert names(out) == [LOCK_NAME]
    assert not out.exists()  # made for a run that wrote nothing: not left behind


def test_a_lock_file_that_is_a_link_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "victim").write_text("keep")
    os.symlink(tmp_path / "victim", out / LOCK_NAME)
    with pytest.raises(ClassifyError, match="not QuakeScan's lock file"):
        with exclusive_run(out, "classify", ClassifyError):
            pass
    assert (tmp_path / "victim").read_text() == "keep"


@pytest.mark.parametrize("command", [["inject", "{d}/cloud.las", "--footprints", "{d}/fp.geojson", "-o", "{out}"],
                                     ["training-set", "--size", "quick", "-o", "{out}"],
                                     ["experiment", "paper", "-o", "{out}"]])
def test_every_command_that_writes_a_folder_takes_its_lock(tmp_path, capsys, command):
    out = tmp_path / "out"
    holder = _holder(out)
    try:
        args = [a.format(d=tmp_path, out=out) for a in command]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"quakescan: error: {out}: another run is writing into this output folder (pid {holder.pid}" in err
        assert names(out) == [LOCK_NAME]
    finally:
        holder.stdin.close()  # the holder leaves: its lock file goes with it
        holder.wait(30)
    assert not out.exists()
