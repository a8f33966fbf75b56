"""The registry of building change descriptors: every column a model can read about a
building's change, in families that are computed together.

A `Descriptor` names one column, its unit, what it means in an engineer's words (the evidence
wording of a grade) and whether it *transfers*: whether its meaning is independent of the
sensor's noise, so that a model trained on one sensor's clouds may read it on another's (the
shipped model reads only those; `quakescan.learning.default_model`). A `Family` is the
descriptors one computation yields, with the version that the training tables' caches key on.

The built-in families are computed by `quakescan.change.surface.describe_surfaces`, which
shares one raster of cell tops, one interior view and one M3C2 pass among them:

- `raster`: the 2.5-D upper surfaces (`s_*`, but `s_interior_seen`);
- `interior`: the interior seen through an opening (`s_interior_seen`);
- `core`: surface change on core points (`m_*`, `quakescan.change.m3c2`);
- `openings`: openings per return (`o_*`, `quakescan.change.openings`).

A new descriptor is one module and one registration line: a function of a `BuildingView`
(the building's own pre-event points, its ground, its roof density, the points of both epochs
around it) returning {name: value}, and `register(Family(...))` naming its descriptors. It is
computed for every building of a run that asks for one of its names (a model trained with it,
`PipelineSettings.surface_descriptors`), in this process and in Dask workers alike, where the
module must be imported too (a `--preload` of the worker or an import in the package that
registers it). Its version joins the cache keys (`code_versions`), so a changed computation
never reuses an old table.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError

# Bumped whenever a built-in descriptor's computation changes (raster, interior, core): cached
# training tables made with another version are not reused (quakescan.learning.trainset), and a
# model records the version it was trained on.
DESCRIPTOR_VERSION = 16
# The openings per return have a version of their own: 2: courtyards stay outside the inner area,
# the radius floor 0.5 -> 0.25 m; 3: a fallen return must be surrounded by the surface it fell
# through; 4: and not lie on a wall; 5: a wall is a surface steeper than 63 deg up to 2 m above,
# within a point spacing.
OPENINGS_VERSION = 5

UNITS = ("share", "ratio", "m")


class DescriptorError(QuakeScanError):
    """A descriptor family that cannot be registered, or that computed something else than it named."""


@dataclass(frozen=True)
class Descriptor:
    """One column: `meaning` reads after its value ("38 % of the footprint lowered by more than 1 m")."""

    name: str
    unit: str
    meaning: str
    transfers: bool = True

    def __post_init__(self):
        if not self.name.isidentifier() or self.name != self.name.lower():
            raise DescriptorError(f"descriptor name {self.name!r}: use a lower-case identifier")
        if self.unit not in UNITS:
            raise DescriptorError(f"descriptor {self.name}: unit {self.unit!r} is not one of {', '.join(UNITS)}")

    def wording(self, value: float) -> str:
        """The value in an engineer's words: shares in per cent, ratios as they are, lengths in metres."""
        if self.unit == "share":
            return f"{100.0 * value:.0f} % {self.meaning}"
        if self.unit == "m":
            return f"{value:.2f} m {self.meaning}"
        return f"{value:.2f} {self.meaning}"


@dataclass(frozen=True)
class BuildingView:
    """What a registered family sees of one building (coordinates in the pair's local frame, metres).

    own: (n, 3) the building's pre-event points; ground: its ground height; density: the
    planimetric density of `own` (pts/m²); cell_m: the run's raster cell (set by the sparser
    epoch); settings: the run's `SurfaceSettings`. `pre_near(reach)` and `post_near(reach)` are
    the points of each epoch (every class: debris, neighbours, ground) within `reach` metres of
    the building's x/y box; `post_over()` the post-event points over the building's cells."""

    own: np.ndarray
    ground: float
    density: float
    cell_m: float
    settings: object
    pre_near: Callable[[float], np.ndarray] = field(repr=False)
    post_near: Callable[[float], np.ndarray] = field(repr=False)
    post_over: Callable[[], np.ndarray] = field(repr=False)


@dataclass(frozen=True)
class Family:
    """Descriptors computed together; `compute(view) -> {name: value}` for a registered family,
    None for the built-in ones (computed in `describe_surfaces`'s shared passes)."""

    name: str
    descriptors: tuple[Descriptor, ...]
    version: int | str
    compute: Callable[[BuildingView], Mapping[str, float]] | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.descriptors)


def _d(name, unit, meaning, transfers=True):
    return Descriptor(name, unit, meaning, transfers)


