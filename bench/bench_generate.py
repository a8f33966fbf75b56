"""Time and peak memory to generate the paper's generic dataset: 112 buildings, pre + 3 post scenes.

    .venv/bin/python bench/bench_generate.py     # prints the table, rewrites its section of BENCHMARKS.md

Runs blender_scripts/generate_scenes.py in a fresh process with the bpy module and, when a
`blender` binary is on PATH (Debian's 3.4 LTS), with `blender -b` too, side by side.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._report import machine, run_child, table, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "blender_scripts" / "generate_scenes.py"
ARGS = ["--set", "generic", "--dataset", "paper", "--buildings", "112", "--seed", "1"]


def run(cmd: list, out: Path) -> dict:
    """Wall time and peak RSS of one generator process (a fresh child each time)."""
    r = run_child([*cmd, "--out", str(out)])
    if r["rc"] != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r['stderr'][-2000:]}")
    wall, peak_mb = r["wall_s"], r["peak_mb"]
    faces = {}
    for scene in ("pre", "post_heavy", "post_extreme", "post_destruction"):
        head = (out / scene / "mesh.ply").read_bytes()[:400].decode("ascii", "replace")
        faces[scene] = int(head.split("element face ")[1].split()[0])
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"wall_s": wall, "peak_mb": peak_mb, "faces": faces, "mb": size / 2 ** 20}


def main():
    runners = [("bpy module (Python 3.11)", [sys.executable, str(SCRIPT), *ARGS])]
    blender = shutil.which("blender")
    if blender:
        version = subprocess.run([blender, "--version"], capture_output=True, text=True).stdout.split("\n")[0]
        runners.append((f"`blender -b` ({version.strip()})",
                        [blender, "-b", "--factory-startup", "--python-exit-code", "1", "-P", str(SCRIPT), "--",
                         *ARGS]))
    rows, results = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, cmd) in enumerate(runners):
            r = run(cmd, Path(tmp) / f"run{k}")
            results[label] = r
            print(f"{label}: {r['wall_s']:.1f} s, peak {r['peak_mb']:.0f} MiB, faces {r['faces']}", flush=True)
            rows.append((label, f"{r['wall_s']:.1f}", "≤ 180", f"{r['peak_mb']:.0f}",
                         " / ".join(f"{v:,}" for v in r["faces"].values()), f"{r['mb']:.1f}"))
    text = "\n\n".join([
        "## Scene generation (`bench/bench_generate.py`)",
        f"Machine: {machine()}. The paper's generic dataset: 112 buildings, scene bundles `pre`, `post_heavy`, "
        "`post_extreme`, `post_destruction` (`generate_scenes.py --set generic --dataset paper --buildings 112 "
        "--seed 1`), each run a fresh process writing a fresh folder. Command: "
        "`.venv/bin/python bench/bench_generate.py`.",
        table(["runner", "wall s", "target s", "peak MiB", "faces pre / heavy / extreme / destruction", "output MiB"],
              rows),
    ])
    print("\n" + text)
    write_section("bench_generate", text)


if __name__ == "__main__":
    main()
