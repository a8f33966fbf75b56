"""What damage a building's data could resolve at all, from the sampling of both epochs.

A building reported "no damage" says something only where its points could have shown the
damage. Sparse points miss small openings by chance alone, whatever the descriptors and the
model do with them, so every building gets, from closed-form sampling statistics of its own
pre- and post-event roof densities (`planimetric_density`, pts/m²):

- the **smallest opening it resolves**, `min_opening_m2`. A laser or photogrammetric epoch
  samples a surface as a Poisson process of its planimetric density d: the returns on a
  patch of area A are Poisson with mean A·d, so the patch gets none with chance exp(-A·d)
  and fewer than k with the Poisson CDF P(N < k; A·d) = Q(k, A·d) (the regularised upper
  incomplete gamma function). The smallest A with at least k returns at confidence 1 - a
  solves P(N >= k; A·d) = P(k, A·d) >= 1 - a, i.e. A = P⁻¹(k, 1 - a) / d
  (`scipy.special.gammaincinv`; for k = 1, A = ln(1/a) / d). An opening needs both epochs:
  the post-event one must put `RETURNS_THROUGH_OPENING` returns on what is seen through it
  (the storey below), the pre-event one `RETURNS_ON_ROOF_BEFORE` on the roof that was there.
  Each epoch is given half of `ALPHA` (the union bound): both succeed with a chance of at
  least (1 - ALPHA/2)² >= 1 - ALPHA, and the opening resolvable is the larger of the two areas.
- the **smallest lowering it resolves**, `min_lowering_m`: the median level of detection of
  the building's comparable M3C2 core points, never below the pipeline's floor
  (`SurfaceSettings.lod_floor_m`); unknown (None) where no core point was comparable.
- the **lowest damage grade it resolves**, `detectable_grade`: the lowest of EMS-98 grades
  3, 4, 5 whose smallest signature in docs/DAMAGE_CATALOGUE.md (`SIGNATURES`: a share of the
  footprint opened or lowered, by at least a drop) spans at least `min_opening_m2` of the
  building's footprint and drops by at least `min_lowering_m`; None when none does.

- whether its **walls resolve heavy damage**, `walls_resolved`: the catalogue's smallest
  heavy damage confined to walls (holes and break-outs over `WALL_HEAVY_SHARE` of a facade)
  spans at least `min_wall_opening_m2`, the same closed form with each epoch's returns per m²
  of facade (`quakescan.change.facade_sampling`), on its facades together and on each open
  facing apart (`facings_resolve`: the damage may be on the one facade a flight never saw).
  An airborne laser's few wall returns resolve no wall holes; a drone's oblique flight does.

These are bounds of the sampling, not of the descriptors: a building may resolve heavy damage
and still be misread by the model, but one that does not resolve it cannot be read as
"no damage seen, heavy damage excluded". `detectable_grade` rests on the roof signatures
(what every sensor sees); `walls_resolved` says apart whether wall-only heavy damage could
have shown.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

# The chance that a resolvable opening is missed: 5 %, the confidence of the levels of
# detection elsewhere in the pipeline (M3C2's 95 % LoD), shared by the two epochs.
ALPHA = 0.05
# An opening shows as returns from below the roof, in patches of at least three cells or core
# points (`SurfaceSettings.min_patch_cells`, `min_patch_cores`): a single return below the old
# roof is a stray (a bird, multipath), and what is seen through an opening is areal.
RETURNS_THROUGH_OPENING = 3
# The roof must have been seen there before the event: one pre-event return on it says where
# it was (the descriptors compare a post-event point with every pre-event point around it).
RETURNS_ON_ROOF_BEFORE = 1


@dataclass(frozen=True)
class Signature:
    """The smallest change of a damage grade in docs/DAMAGE_CATALOGUE.md."""

    grade: int
    share: float  # of the building's footprint (its roof seen from above)
    drop_m: float  # how far the surface seen afterwards lies below the old roof, at least
    pattern: str


# Heavy: roof-covering holes over 5-30 % of the roof, through to the attic. The smallest share
# is taken, not the 10 % the independent benchmark's openings start at: a grade is "resolvable"
# only where its mildest catalogue form is, so "no damage" is never read as excluding heavy damage
# the data could not have shown. What is seen through a hole lies at least 1 m below the roof
# around it (`quakescan.change.surface.SEE_THROUGH_M`).
HEAVY = Signature(3, 0.05, 1.0, "roof-covering holes, 5-30 % of the roof")
# Extreme: partial roof collapse, 20-60 % of the roof area drops 1-3 m.
EXTREME = Signature(4, 0.20, 1.0, "partial roof collapse, 20-60 % of the roof drops 1-3 m")
# Destruction: the whole or a wing (20-60 % of the footprint) becomes a heap 10-40 % of the
# building's height: at least 60 % of it lowered, 1.8 m for the lowest building, one 3 m storey.
DESTRUCTION = Signature(5, 0.20, 0.6 * 3.0, "wing collapse, 20-60 % of the footprint becomes a heap")
SIGNATURES = (HEAVY, EXTREME, DESTRUCTION)
# Heavy damage confined to walls: 1-4 holes or corner break-outs per facade, 0.5-2 m, over
# 2-10 % of the facade area (docs/DAMAGE_CATALOGUE.md, masonry); the smallest share is taken.
WALL_HEAVY_SHARE = 0.02
# The share of each grade's catalogue forms confined to walls, which only a sensor that samples
# the walls can show (`quakescan.learning.unseen_damage`): wall holes and corner break-outs
# (masonry, grade 3) and infill blow-outs (RC, grade 3, and grade 4 over 30 % of a storey).
# Everything else a grade does changes the roof or puts debris beside the building, which is
# seen from above. Shares of the add-on's pattern weights for each grade (addon/ems98.py
# PRIMARY, the generator's and the injector's draws), masonry and RC counted alike since a
# real building's material is not known: grade 3 (2 / 8.7 + 3 / 4) / 2, grade 4 (0 + 1.5 / 6.5) / 2.
WALLS_ONLY_PATTERNS = ("wall_holes", "infill_blowout")
WALLS_ONLY_SHARE = {3: (2.0 / 8.7 + 3.0 / 4.0) / 2, 4: (0.0 + 1.5 / 6.5) / 2, 5: 0.0}


def chance_fewer_than(k: int, area_m2: float, density_pts_m2: float) -> float:
    """Chance that a patch of `area_m2` gets fewer than `k` returns at planimetric density
    `density_pts_m2`: the Poisson CDF P(N <= k - 1; A·d) = Q(k, A·d), exp(-A·d) for k = 1."""
    from scipy.special import gammaincc

    _check_count(k)
    mean = _nonnegative(area_m2, "area (m²)") * _nonnegative(density_pts_m2, "density (pts/m²)")
    if k == 0:
        return 0.0
    return float(gammaincc(k, mean))


def min_area_m2(density_pts_m2: float, k: int = 1, alpha: float = ALPHA) -> float:
    """The smallest area that gets at least `k` returns at density `density_pts_m2` with chance
    1 - `alpha`: P⁻¹(k, 1 - alpha) / d (ln(1/alpha) / d for k = 1); infinite without points."""
    from scipy.special import gammaincinv

    _check_count(k)
    d = _nonnegative(density_pts_m2, "density (pts/m²)")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha!r}")
    if k == 0:
        return 0.0
    if d == 0.0:
        return math.inf
    return float(gammaincinv(k, 1.0 - alpha)) / d


def min_opening_m2(density_pre: float, density_post: float, alpha: float = ALPHA,
                   k_pre: int = RETURNS_ON_ROOF_BEFORE, k_post: int = RETURNS_THROUGH_OPENING) -> float:
    """The smallest roof opening both epochs resolve together with chance at least 1 - `alpha`:
    the pre-event epoch `k_pre` returns on the roof, the post-event one `k_post` through the
    opening, each at 1 - alpha/2 (union bound)."""
    return max(min_area_m2(density_pre, k_pre, alpha / 2.0), min_area_m2(density_post, k_post, alpha / 2.0))


def min_lowering_m(lod_median_m: float | None, lod_floor_m: float) -> float | None:
    """The smallest lowering a building resolves: its core points' median level of detection,
    never below the floor under which no change counts; None when it has no comparable one."""
    if lod_median_m is None or not math.isfinite(lod_median_m):
        return None
    return max(float(lod_median_m), float(lod_floor_m))


def resolves(signature: Signature, footprint_m2: float, opening_m2: float, lowering_m: float | None) -> bool:
    """Whether a building of `footprint_m2` with these resolutions could show `signature`; an
    unknown lowering resolution (None) leaves the area alone to decide."""
    if not (math.isfinite(opening_m2) and footprint_m2 > 0):
        return False
    big_enough = footprint_m2 * signature.share >= opening_m2
    return big_enough and (lowering_m is None or lowering_m <= signature.drop_m)


def detectable_grade(footprint_m2: float, opening_m2: float, lowering_m: float | None = None) -> int | None:
    """The lowest of EMS-98 grades 3, 4, 5 whose smallest signature (`SIGNATURES`) the building
    resolves, None when it resolves none."""
    for s in SIGNATURES:
        if resolves(s, footprint_m2, opening_m2, lowering_m):
            return s.grade
    return None


def walls_resolved(facade_m2: float, wall_opening_m2: float) -> bool:
    """Whether facades of `facade_m2` in all resolve the smallest heavy wall damage
    (`WALL_HEAVY_SHARE` of them) at the smallest wall opening `wall_opening_m2` resolvable."""
    return bool(math.isfinite(wall_opening_m2) and facade_m2 > 0 and facade_m2 * WALL_HEAVY_SHARE >= wall_opening_m2)


def facings_resolve(facings) -> bool | None:
    """Whether every open facing of a building (`facade_sampling.FacadeSampling.facings`:
    (area m², pre-event, post-event returns per m²)) resolves heavy damage confined to it:
    the catalogue's wall damage is 1-4 holes on one facade or more, and a facade the flight
    never sampled hides it however densely the others were. None: no facing recorded."""
    try:
        sides = [(float(a), float(p), float(q)) for a, p, q in facings]
    except (TypeError, ValueError):
        return None
    if not sides or not all(math.isfinite(v) and v >= 0 for side in sides for v in side):
        return None
    return all(walls_resolved(a, min_opening_m2(p, q)) for a, p, q in sides)


@dataclass(frozen=True)
class Detectability:
    """What one building's data could resolve."""

    min_opening_m2: float
    min_lowering_m: float | None
    detectable_grade: int | None  # 3, 4, 5, or None: no grade of damage is resolvable
    # the smallest hole in a wall both epochs resolve (m²; inf: an epoch has no wall returns)
    # and whether the walls resolve heavy damage; None: unknown (no facade record, no facade)
    min_wall_opening_m2: float | None = None
    walls_resolved: bool | None = None


