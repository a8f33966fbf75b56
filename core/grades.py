"""The one table of damage-grade names: EMS-98's names and the paper's short ones.

EMS-98 (Grünthal 1998) names grades 1-5; grade 0 is "no damage". Zahs et al. call the
three damaged target classes heavy, extreme and destruction (grades 3, 4, 5): those short
names are what `label` holds in buildings.csv and what tables use where space is short;
maps, popups and the CLI's counts give the EMS-98 name. The add-on cannot import `quakescan`
and keeps its own copy in addon/ems98.py; tests/test_grades.py checks both are identical.
"""
from __future__ import annotations

# EMS-98 grade -> its EMS-98 name
GRADE_NAMES = {0: "no damage", 1: "negligible to slight", 2: "moderate", 3: "substantial to heavy",
               4: "very heavy", 5: "destruction"}
# EMS-98 grade -> the paper's short name (buildings.csv `label`, table headers)
GRADE_SHORT_NAMES = {0: "no damage", 1: "negligible", 2: "moderate", 3: "heavy", 4: "extreme", 5: "destruction"}


def grade_name(grade: int) -> str:
    """EMS-98 name of a grade ("substantial to heavy"); "grade N" for a grade outside 0-5."""
    return GRADE_NAMES.get(int(grade), f"grade {int(grade)}")


def short_name(grade: int) -> str:
    """The paper's short name of a grade ("heavy"); "grade N" for a grade outside 0-5."""
    return GRADE_SHORT_NAMES.get(int(grade), f"grade {int(grade)}")


def long_label(grade: int) -> str:
    """"3 substantial to heavy (heavy)": number, EMS-98 name and, where it differs, the short name."""
    g = int(grade)
    name, short = grade_name(g), short_name(g)
    return f"{g} {name}" if short == name else f"{g} {name} ({short})"


__all__ = ["GRADE_NAMES", "GRADE_SHORT_NAMES", "grade_name", "long_label", "short_name"]


def parse_grade_counts(text: str, allowed=range(0, 6)) -> dict[int, int]:
    """{grade: count} of a "GRADE:COUNT,..." text such as "0:35,3:19" (the generator's
    --grade-mix, inject's --grade-mix); ValueError naming what is wrong. Standard library
    only: Blender's Python reads it too."""
    mix = {}
    try:
        for part in text.split(","):
            g, n = part.split(":")
            mix[int(g)] = int(n)
    except ValueError:
        raise ValueError(f"expected GRADE:COUNT,... e.g. 0:35,3:19, got {text!r}") from None
    allowed = list(allowed)
    if not mix or any(g not in allowed for g in mix) or any(n < 0 for n in mix.values()) or sum(mix.values()) < 1:
        raise ValueError(f"grades must be {', '.join(map(str, allowed))} with counts >= 0 summing to >= 1, "
                         f"got {text!r}")
    return mix
