"""One building's result for responders, which every output file writes.

docs/DESIGN.md: "Result — one row per building: building_id, predicted grade, class
probabilities, share of changed points, point counts per epoch, an assessable flag; written
as CSV and as GeoJSON when footprints are known."

A building that cannot be assessed (too few points in an epoch, no point in its footprint)
has no grade: the files leave it empty, never a guess. Every writer goes through
`quakescan.runtime.atomic`, so a file under its final name is always complete.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..grades import GRADE_SHORT_NAMES, grade_name
from .colours import colour_of

NOT_ASSESSABLE = "not assessable"


@dataclass
class BuildingResult:
    building_id: int
    n_pre: int
    n_post: int
    assessable: bool
    reason: str = ""  # why not assessable, e.g. "12 pre-event points < 50"
    grade: int | None = None  # None when not assessable: never a guess
    probabilities: dict[int, float] = field(default_factory=dict)  # class grade → p
    share_changed: float | None = None
    decided_by: str = ""  # "model" | "no change" (no changed points → no damage, per the paper) | ""
    # probability of the predicted grade (DamageModel.confidence); 1.0 when decided by rule,
    # None when not assessable
    confidence: float | None = None
    # what the building's data could resolve (quakescan.change.detectability): the lowest
    # grade among 3, 4, 5 (None: none of them, or unknown), the smallest roof opening (m²; None:
    # unknown, e.g. not assessable) and lowering (m; None: unknown)
    detectable_grade: int | None = None
    min_opening_m2: float | None = None
    min_lowering_m: float | None = None
    # whether the walls resolve heavy damage confined to them, and the smallest wall hole they
    # resolve (m²); None: unknown (no facade band, or no facade record)
    walls_resolved: bool | None = None
    min_wall_opening_m2: float | None = None

    @property
    def heavy_unresolved(self) -> bool:
        """Graded 0 on data that cannot resolve heavy damage: "no damage" excludes nothing
        below the lowest grade it resolves (hatched on the maps, counted in the summary)."""
        from ..change.detectability import heavy_unresolved

        ok = self.assessable and self.grade is not None
        return heavy_unresolved(self.grade if ok else None, self.detectable_grade, self.min_opening_m2)

    @property
    def label(self) -> str:
        if not self.assessable or self.grade is None:
            return NOT_ASSESSABLE
        return GRADE_SHORT_NAMES.get(int(self.grade), f"grade {self.grade}")

    @property
    def grade_name(self) -> str:
        """EMS-98 name of the grade ("substantial to heavy"); "not assessable" without one."""
        if not self.assessable or self.grade is None:
            return NOT_ASSESSABLE
        return grade_name(self.grade)

    @property
    def colour(self) -> str:
        return colour_of(self.grade if self.assessable else None)


def in_id_order(rows) -> list[BuildingResult]:
    """The rows by building ID: the order of every file's buildings."""
    return sorted(rows, key=lambda r: int(r.building_id))


__all__ = ["BuildingResult", "NOT_ASSESSABLE", "in_id_order"]
