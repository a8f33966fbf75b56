"""The add-on's headless scene generator (blender_scripts/generate_scenes.py), run as a
separate process: `quakescan` never imports bpy. It needs Blender's Python: the `bpy` module
in this environment (set-up installs it) or a `blender` binary on PATH.

Below every command that makes scenes (the demo, the training set, the injector, the
experiments), so none of them imports another to reach it.
"""
from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

from .errors import QuakeScanError

PACKAGE = Path(__file__).resolve().parent
# An installed wheel carries the generator inside this package; a checkout has it only in
# blender_scripts/ beside core/, where users run it (an editable install maps nothing there).
_INSTALLED_GENERATOR = PACKAGE / "blender_scripts" / "generate_scenes.py"
GENERATOR = (_INSTALLED_GENERATOR if _INSTALLED_GENERATOR.is_file()
             else PACKAGE.parent / "blender_scripts" / "generate_scenes.py")


class GeneratorError(QuakeScanError):
    """The scene generator cannot run here, or refused or failed its run."""


def generator_command(args: list[str]) -> list[str]:
    """How to run blender_scripts/generate_scenes.py here: with the bpy module, else blender -b."""
    if not GENERATOR.is_file():
        raise GeneratorError(f"{GENERATOR}: the scene generator is missing (neither this installation nor a "
                        "source checkout has blender_scripts/generate_scenes.py)")
    if importlib.util.find_spec("bpy") is not None:
        return [sys.executable, str(GENERATOR), *args]
    blender = shutil.which("blender")
    if blender:
        return [blender, "-b", "--factory-startup", "--python-exit-code", "1", "-P", str(GENERATOR), "--", *args]
    raise GeneratorError("generating scenes needs Blender's Python: `pip install bpy==5.0.1` (Python 3.11) or a "
                    "`blender` binary on PATH")


def generate(set_name: str, dataset: str, buildings: int | None, seed: int, out: Path,
             grade_mix: dict | None = None, source: Path | None = None, details: str = "none",
             streetscape: str = "none", origin=None, crs: str | None = None, force: bool = False,
             damage: str = "patterns", grades_file: Path | None = None) -> None:
    """Run the add-on's scene generator; `grade_mix` (grade -> count) fixes a mixed city's grades;
    `source`: the scene bundle whose buildings `set_name` "bundle" damages; `details`: "none" or
    "typical" roof and facade details (dormers, chimneys, balconies, solar panels, ...);
    `streetscape` "typical" adds trees, hedges, parked cars and street furniture ("none": without);
    `origin` (x, y, z) and `crs` place a procedural city in the world; `force` regenerates
    bundles made with other settings (finished ones with the same settings are kept);
    `damage` "physics" or "both" makes grades 4-5 (all, or a seeded half) by rigid-body
    collapse instead of the parametric patterns; `grades_file` (set "bundle", dataset "mixed"): a JSON
    {building ID: grade} fixing each listed building's grade (the others 0)."""
    args = ["--set", set_name, "--dataset", dataset, "--seed", str(seed), "--out", str(out)]
    if origin is not None:
        args += ["--origin", ",".join(repr(float(v)) for v in origin)]
    if crs:
        args += ["--crs", str(crs)]
    if force:
        args += ["--force"]
    if details != "none":
        args += ["--details", details]
    if streetscape != "none":  # the generator's default: its command line stays what it was
        args += ["--streetscape", streetscape]
    if source is not None:
        args += ["--source", str(source)]
    if damage != "patterns":  # the generator's default: its command line stays what it was
        args += ["--damage", damage]
    if grades_file is not None:
        args += ["--grades", str(grades_file)]
    if grade_mix:
        args += ["--grade-mix", ",".join(f"{g}:{n}" for g, n in sorted(grade_mix.items()))]
    elif buildings is not None:
        args += ["--buildings", str(buildings)]
    cmd = generator_command(args)
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        usage = [ln for ln in proc.stderr.splitlines() if ln.startswith(f"{GENERATOR.name}: error:")]
        if usage:  # its argument parser refused what it was given: say so without its usage text
            raise GeneratorError(f"the scene generator refused {' '.join(args)}: {usage[-1].split('error:', 1)[1].strip()}")
        tail = "\n".join(proc.stderr.strip().splitlines()[-8:])
        raise GeneratorError(f"scene generation failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")


__all__ = ["GENERATOR", "GeneratorError", "generate", "generator_command"]
