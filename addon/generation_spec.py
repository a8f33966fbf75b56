"""One job of the headless scene generator: what to make and where (standard library only:
the generator reads it before Blender's modules load, and the library writes the same
document without importing the add-on).

A job crosses the process boundary as one JSON file, `generate_scenes.py --spec FILE.json`,
whose keys are the fields of `GenerationSpec`; the script's command-line options build the
same spec, one option a field (`--set` is `set_name`, `--grade-mix` `grade_mix`, `--grades`
`grades`, `--settle-steps` `settle_steps`). `checked` is the one place a job is refused, so
both forms refuse the same jobs in the same words, naming the documented options.
`quakescan.generator.GenerationSpec` mirrors the fields (tests/addon/test_addon_generation_spec.py
holds the two to each other).
"""
from __future__ import annotations

import json
import sys
from dataclasses import MISSING, asdict, dataclass, fields, replace
from pathlib import Path

# The generator's name in its records (scene.json "generator"), its messages and its refusals
# ("generate_scenes.py: error: ...", which the library reads).
PROG = "generate_scenes.py"

# citygen.SETS and "bundle" (spelt out: the spec is checked before the add-on's numpy modules load)
SETS = ("generic", "region", "small", "bundle")
DATASETS = ("paper", "mixed")
DETAILS = ("none", "typical")
STREETSCAPES = ("none", "typical")
DAMAGES = ("patterns", "physics", "both")
DEFAULT_BUILDINGS = 112
SEED_LIMIT = 2 ** 32


class SpecError(ValueError):
    """A job the generator refuses, in the words of its command-line options."""


@dataclass(frozen=True)
class GenerationSpec:
    """A batch of scene bundles: a city (or a source bundle's buildings), its damage and where
    the bundles go (the script's module doc says what each option does)."""

    set_name: str  # generic | region | small | bundle
    dataset: str  # paper | mixed
    buildings: int | None  # None: 112 for a procedural set, every source building for "bundle"
    seed: int
    out: str  # output folder
    source: str | None = None  # set "bundle": the scene bundle whose buildings are damaged
    grade_mix: dict | None = None  # dataset "mixed": {grade: count}; fixes the buildings' number
    grades: str | None = None  # set "bundle", dataset "mixed": a JSON file {building ID: grade}
    details: str = "none"  # none | typical roof and facade details
    streetscape: str = "none"  # none | typical trees, hedges, cars and street furniture
    origin: tuple | None = None  # procedural sets: (x, y, z) of the local origin in the world
    crs: str | None = None  # procedural sets: the CRS the bundles name
    damage: str = "patterns"  # how grades 4-5 are made: patterns | physics | both
    settle_steps: int = 250  # damage physics|both: frames a collapse may take to come to rest
    force: bool = False  # regenerate bundles made with other settings
    jobs: int = 1  # processes at once

    def checked(self) -> GenerationSpec:
        """The job with its defaults filled in (the buildings' number), or SpecError."""
        s = self
        _choice("--set", s.set_name, SETS)
        _choice("--dataset", s.dataset, DATASETS)
        _choice("--details", s.details, DETAILS)
        _choice("--streetscape", s.streetscape, STREETSCAPES)
        _choice("--damage", s.damage, DAMAGES)
        if s.buildings is not None:
            _at_least_one("--buildings", s.buildings)
        _at_least_one("--settle-steps", s.settle_steps)
        _at_least_one("--jobs", s.jobs)
        if _not_int(s.seed) or not 0 <= s.seed < SEED_LIMIT:
            raise SpecError(f"argument --seed: seed must be in 0..2^32-1, got {s.seed!r}")
        if not isinstance(s.out, str) or not s.out:
            raise SpecError(f"argument --out: expected a folder, got {s.out!r}")
        for option, value in (("--source", s.source), ("--grades", s.grades), ("--crs", s.crs)):
            if value is not None and not isinstance(value, str):
                raise SpecError(f"argument {option}: expected text, got {value!r}")
        if not isinstance(s.force, bool):
            raise SpecError(f"force: expected true or false, got {s.force!r}")
        if s.origin is not None:
            s = replace(s, origin=_origin(s.origin))
        if s.set_name == "bundle" and not s.source:
            raise SpecError("--set bundle needs --source SCENE_DIR")
        if s.grade_mix is not None:
            s = replace(s, grade_mix=_grade_mix(s.grade_mix))
            if s.dataset != "mixed":
                raise SpecError("--grade-mix is only used with --dataset mixed")
            total = sum(s.grade_mix.values())
            if s.buildings is not None and s.buildings != total:
                raise SpecError(f"--buildings {s.buildings} disagrees with --grade-mix, which sums to {total}")
            s = replace(s, buildings=total)
        if s.grades is not None:
            if s.set_name != "bundle" or s.dataset != "mixed":
                raise SpecError("--grades is only used with --set bundle --dataset mixed")
            if s.grade_mix is not None:
                raise SpecError("--grades and --grade-mix both set the grades: give one")
        if s.set_name == "bundle" and (s.origin is not None or s.crs):
            raise SpecError("--origin and --crs are not used with --set bundle: the output keeps the source's")
        if s.set_name != "bundle":
            if s.source:
                raise SpecError("--source is only used with --set bundle")
            if s.buildings is None:
                s = replace(s, buildings=DEFAULT_BUILDINGS)
        return s

    def to_json(self) -> dict:
        d = asdict(self)
        if self.grade_mix is not None:
            d["grade_mix"] = {str(g): n for g, n in sorted(self.grade_mix.items())}
        if self.origin is not None:
            d["origin"] = list(self.origin)
        return d

    @classmethod
    def from_json(cls, doc) -> GenerationSpec:
        """The spec of a JSON document (unchecked: `checked` refuses what it must)."""
        if not isinstance(doc, dict):
            raise SpecError(f"expected an object of {', '.join(FIELDS)}, got {type(doc).__name__}")
        unknown = sorted(set(doc) - set(FIELDS))
        if unknown:
            raise SpecError(f"unknown field(s) {', '.join(unknown)}; the fields are {', '.join(FIELDS)}")
        missing = [f.name for f in fields(cls) if f.default is MISSING and f.name not in doc]
        if missing:
            raise SpecError(f"missing field(s) {', '.join(missing)}")
        d = dict(doc)
        if isinstance(d.get("origin"), list):
            d["origin"] = tuple(d["origin"])
        return cls(**d)

    def write(self, path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1, sort_keys=True) + "\n")

    @classmethod
    def read(cls, path) -> GenerationSpec:
        """The checked spec of a JSON file; SpecError naming the file and what is wrong."""
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise SpecError(f"--spec {path}: cannot read it as JSON ({e})") from None
        try:
            return cls.from_json(doc).checked()
        except (SpecError, TypeError) as e:
            raise SpecError(f"--spec {path}: {e}") from None


