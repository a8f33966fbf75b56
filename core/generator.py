"""The add-on's headless scene generator (blender_scripts/generate_scenes.py), run as a
separate process: `quakescan` never imports bpy. It needs Blender's Python: the `bpy` module
in this environment (set-up installs it) or a `blender` binary on PATH. A job is one
`GenerationSpec`, handed to the generator as one JSON file (`--spec`).

Below every command that makes scenes (the demo, the training set, the injector, the
experiments), so none of them imports another to reach it.
"""
from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
import tempfile
from dataclasses import MISSING, asdict, dataclass, fields
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


@dataclass(frozen=True)
class GenerationSpec:
    """One job of the scene generator: the fields of the add-on's `GenerationSpec`
    (addon/generation_spec.py, which says what each means and refuses bad values), kept here
    because the library never imports the add-on; tests/addon/test_addon_generation_spec.py
    holds the two field for field. `grade_mix` (grade -> count) fixes a mixed city's grades;
    `source`: the scene bundle whose buildings set "bundle" damages; `grades` (set "bundle",
    dataset "mixed"): a JSON file {building ID: grade} fixing each listed building's grade
    (the others 0); `details` and `streetscape` "typical" add roof and facade details or
    trees, hedges, cars and street furniture; `origin` (x, y, z) and `crs` place a
    procedural city in the world; `damage` "physics" or "both" makes grades 4-5 (all, or a
    seeded half) by rigid-body collapse; `force` regenerates bundles made with other
    settings (finished ones with the same settings are kept)."""

    set_name: str  # generic | region | small | bundle
    dataset: str  # paper | mixed
    buildings: int | None  # None: 112 for a procedural set, every source building for "bundle"
    seed: int
    out: Path | str
    source: Path | str | None = None
    grade_mix: dict | None = None
    grades: Path | str | None = None
    details: str = "none"
    streetscape: str = "none"
    origin: tuple | None = None
    crs: str | None = None
    damage: str = "patterns"
    settle_steps: int = 250
    force: bool = False
    jobs: int = 1

    def to_json(self) -> dict:
        """The document `generate_scenes.py --spec` reads."""
        d = asdict(self)
        for key in ("out", "source", "grades"):
            if d[key] is not None:
                d[key] = str(d[key])
        if self.grade_mix is not None:
            d["grade_mix"] = {str(g): n for g, n in sorted(self.grade_mix.items())}
        if self.origin is not None:
            d["origin"] = [float(v) for v in self.origin]
        return d

    def describe(self) -> str:
        """The job in a message: the fields that differ from their defaults."""
        doc, defaults = self.to_json(), {f.name: f.default for f in fields(self)}
        return ", ".join(f"{k} {v}" for k, v in doc.items() if defaults[k] is MISSING or v != defaults[k])


def generate(spec: GenerationSpec) -> None:
    """Run the add-on's scene generator on `spec`, handed over as one JSON file."""
    with tempfile.TemporaryDirectory(prefix="quakescan-generate-") as tmp:
        job = Path(tmp) / "spec.json"
        job.write_text(json.dumps(spec.to_json(), indent=1, sort_keys=True) + "\n")
        cmd = generator_command(["--spec", str(job)])
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        usage = [ln for ln in proc.stderr.splitlines() if ln.startswith(f"{GENERATOR.name}: error:")]
        if usage:  # it refused the job: say so without its usage text, nor the file's name
            reason = usage[-1].split("error:", 1)[1].strip().replace(f"--spec {job}: ", "")
            raise GeneratorError(f"the scene generator refused {spec.describe()}: {reason}")
        tail = "\n".join(proc.stderr.strip().splitlines()[-8:])
        raise GeneratorError(f"scene generation failed (exit {proc.returncode}) for {spec.describe()}: "
                             f"{' '.join(cmd)}\n{tail}")


__all__ = ["GENERATOR", "GenerationSpec", "GeneratorError", "generate", "generator_command"]