def of_building(quality: dict) -> Detectability | None:
    """The detectability of a building from its quality record (`BuildingRow.quality`: its
    own pre-event density over its cells, the post-event density over them, its footprint
    area `area_m2` and lowering resolution `lowering_lod_m`); None when the record lacks the
    densities or the area (a model without surface descriptors, a row of an older checkpoint)."""
    try:
        d_pre, d_post, area = (float(quality[k]) for k in ("density_pre", "density_post", "area_m2"))
    except (KeyError, TypeError, ValueError):
        return None
    if not all(math.isfinite(v) and v >= 0 for v in (d_pre, d_post, area)):
        return None
    opening = min_opening_m2(d_pre, d_post)
    lod = quality.get("lowering_lod_m")
    lowering = None if lod is None else float(lod)
    wall_opening, walls = None, None
    try:
        w_pre, w_post, facade = (float(quality[k]) for k in ("wall_density_pre", "wall_density_post", "facade_m2"))
    except (KeyError, TypeError, ValueError):
        facade = 0.0
    if facade > 0 and all(math.isfinite(v) and v >= 0 for v in (w_pre, w_post, facade)):
        wall_opening = min_opening_m2(w_pre, w_post)
        walls = walls_resolved(facade, wall_opening)
        sides = quality.get("wall_facings_resolved")  # a table's record of `facings_resolve`
        sides = facings_resolve(quality.get("wall_facings", ())) if sides is None else bool(sides)
        if walls and sides is False:
            walls = False
    return Detectability(opening, lowering, detectable_grade(area, opening, lowering), wall_opening, walls)