FIELDS = tuple(f.name for f in fields(GenerationSpec))


def log(msg: str) -> None:
    """A progress or error line of the generator (stderr: its output is the bundles)."""
    print(f"[{PROG}] {msg}", file=sys.stderr, flush=True)


def _not_int(v) -> bool:
    return isinstance(v, bool) or not isinstance(v, int)


def _choice(option, value, choices):
    if value not in choices:
        raise SpecError(f"argument {option}: invalid choice: {value!r} (choose from "
                        f"{', '.join(map(repr, choices))})")


def _at_least_one(option, value):
    if _not_int(value):
        raise SpecError(f"argument {option}: expected an integer, got {value!r}")
    if value < 1:
        raise SpecError(f"argument {option}: must be at least 1, got {value}")


def _origin(value) -> tuple:
    v = list(value) if isinstance(value, (list, tuple)) else None
    if (v is None or len(v) not in (2, 3) or any(_not_int(c) and not isinstance(c, float) for c in v)
            or not all(abs(c) < 1e8 for c in v)):  # NaN fails too
        raise SpecError(f"argument --origin: expected X,Y or X,Y,Z, each finite and within 1e8 m, got {value!r}")
    return tuple([float(c) for c in v] + [0.0] * (3 - len(v)))


def _grade_mix(value) -> dict:
    """{grade: count} with integer keys (a JSON document's keys are text)."""
    try:
        mix = {int(g): n for g, n in dict(value).items()}
    except (TypeError, ValueError):
        raise SpecError(f"argument --grade-mix: expected {{grade: count}}, got {value!r}") from None
    if (not mix or any(g not in range(6) for g in mix) or any(_not_int(n) or n < 0 for n in mix.values())
            or sum(mix.values()) < 1):
        raise SpecError(f"argument --grade-mix: grades must be 0, 1, 2, 3, 4, 5 with counts >= 0 summing to >= 1, "
                        f"got {value!r}")
    return mix