_RASTER = Family("raster", (
    _d("s_lowered_1m", "share", "of the footprint lowered by more than 1 m"),
    _d("s_lowered_storey", "share", "of the footprint lowered by more than a storey"),
    _d("s_lowered_half", "share", "of the footprint lowered by more than half its height"),
    _d("s_raised", "share", "of the footprint raised (tilted or displaced parts, debris)"),
    _d("s_volume_loss", "share", "of the building's volume lost"),
    _d("s_volume_gain", "share", "of the building's volume gained (debris, displaced parts)"),
    _d("s_height_ratio_mean", "ratio", "of its height left on average over the footprint"),
    _d("s_height_ratio_p10", "ratio", "of its height left at the lowest tenth of the footprint"),
    _d("s_post_gap", "share", "of the footprint with no post-event point (not covered or occluded)"),
    _d("s_debris_ring", "share", "of the ring around the building raised (debris)"),
    _d("s_debris_volume", "share", "of the building's volume in debris around it"),
    _d("s_see_through", "share", "of the footprint seen through the roof, the floor below in view"),
), DESCRIPTOR_VERSION)
_INTERIOR = Family("interior", (
    _d("s_interior_seen", "share", "of the footprint where the post-event survey saw inside the building"),
), DESCRIPTOR_VERSION)
_OPENINGS = Family("openings", (
    _d("o_fallen", "share", "of the roof's post-event returns fallen through it"),
    _d("o_fallen_null", "share", "of the roof's pre-event returns below every post-event one (the pair's null)"),
    _d("o_fallen_excess", "share", "of the roof's returns fallen beyond what the pair's sampling explains"),
    _d("o_fallen_ground", "share", "of the fallen returns down at the ground (a collapse, not an opening)"),
    _d("o_fallen_largest", "share", "of the roof's returns in the largest fallen patch"),
    _d("o_fallen_scatter", "share", "of the fallen returns outside the largest patch (scattered openings)"),
), OPENINGS_VERSION)
_CORE = Family("core", (
    _d("m_changed", "share", "of the building's surface changed"),
    _d("m_lost", "share", "of the building's surface gone"),
    _d("m_roof_changed", "share", "of the roof changed"),
    _d("m_wall_changed", "share", "of the walls changed"),
    _d("m_holes", "share", "of the surface gone with what lay behind it in view (openings)"),
    _d("m_wall_holes", "share", "of the walls gone with the rooms behind them in view"),
    _d("m_upper_changed", "share", "of the surface above the ground storey changed"),
    _d("m_lower_changed", "share", "of the ground storey's surface changed"),
    _d("m_inward", "share", "of the surface moved inwards (a sagging roof, a wall pushed in)"),
    _d("m_outward", "share", "of the surface moved outwards (a bulging or buried wall)"),
    _d("m_coherent", "share", "of the surface changed in coherent patches"),
    _d("m_largest_patch", "share", "of the surface in the largest changed patch"),
    _d("m_distance_p10", "m", "moved at the 10th percentile of the changed surface", transfers=False),
    _d("m_distance_median", "m", "moved at the median of the changed surface", transfers=False),
    _d("m_distance_p90", "m", "moved at the 90th percentile of the changed surface", transfers=False),
    _d("m_lod_median", "m", "the pair's typical level of detection", transfers=False),
), DESCRIPTOR_VERSION)
BUILT_IN = (_RASTER, _INTERIOR, _CORE, _OPENINGS)

_FAMILIES: dict[str, Family] = {f.name: f for f in BUILT_IN}


def register(family: Family) -> Family:
    """Add a family computed per building; its names must be new and it must compute them."""
    if not callable(family.compute):
        raise DescriptorError(f"descriptor family {family.name!r}: give compute(view) -> {{name: value}}")
    if family.name in _FAMILIES:
        raise DescriptorError(f"descriptor family {family.name!r} is registered already")
    if not family.descriptors:
        raise DescriptorError(f"descriptor family {family.name!r} names no descriptor")
    taken = set(names())
    clash = [n for n in family.names if n in taken or n == "share_changed"]
    if clash or len(set(family.names)) != len(family.names):
        raise DescriptorError(f"descriptor family {family.name!r}: names {clash or list(family.names)} are taken")
    _FAMILIES[family.name] = family
    return family


def unregister(name: str) -> None:
    """Remove a registered family (a plugin's or a test's); the built-in ones stay."""
    if name in (f.name for f in BUILT_IN):
        raise DescriptorError(f"descriptor family {name!r} is built in")
    _FAMILIES.pop(name, None)


def families() -> tuple[Family, ...]:
    return tuple(_FAMILIES.values())


def computed_per_building() -> tuple[Family, ...]:
    """The registered families `describe_surfaces` calls with a `BuildingView`, in registration order."""
    return tuple(f for f in _FAMILIES.values() if f.compute is not None)


def names() -> tuple[str, ...]:
    """Every descriptor name, in the families' order (the built-in ones first)."""
    return tuple(n for f in _FAMILIES.values() for n in f.names)


def names_of(family: str) -> tuple[str, ...]:
    return _FAMILIES[family].names


def get(name: str) -> Descriptor:
    for f in _FAMILIES.values():
        for d in f.descriptors:
            if d.name == name:
                return d
    raise KeyError(name)


def family_of(name: str) -> Family:
    for f in _FAMILIES.values():
        if name in f.names:
            return f
    raise KeyError(name)


def transferring(names_: tuple[str, ...] | None = None) -> tuple[str, ...]:
    """The names (of `names_`, default every one) whose meaning does not depend on the sensor's noise."""
    pool = names() if names_ is None else names_
    return tuple(n for n in pool if get(n).transfers)


def code_versions(wanted=None) -> dict:
    """The versions a descriptor table depends on, for the caches' keys: the built-in families'
    two, and every registered family's among `wanted` (default: all)."""
    out = {"descriptors": DESCRIPTOR_VERSION, "openings": OPENINGS_VERSION}
    for f in computed_per_building():
        if wanted is None or set(f.names) & set(wanted):
            out[f.name] = f.version
    return out


def checked(family: Family, values) -> dict:
    """`values` as {name: float} when they are exactly the family's names with finite values."""
    if not isinstance(values, Mapping) or set(values) != set(family.names):
        got = sorted(values) if isinstance(values, Mapping) else type(values).__name__
        raise DescriptorError(f"descriptor family {family.name!r} returned {got}, not {list(family.names)}")
    out = {}
    for n in family.names:
        try:
            v = float(values[n])
        except (TypeError, ValueError):
            raise DescriptorError(f"descriptor family {family.name!r}: {n} = {values[n]!r} is not a number") from None
        if not np.isfinite(v):
            raise DescriptorError(f"descriptor family {family.name!r}: {n} = {v} is not finite")
        out[n] = v
    return out