def heavy_unresolved(grade: int | None, grade_resolved: int | None, opening_m2: float | None) -> bool:
    """A building graded 0 whose data cannot resolve heavy damage (grade 3): its "no damage"
    excludes nothing below the lowest grade it resolves. False where detectability is unknown
    (`opening_m2` None)."""
    if grade is None or int(grade) != 0 or opening_m2 is None:
        return False
    return grade_resolved is None or int(grade_resolved) > HEAVY.grade


def _check_count(k) -> None:
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise ValueError(f"the number of returns must be a whole number >= 0, got {k!r}")


def _nonnegative(v, what: str) -> float:
    v = float(v)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{what} must be a finite number >= 0, got {v!r}")
    return v


__all__ = ["ALPHA", "DESTRUCTION", "Detectability", "EXTREME", "HEAVY", "RETURNS_ON_ROOF_BEFORE",
           "RETURNS_THROUGH_OPENING", "SIGNATURES", "Signature", "WALLS_ONLY_PATTERNS", "WALLS_ONLY_SHARE",
           "WALL_HEAVY_SHARE", "chance_fewer_than",
           "detectable_grade", "heavy_unresolved", "min_area_m2", "min_lowering_m", "min_opening_m2", "of_building",
           "resolves", "walls_resolved", "facings_resolve"]
