"""EMS-98 damage grades, building materials and the parametric damage patterns.

Pure Python (no bpy, no numpy needed): the tables the add-on's UI, operators and the
batch generator share, and the sampling of pattern parameters. Ranges follow
docs/DAMAGE_CATALOGUE.md (engineering defaults, not measurements) and stay editable here.

Angles are in degrees, lengths in metres, fractions in 0..1.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

MASONRY = "masonry"
RC = "reinforced_concrete"
MATERIALS = (MASONRY, RC)
MATERIAL_LABELS = {MASONRY: "Masonry", RC: "Reinforced concrete"}

# The one table of grade names (a copy of core/grades.py, which the add-on cannot import;
# tests/test_grades.py checks they are identical): EMS-98's names, and the paper's short
# names where space is short.
GRADE_NAMES = {0: "no damage", 1: "negligible to slight", 2: "moderate", 3: "substantial to heavy",
               4: "very heavy", 5: "destruction"}
GRADE_SHORT_NAMES = {0: "no damage", 1: "negligible", 2: "moderate", 3: "heavy", 4: "extreme", 5: "destruction"}

# EMS-98 grade -> (EMS-98 name, masonry description, RC description)
GRADES = {
    0: (GRADE_NAMES[0], "no visible damage", "no visible damage"),
    1: (GRADE_NAMES[1], "hairline cracks, plaster pieces fall", "fine cracks in plaster/infill"),
    2: (GRADE_NAMES[2], "cracks in many walls, chimneys partly fall", "cracks in columns, beams, infills"),
    3: (GRADE_NAMES[3], "large cracks in most walls, roof tiles detach, chimneys break, "
        "gable walls or partitions fail", "column/joint cracking, spalling, individual infill panels fail"),
    4: (GRADE_NAMES[4], "serious failure of walls, partial collapse of roofs and floors",
        "tilting columns, a few columns or a single upper floor collapse"),
    5: (GRADE_NAMES[5], "total or near-total collapse", "collapse of the ground floor or of parts (wings)"),
}
# The paper's target classes: grades 1-2 are geometrically "no damage" at UAV resolution.
TARGET_GRADES = (0, 3, 4, 5)

# EMS-98 vulnerability classes (A most vulnerable).
VULNERABILITY_CLASSES = ("A", "B", "C", "D", "E", "F")
VULNERABILITY_LABELS = {
    "A": "A: rubble / adobe masonry",
    "B": "B: simple stone, unreinforced brick",
    "C": "C: massive stone, masonry with RC floors, RC without seismic design",
    "D": "D: reinforced/confined masonry, RC with moderate design",
    "E": "E: RC with high seismic design",
    "F": "F: timber / steel",
}

# What the sidebar's dropdown shows (its width holds ~28 characters); the full label is the tooltip.
VULNERABILITY_SHORT = {"A": "A: rubble, adobe", "B": "B: stone, brick", "C": "C: massive stone, old RC",
                       "D": "D: confined masonry, RC", "E": "E: RC, high design", "F": "F: timber, steel"}

# Storey heights (m) by material.
STOREY_HEIGHT = {MASONRY: (2.8, 3.2), RC: (3.0, 3.5)}
# Debris: volume = solid fraction x bulking x collapsed (gross) volume.
SOLID_FRACTION = {MASONRY: (0.15, 0.30), RC: (0.10, 0.20)}
BULKING = (1.3, 1.7)
# Collapsed gross volume of a wall element = wall area x this depth (wall plus the edges of
# the floors and roof it carries). With the solid fractions above it reproduces the debris
# fan heights of the catalogue (0.5-2 m for a toppled facade).
WALL_ZONE_DEPTH = 1.0
# Debris spread beyond the footprint, as a fraction of the building height H.
DEBRIS_SPREAD = (0.1, 0.67)


@dataclass(frozen=True)
class Param:
    """One sampled parameter: uniform in [lo, hi] (integers inclusive)."""

    lo: float
    hi: float
    kind: str = "float"  # "float" | "int" | "angle" (degrees)
    unit: str = ""
    description: str = ""

    @property
    def default(self):
        mid = 0.5 * (self.lo + self.hi)
        return int(round(mid)) if self.kind == "int" else mid


@dataclass(frozen=True)
class Pattern:
    name: str
    label: str
    materials: tuple
    grades: tuple  # grades this pattern can serve as the building's worst element
    params: dict
    requires: tuple = ()  # shell features: "gable", "chimney", "parapet", "pitched", "storeys>=2", "storeys>=3"
    stage: int = 0  # application order: 0 openings/local, 1 partial collapse, 2 major collapse, 3 rigid
    debris: bool = False  # makes debris (uses solid_fraction/bulking)
    grade_params: dict = field(default_factory=dict)  # grade -> {param: Param} overrides
    description: str = ""


def _sf():
    return Param(0.15, 0.30, "float", "", "solid fraction of the collapsed volume (material dependent)")


def _bulk():
    return Param(*BULKING, "float", "", "bulking factor of debris")


def _p(lo, hi, kind="float", unit="", desc=""):
    return Param(lo, hi, kind, unit, desc)


PATTERNS: dict[str, Pattern] = {}


def _add(p: Pattern):
    PATTERNS[p.name] = p


# Priority order of the issue; names are the manifest's pattern names.
_add(Pattern("roof_holes", "Roof-covering holes", (MASONRY,), (3,), {
    "n_holes": _p(3, 15, "int", "", "number of holes"),
    "area_fraction": _p(0.05, 0.30, "float", "", "share of the roof area opened"),
    "hole_min": _p(0.5, 0.5, "float", "m", "smallest hole size"),
    "hole_max": _p(3.0, 3.0, "float", "m", "largest hole size"),
}, description="irregular holes through the roof covering, revealing the attic"))
_add(Pattern("wall_holes", "Wall holes", (MASONRY,), (3,), {
    "n_facades": _p(1, 4, "int", "", "facades with holes"),
    "holes_per_facade": _p(1, 4, "int"),
    "area_fraction": _p(0.02, 0.10, "float", "", "share of each facade's area"),
    "hole_min": _p(0.5, 0.5, "float", "m"),
    "hole_max": _p(2.0, 2.0, "float", "m"),
    "corner_breakouts": _p(0, 2, "int", "", "building corners whose masonry breaks out (both walls)"),
}, description="irregular holes in facades and corner break-outs, revealing floors and inner walls"))
_add(Pattern("partial_roof_collapse", "Partial roof collapse", (MASONRY,), (4,), {
    "area_fraction": _p(0.20, 0.60, "float", "", "share of the roof area that drops"),
    "drop": _p(1.0, 3.0, "float", "m", "mean drop of the collapsed roof planes"),
    "tilt": _p(10.0, 45.0, "angle", "deg", "inclination of the collapsed planes"),
}, requires=(), stage=1))
_add(Pattern("top_storey_collapse", "Top storey partly collapsed", (MASONRY,), (4,), {
    "footprint_fraction": _p(0.20, 0.70, "float", "", "share of the footprint losing its top storey"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("storeys>=2",), stage=1, debris=True))
_add(Pattern("pancake_collapse", "Pancake collapse", (RC,), (5,), {
    "final_height_fraction": _p(0.10, 0.25, "float", "", "final height / original height"),
    "max_slab_tilt": _p(10.0, 20.0, "angle", "deg", "slabs within this angle of horizontal"),
    "spread_fraction": _p(0.05, 0.30, "float", "", "debris spread beyond the footprint / H"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("storeys>=2",), stage=2, debris=True))
_add(Pattern("soft_storey_collapse", "Soft-storey collapse", (RC,), (5,), {
    "drop": _p(2.7, 4.0, "float", "m", "drop of the upper part (at most the storey height)"),
    "tilt": _p(0.0, 15.0, "angle", "deg", "tilt of the intact upper part"),
    "offset": _p(0.5, 2.0, "float", "m", "horizontal offset of the upper part"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("storeys>=2",), stage=2, debris=True,
    description="ground storey crushed, upper part intact: grade 5 although it can look intact"))
_add(Pattern("tilt", "Whole building tilts", (RC,), (4, 5), {
    "angle": _p(1.0, 3.0, "angle", "deg", "rotation about a base edge"),
}, stage=3, grade_params={5: {"angle": _p(5.0, 12.0, "angle", "deg", "rotation about a base edge")}}))
_add(Pattern("debris_heap", "Debris heap", (MASONRY,), (5,), {
    "heap_height_fraction": _p(0.10, 0.40, "float", "", "heap height / original height"),
    "stub_fraction": _p(0.0, 0.30, "float", "", "share of the perimeter keeping wall stubs"),
    "stub_height_fraction": _p(0.3, 1.0, "float", "", "stub height / storey height"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, stage=2, debris=True))
_add(Pattern("gable_fall", "Gable wall falls outward", (MASONRY,), (3, 4), {
    "gable_fraction": _p(0.20, 1.0, "float", "", "share of the gable triangle that falls"),
    "fan_height": _p(0.3, 0.8, "float", "m", "target height of the debris fan (its reach stays "
                     "within 0.5-1.0 x gable height)"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("gable",), stage=0, debris=True))
_add(Pattern("facade_topple", "Facade or corner topples", (MASONRY,), (4,), {
    "facade_fraction": _p(0.20, 1.0, "float", "", "share of the facade length"),
    "height_fraction": _p(0.25, 1.0, "float", "", "share of the storeys, from the top (at least one)"),
    "fan_height": _p(0.5, 2.0, "float", "m", "target height of the debris fan (its reach stays "
                     "within 0.5-1.0 x collapsed wall height)"),
    "solid_fraction": _sf(), "bulking": _bulk(),
    # the roof and floors bore on the wall that fell (EMS-98 grade 4: "partial structural
    # failure of roofs and floors"): without it the roof edge floated over the gap
    "roof_drop": _p(0.3, 2.5, "float", "m", "drop of the roof edge over the fallen wall (hinged strip; "
                    "at most down to the wall left standing)"),
    "sag_depth": _p(1.5, 4.0, "float", "m", "depth of the roof strip that hinges down, from the facade"),
}, stage=1, debris=True))
_add(Pattern("parapet_loss", "Parapet / cornice loss", (MASONRY, RC), (3,), {
    "length_fraction": _p(0.10, 0.50, "float", "", "share of the roof-edge length"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("parapet",), stage=0, debris=True))
_add(Pattern("infill_blowout", "Infill blow-out", (RC,), (3, 4), {
    "panels": _p(1, 3, "int", "", "infill panels that fail"),
    "debris_height": _p(0.3, 1.0, "float", "m", "target height of the debris in front"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, stage=0, debris=True, grade_params={4: {
    "panels": _p(0, 0, "int", "", "0 = use storey_share"),
    "storey_share": _p(0.30, 0.80, "float", "", "share of one storey's panels that fail"),
}}))
_add(Pattern("top_floor_pancake", "Top floor pancaked", (RC,), (4,), {
    "residual_height": _p(0.3, 0.8, "float", "m", "remaining height of the top storey"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("storeys>=2",), stage=2, debris=True))
_add(Pattern("corner_failure", "Corner / column failure", (RC,), (4,), {
    "drop": _p(1.0, 3.0, "float", "m", "drop of the failed corner"),
    "tilt": _p(10.0, 30.0, "angle", "deg", "inclination of the slabs over the failed bays"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, stage=1, debris=True))
_add(Pattern("mid_storey_collapse", "Mid-storey collapse", (RC,), (5,), {
    "residual_height": _p(0.3, 0.8, "float", "m", "remaining height of the crushed storey"),
    "tilt": _p(0.0, 5.0, "angle", "deg"),
    "offset": _p(0.0, 1.0, "float", "m"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, requires=("storeys>=3",), stage=2, debris=True))
_add(Pattern("wing_collapse", "Wing collapse", (MASONRY, RC), (5,), {
    "footprint_fraction": _p(0.20, 0.60, "float", "", "share of the footprint that becomes a heap"),
    "spread_fraction": _p(0.10, 0.40, "float", "", "debris spread beyond the footprint / H"),
    "solid_fraction": _sf(), "bulking": _bulk(),
}, stage=2, debris=True))
_add(Pattern("overturn", "Overturn", (RC,), (5,), {
    "angle": _p(30.0, 90.0, "angle", "deg", "rotation about a base edge"),
}, stage=3))
_add(Pattern("chimney_loss", "Chimney loss", (MASONRY,), (2, 3), {
    "removed_height": _p(0.5, 1.5, "float", "m", "height of the stack that falls"),
    "fragment_distance": _p(1.0, 3.0, "float", "m", "fragments land within this distance"),
    "n_fragments": _p(3, 8, "int"),
}, requires=("chimney",), stage=0, debris=True))

PATTERN_NAMES = tuple(PATTERNS)


def register(p: Pattern, primary: float = 0.0, secondary: float = 0.0) -> None:
    """Add a pattern to the catalogue (its bmesh function is registered beside it,
    `addon.geometry.patterns.register_pattern`). `primary`: its weight among the primary
    choices for each of its (grade, material) pairs; `secondary`: among its materials'
    secondary damage; 0: applied only when asked for by name. A weight changes which pattern
    other buildings of those grades draw (the choice is shared), never a pattern's own draws
    (`pattern_salt`)."""
    global PATTERN_NAMES
    if p.name in PATTERNS:
        raise ValueError(f"damage pattern {p.name!r} is already in the catalogue")
    if not p.name.isidentifier() or "+" in p.name:
        raise ValueError(f"damage pattern name {p.name!r}: a Python identifier (it names a manifest entry)")
    for weight, what in ((primary, "primary"), (secondary, "secondary")):
        if not weight >= 0.0:
            raise ValueError(f"damage pattern {p.name!r}: {what} weight {weight!r} must be >= 0")
    PATTERNS[p.name] = p
    PATTERN_NAMES = tuple(PATTERNS)
    if primary > 0.0:
        for grade in p.grades:
            for material in p.materials:
                PRIMARY.setdefault((grade, material), []).append((p.name, float(primary)))
    if secondary > 0.0:
        for material in p.materials:
            SECONDARY.setdefault(material, []).append((p.name, float(secondary)))


def unregister(name: str) -> None:
    """Take a registered pattern out of the catalogue and of every choice table."""
    global PATTERN_NAMES
    PATTERNS.pop(name, None)
    PATTERN_NAMES = tuple(PATTERNS)
    for table in (PRIMARY, SECONDARY):
        for key, entries in table.items():
            table[key] = [(e, w) for e, w in entries if name not in e.split("+")]


def param_specs(pattern: str, grade: int | None = None, material: str | None = None) -> dict[str, Param]:
    """The parameters of `pattern` with grade- and material-specific ranges applied."""
    try:
        p = PATTERNS[pattern]
    except KeyError:
        raise ValueError(f"unknown damage pattern {pattern!r}; known: {', '.join(PATTERN_NAMES)}") from None
    specs = dict(p.params)
    if grade is not None and grade in p.grade_params:
        specs.update(p.grade_params[grade])
    if material in SOLID_FRACTION and "solid_fraction" in specs:
        lo, hi = SOLID_FRACTION[material]
        specs["solid_fraction"] = Param(lo, hi, "float", "", specs["solid_fraction"].description)
    return specs


def default_params(pattern: str, grade: int | None = None, material: str | None = None) -> dict:
    return {k: s.default for k, s in param_specs(pattern, grade, material).items()}


def _uniform(rng, lo, hi):
    return float(rng.uniform(lo, hi))


def _integer(rng, lo, hi):
    if hasattr(rng, "integers"):  # numpy Generator
        return int(rng.integers(lo, hi + 1))
    return int(rng.randint(lo, hi))  # random.Random


def sample_params(pattern: str, rng, grade: int | None = None, material: str | None = None) -> dict:
    """Draw every parameter of `pattern` uniformly from its range.

    `rng` is a numpy Generator or a random.Random; the draw order is the parameter order,
    so the same seed gives the same parameters.
    """
    out = {}
    for name, s in param_specs(pattern, grade, material).items():
        if s.kind == "int":
            out[name] = _integer(rng, int(s.lo), int(s.hi))
        else:
            out[name] = s.lo if s.lo == s.hi else _uniform(rng, s.lo, s.hi)
    return out


# --- which patterns serve which grade -------------------------------------------------------

# (grade, material) -> [(pattern, weight)]; the worst element defines the grade.
PRIMARY = {
    (2, MASONRY): [("chimney_loss", 1.0)],
    (3, MASONRY): [("roof_holes", 3.0), ("wall_holes", 2.0), ("gable_fall", 2.0), ("chimney_loss", 0.7),
                   ("parapet_loss", 1.0)],
    (4, MASONRY): [("partial_roof_collapse", 3.0), ("facade_topple", 2.0), ("top_storey_collapse", 2.0),
                   ("gable_fall+partial_roof_collapse", 1.0)],
    (5, MASONRY): [("debris_heap", 3.0), ("wing_collapse", 1.5)],
    (3, RC): [("infill_blowout", 3.0), ("parapet_loss", 1.0)],
    (4, RC): [("top_floor_pancake", 2.0), ("corner_failure", 2.0), ("tilt", 1.0), ("infill_blowout", 1.5)],
    (5, RC): [("soft_storey_collapse", 3.0), ("pancake_collapse", 2.0), ("mid_storey_collapse", 1.0),
              ("wing_collapse", 1.0), ("tilt", 0.7), ("overturn", 0.2)],
}
# Lower-grade companions that may accompany a primary pattern (stage 0 only).
SECONDARY = {
    MASONRY: [("roof_holes", 1.0), ("wall_holes", 1.0), ("chimney_loss", 0.5), ("parapet_loss", 0.5)],
    RC: [("infill_blowout", 1.0), ("parapet_loss", 0.5)],
}
# Vulnerability class bias: multiply the weight of these patterns.
CLASS_BIAS = {
    "A": {"gable_fall": 1.6, "wall_holes": 1.5, "facade_topple": 1.6, "debris_heap": 1.8,
          "gable_fall+partial_roof_collapse": 1.5},
    "B": {"gable_fall": 1.4, "wall_holes": 1.3, "facade_topple": 1.4, "debris_heap": 1.5},
    "C": {"soft_storey_collapse": 1.8, "infill_blowout": 1.6, "pancake_collapse": 1.2},
    "D": {"corner_failure": 1.4, "tilt": 1.4, "top_floor_pancake": 1.2, "debris_heap": 0.7},
    "E": {"tilt": 1.8, "corner_failure": 1.5, "pancake_collapse": 0.6, "overturn": 1.5},
}


def requirements_met(pattern: str, features) -> bool:
    """`features`: set of shell features ("gable", "chimney", "parapet", "pitched",
    "storeys>=2", "storeys>=3")."""
    return all(r in features for r in PATTERNS[pattern].requires)


def candidates(grade: int, material: str, features, vulnerability_class: str | None = None):
    """[(entry, weight)] primary choices for a building; an entry is a pattern name or
    several joined by '+' (applied together)."""
    out = []
    bias = CLASS_BIAS.get(vulnerability_class or "", {})
    for entry, w in PRIMARY.get((grade, material), []):
        if all(requirements_met(p, features) for p in entry.split("+")):
            out.append((entry, w * bias.get(entry, 1.0)))
    return out


def _choice(rng, items):
    total = sum(w for _, w in items)
    x = _uniform(rng, 0.0, total)
    acc = 0.0
    for item, w in items:
        acc += w
        if x < acc:
            return item
    return items[-1][0]


def pattern_salt(name: str) -> int:
    """The salt of a pattern's own random stream: from its name (CRC-32, the same in every
    Python process), so that adding a pattern to the catalogue changes no other pattern's draws
    (an index into the catalogue would shift every later pattern's)."""
    return zlib.crc32(name.encode("utf-8"))


def choose_patterns(grade: int, material: str, features, rng, vulnerability_class: str | None = None,
                    secondary_probability: float = 0.4, streams=None) -> list[tuple[str, dict]]:
    """Pick and parameterise the patterns that give a building the EMS-98 `grade`.

    `rng` draws the choices; `streams(name)`, when given, is the random stream of a pattern's
    own draws (its parameters here, its geometry when applied), so that which other patterns
    were chosen, or exist, does not change them; without it `rng` draws everything.
    Returns [(pattern, params)] in application order (stage, then as chosen). Grade 0-1
    (and 2 without a chimney) return [] : geometrically no damage at UAV resolution.
    Raises ValueError when no pattern of the catalogue fits (e.g. grade 4 masonry on a
    building without a roof to collapse is never the case; kept for user meshes).
    """
    if grade not in GRADES:
        raise ValueError(f"grade must be an EMS-98 grade 0..5, got {grade!r}")
    if material not in MATERIALS:
        raise ValueError(f"material must be one of {MATERIALS}, got {material!r}")
    if grade <= 1:
        return []
    cands = candidates(grade, material, features, vulnerability_class)
    if not cands:
        if grade == 2:
            return []
        raise ValueError(f"no damage pattern for grade {grade} {material} with features {sorted(features)}")
    stream = streams or (lambda name: rng)
    entry = _choice(rng, cands)
    chosen = []
    for name in entry.split("+"):
        g = grade if grade in PATTERNS[name].grades else max(g for g in PATTERNS[name].grades if g <= grade)
        chosen.append((name, sample_params(name, stream(name), grade=g, material=material)))
    primary_stage = max(PATTERNS[n].stage for n, _ in chosen)
    # Secondary, lower-grade damage elsewhere on the building (not before rigid motions that
    # would carry ground debris along, nor before a total collapse that erases it).
    if grade >= 3 and primary_stage in (0, 1) and _uniform(rng, 0, 1) < secondary_probability:
        names = {n for n, _ in chosen}
        sec = [(n, w) for n, w in SECONDARY[material]
               if n not in names and requirements_met(n, features)]
        if sec:
            name = _choice(rng, sec)
            g = 3 if 3 in PATTERNS[name].grades else PATTERNS[name].grades[0]
            chosen.insert(0, (name, sample_params(name, stream(name), grade=g, material=material)))
    chosen.sort(key=lambda np_: PATTERNS[np_[0]].stage)
    return chosen


def grade_label(grade: int) -> str:
    return GRADES[grade][0]
