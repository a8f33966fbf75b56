"""Pattern registry: name → bmesh function, and damage by EMS-98 grade.

Every pattern function has the signature ``fn(bm, spec, rng, building_id, **params) -> dict``
and returns the parameters it realised (after clamping to what the building allows) plus
measures such as ``debris_volume``; that dict is what the scene manifest records.
"""
from __future__ import annotations

import inspect

import numpy as np

from .. import ems98
from . import collapse, details, elements, openings, rigid
from .common import PatternNotApplicable, rnd

FUNCTIONS = {
    "roof_holes": openings.roof_holes,
    "wall_holes": openings.wall_holes,
    "partial_roof_collapse": collapse.partial_roof_collapse,
    "top_storey_collapse": collapse.top_storey_collapse,
    "pancake_collapse": collapse.pancake_collapse,
    "soft_storey_collapse": collapse.soft_storey_collapse,
    "tilt": rigid.tilt,
    "debris_heap": collapse.debris_heap,
    "gable_fall": elements.gable_fall,
    "facade_topple": elements.facade_topple,
    "parapet_loss": elements.parapet_loss,
    "infill_blowout": openings.infill_blowout,
    "top_floor_pancake": collapse.top_floor_pancake,
    "corner_failure": collapse.corner_failure,
    "mid_storey_collapse": collapse.mid_storey_collapse,
    "wing_collapse": collapse.wing_collapse,
    "overturn": rigid.overturn,
    "chimney_loss": elements.chimney_loss,
}
assert set(FUNCTIONS) == set(ems98.PATTERN_NAMES), "pattern table and functions disagree"


def register_pattern(pattern: ems98.Pattern, function, primary: float = 0.0, secondary: float = 0.0) -> None:
    """A new damage pattern: its catalogue entry (`ems98.register`, with its choice weights)
    and its bmesh function ``fn(bm, spec, rng, building_id, **params) -> dict``, whose keyword
    parameters must be the pattern's `params` (each grade's overrides included)."""
    accepted = set(inspect.signature(function).parameters) - {"bm", "spec", "rng", "building_id"}
    wanted = set(pattern.params).union(*(set(o) for o in pattern.grade_params.values()))
    if not wanted <= accepted and not any(p.kind == p.VAR_KEYWORD
                                          for p in inspect.signature(function).parameters.values()):
        raise ValueError(f"damage pattern {pattern.name!r}: its function takes no parameter(s) "
                         f"{sorted(wanted - accepted)}")
    ems98.register(pattern, primary, secondary)
    FUNCTIONS[pattern.name] = function


def unregister_pattern(name: str) -> None:
    """Take a pattern registered with `register_pattern` out again."""
    ems98.unregister(name)
    FUNCTIONS.pop(name, None)


def pattern_rng(seed: int, *salt: int) -> np.random.Generator:
    """The random generator of one building's damage: same seed and salt → same draws."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *[int(s) & 0xFFFFFFFF for s in salt]])


def apply_pattern(bm, spec, name: str, params: dict | None, rng, building_id: int) -> dict:
    """Apply one pattern; returns the manifest record {"name", "params"}.
    Raises PatternNotApplicable when the building lacks what the pattern needs."""
    try:
        fn = FUNCTIONS[name]
    except KeyError:
        raise ValueError(f"unknown damage pattern {name!r}; known: {', '.join(FUNCTIONS)}") from None
    params = dict(params or ems98.default_params(name, material=spec.material))
    accepted = set(inspect.signature(fn).parameters) - {"bm", "spec", "rng", "building_id"}
    unknown = set(params) - accepted
    if unknown:
        raise ValueError(f"pattern {name!r} has no parameter(s) {sorted(unknown)}; it takes {sorted(accepted)}")
    realised = fn(bm, spec, rng, building_id, **params)
    # Details resting on an element that fell away fall too (rigid motions carry them along).
    if ems98.PATTERNS[name].stage < 3:
        fallen = details.settle(bm, spec, building_id)
        if fallen:
            realised["details_fallen"] = fallen
    return {"name": name, "params": rnd(realised)}


def damage_for_grade(bm, spec, grade: int, rng, building_id: int, vulnerability_class: str | None = None,
                     secondary_probability: float = 0.4):
    """Choose patterns for the grade and material (ems98.choose_patterns) and apply them to
    a copy of `bm`. A plan the building cannot take is re-drawn (up to 8 times).

    Returns (new BMesh, records); `bm` itself is left untouched (the caller frees both).
    """
    features = spec.features()
    last = None
    for attempt in range(8):
        # each pattern draws its parameters and geometry from a stream of its own, salted by its
        # name: adding a pattern to the catalogue (or a secondary pattern drawing more numbers)
        # changes no other pattern's output
        base, streams = int(rng.integers(0, 2 ** 32)), {}

        def stream(name, base=base, streams=streams):
            return streams.setdefault(name, pattern_rng(base, ems98.pattern_salt(name)))

        plan = ems98.choose_patterns(grade, spec.material, features, rng, vulnerability_class,
                                     secondary_probability, streams=stream)
        trial = bm.copy()
        try:
            records = [apply_pattern(trial, spec, n, p, stream(n), building_id) for n, p in plan]
        except PatternNotApplicable as e:
            trial.free()
            last = e
            continue
        return trial, records
    raise PatternNotApplicable(f"no damage pattern for grade {grade} fits this building ({last})")
