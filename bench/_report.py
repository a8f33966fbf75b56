"""Shared by the benchmarks: machine line, peak memory, and writing a section of BENCHMARKS.md."""
from __future__ import annotations

import os
import platform
import re
import resource
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_child(cmd: list) -> dict:
    """Run `cmd` in a fresh child and return its exit code, stderr, wall seconds and peak RSS
    (MiB). A small wrapper process runs it, so that its RUSAGE_CHILDREN is this run's alone."""
    import json
    import subprocess
    import sys

    wrapper = ("import json, resource, subprocess, sys, time; t0 = time.perf_counter(); "
               "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
               "print(json.dumps({'rc': r.returncode, 'err': r.stderr, 'wall': time.perf_counter() - t0, "
               "'peak_kb': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))")
    res = subprocess.run([sys.executable, "-c", wrapper, *cmd], capture_output=True, text=True)
    info = json.loads(res.stdout.strip().splitlines()[-1])
    return {"rc": info["rc"], "stderr": info["err"], "wall_s": info["wall"], "peak_mb": info["peak_kb"] / 1024}


def table(headers, rows) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def write_section(name: str, text: str) -> None:
    """Replace (or append) the section between `<!-- name -->` markers in BENCHMARKS.md."""
    start, end = f"<!-- {name} start -->", f"<!-- {name} end -->"
    block = f"{start}\n{text.strip()}\n{end}"
    old = BENCHMARKS.read_text() if BENCHMARKS.exists() else "# Benchmarks\n\nWritten by the scripts in `bench/`; rerun one to refresh its section.\n"
    if start in old and end in old:
        new = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _: block, old, flags=re.S)
    else:
        new = old.rstrip() + "\n\n" + block + "\n"
    tmp = BENCHMARKS.with_name(BENCHMARKS.name + ".tmp")
    tmp.write_text(new)
    os.replace(tmp, BENCHMARKS)
