"""What decides a pair's descriptors: the pipeline's settings, checked, stored with a model
and made again from a model's descriptor columns; the one rule of a neighbourhood radius.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError
from . import descriptors as registry
from .features import FEATURES
from .split import STATISTICS, SplitSettings
from .surface import SURFACE_DESCRIPTORS, SurfaceSettings

# The paper's robust change features (planarity, surface variation, point density, number
# of neighbours, surface density, volume density, roughness, z rank, z range, normal).
PAPER_FEATURES = ("planarity", "surface_variation", "point_density", "num_neighbours", "surface_density",
                  "volume_density", "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z")
# Changes that are not point features but are described like them.
EXTRA_CHANGES = ("height", "distance")
DEFAULT_RADIUS_M = 1.5
# what a per-point level of detection of the curvature change needs of both neighbourhoods
LOD_FEATURES = ("eigenvalue1", "eigenvalue2", "eigenvalue3", "num_neighbours")


# The feature radius a model may use. Below 0.5 m a neighbourhood at UAV spacing (~0.1 m)
# holds too few points for stable eigenvalues; above 10 m it spans whole buildings and
# its cost grows with r². The paper uses 1.0-4.0 m.
RADIUS_RANGE_M = (0.5, 10.0)


def radius_problem(r) -> str | None:
    """What is wrong with a neighbourhood radius (settings, a model file), or None: the one rule."""
    if isinstance(r, bool) or not isinstance(r, (int, float, np.integer, np.floating)) or not (
            math.isfinite(r) and RADIUS_RANGE_M[0] <= r <= RADIUS_RANGE_M[1]):
        return f"must lie in [{RADIUS_RANGE_M[0]:g}, {RADIUS_RANGE_M[1]:g}] m, got {r!r}"
    return None


MAX_MIN_POINTS = 1_000_000
MAX_TILE_M = 10_000.0


class PipelineError(QuakeScanError):
    """A pair of epochs cannot be processed as asked."""


@dataclass
class PipelineSettings:
    """Everything that decides the descriptors; a model stores it and classification reuses it."""

    radius_m: float = DEFAULT_RADIUS_M
    point_features: tuple = PAPER_FEATURES
    split: SplitSettings = field(default_factory=SplitSettings)
    min_points_pre: int = 50   # fewer pre-event points: not assessable
    min_points_post: int = 10  # fewer post-event points: not covered by the post-event flight
    tile_m: float = 150.0
    # > 1: changes only at every k-th pre-event point of each building (neighbourhoods, nearest
    # neighbours and the point counts still use the full clouds): approximate, k times fewer queries
    core_point_step: int = 1
    # The paper's descriptors: statistics of the point features' changes over the changed
    # points of the LoD-gated split (share_changed, <feature>_<statistic>).
    paper_descriptors: bool = True
    # Descriptors of 2.5-D surfaces and M3C2 core points (quakescan.change.surface); None: not computed.
    surface: SurfaceSettings | None = None
    # which surface descriptors are columns (all by default; a model may use fewer)
    surface_descriptors: tuple = SURFACE_DESCRIPTORS
    # The split's levels of detection per point (M3C2 at the nearest core point for the
    # height change, the curvature's standard errors for its change), the split's constants
    # as floors; needs `surface` (its core points). False: the constants alone (the paper).
    per_point_lod: bool = False
    # A building whose sparser epoch is below this planimetric density (pts/m²) or whose
    # footprint the post-event epoch covers less than `min_coverage` is not assessable.
    min_density_pts_m2: float = 0.0
    min_coverage: float = 0.0
    # ... or whose footprint spans fewer raster cells (of the pair's cell size) than this: a shed
    # seen by a sparse epoch gives a handful of cells, where one chance patch is 10 % "change"
    min_cells: int = 0

    def __post_init__(self):
        problem = radius_problem(self.radius_m)
        if problem:
            raise PipelineError(f"radius {problem}")
        if not isinstance(self.split, SplitSettings):
            raise PipelineError(f"split settings must be SplitSettings, got {self.split!r}")
        for name in ("min_points_pre", "min_points_post"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= MAX_MIN_POINTS:
                raise PipelineError(f"{name} must be an integer in [1, {MAX_MIN_POINTS}], got {v!r}")
        if not (isinstance(self.tile_m, (int, float)) and math.isfinite(self.tile_m) and self.tile_m <= MAX_TILE_M):
            raise PipelineError(f"tile size must be a number of metres <= {MAX_TILE_M:g}, got {self.tile_m!r}")
        unknown = [f for f in self.point_features if f not in FEATURES]
        if unknown:
            raise PipelineError(f"unknown point features {unknown}; known: {', '.join(FEATURES)}")
        if not self.tile_m > 2 * self.radius_m:
            raise PipelineError(f"tile size {self.tile_m} m must exceed twice the radius {self.radius_m} m")
        k = self.core_point_step
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise PipelineError(f"core point step must be a positive integer (1 = every point), got {k!r}")
        if isinstance(self.surface, dict):
            self.surface = SurfaceSettings.from_json(self.surface)
        self.surface_descriptors = tuple(self.surface_descriptors)
        known = registry.names()
        unknown = [c for c in self.surface_descriptors if c not in known]
        if unknown:
            raise PipelineError(f"unknown surface descriptors {unknown}; known: {', '.join(known)}")
        if self.per_point_lod and self.surface is None:
            raise PipelineError("per-point levels of detection need the surface settings (their M3C2 core points)")
        if not self.paper_descriptors and self.surface is None:
            raise PipelineError("no descriptors asked for: enable the paper's descriptors or the surface ones")
        if not (math.isfinite(self.min_density_pts_m2) and self.min_density_pts_m2 >= 0):
            raise PipelineError(f"minimum density must be >= 0 pts/m², got {self.min_density_pts_m2!r}")
        if not 0 <= self.min_coverage <= 1:
            raise PipelineError(f"minimum coverage must be a share in [0, 1], got {self.min_coverage!r}")
        if isinstance(self.min_cells, bool) or not isinstance(self.min_cells, (int, np.integer)) or self.min_cells < 0:
            raise PipelineError(f"minimum raster cells must be an integer >= 0, got {self.min_cells!r}")

    @property
    def computed_features(self) -> tuple:
        """Point features to compute: the described ones, the split's curvature and, with
        per-point levels of detection, the eigenvalues and counts they need."""
        if not self.paper_descriptors:
            return ()
        names = list(self.point_features)
        extra = [self.split.curvature_feature] + (list(LOD_FEATURES) if self.per_point_lod else [])
        names += [f for f in extra if f not in names]
        return tuple(names)

    def descriptor_names(self) -> list[str]:
        """Columns of the descriptor table, in the order a model is trained on."""
        cols = []
        if self.paper_descriptors:
            cols.append("share_changed")
            for name in (*self.point_features, *EXTRA_CHANGES):
                cols += [f"{name}_{s}" for s in STATISTICS]
        if self.surface is not None:
            cols += list(self.surface_descriptors)
        return cols

    def to_json(self) -> dict:
        d = {"radius_m": self.radius_m, "point_features": list(self.point_features),
             "split": self.split.to_json(), "min_points_pre": self.min_points_pre,
             "min_points_post": self.min_points_post, "tile_m": self.tile_m,
             "core_point_step": int(self.core_point_step)}
        if self.surface is not None or not self.paper_descriptors or self.per_point_lod:
            # keys older QuakeScans never wrote: only when they differ from those versions
            d.update(paper_descriptors=self.paper_descriptors, per_point_lod=self.per_point_lod,
                     surface=None if self.surface is None else self.surface.to_json(),
                     surface_descriptors=list(self.surface_descriptors))
        if self.min_density_pts_m2 or self.min_coverage:
            d.update(min_density_pts_m2=self.min_density_pts_m2, min_coverage=self.min_coverage)
        if self.min_cells:
            d["min_cells"] = int(self.min_cells)
        return d

    @classmethod
    def from_json(cls, d: dict) -> PipelineSettings:
        try:
            return cls(radius_m=float(d["radius_m"]), point_features=tuple(d["point_features"]),
                       split=SplitSettings(**d["split"]), min_points_pre=int(d["min_points_pre"]),
                       min_points_post=int(d["min_points_post"]), tile_m=float(d.get("tile_m", 150.0)),
                       core_point_step=int(d.get("core_point_step", 1)),  # absent in older models
                       **_newer_keys(d))
        except (KeyError, TypeError, ValueError) as e:
            raise PipelineError(f"incomplete pipeline settings ({e!r}): {d}") from None
        except QuakeScanError as e:
            raise PipelineError(str(e)) from None


def _newer_keys(d: dict) -> dict:
    """Settings that older model files do not hold, with the values those versions used."""
    surface = d.get("surface")
    return {"paper_descriptors": bool(d.get("paper_descriptors", True)),
            "per_point_lod": bool(d.get("per_point_lod", False)),
            "surface": None if surface is None else SurfaceSettings.from_json(surface),
            "surface_descriptors": tuple(d.get("surface_descriptors", SURFACE_DESCRIPTORS)),
            "min_density_pts_m2": float(d.get("min_density_pts_m2", 0.0)),
            "min_coverage": float(d.get("min_coverage", 0.0)),
            "min_cells": int(d.get("min_cells", 0))}


DESCRIPTOR_SETS = ("paper", "surface", "both")


def training_settings(descriptors: str = "surface", *, radius_m: float = 1.5,
                      point_features: Sequence[str] | None = None, split: SplitSettings | None = None,
                      per_point_lod: bool = False) -> PipelineSettings:
    """Settings of a model to train: the paper's descriptors (point features and the split's
    changed share), the density-free surface descriptors of the shipped model, or both.
    `per_point_lod` gates the paper's split by each point's level of detection."""
    if descriptors not in DESCRIPTOR_SETS:
        raise PipelineError(f"descriptors must be one of {DESCRIPTOR_SETS}, got {descriptors!r}")
    surface = None
    extra = {}
    if descriptors in ("surface", "both") or per_point_lod:
        from .surface import NOISE_FREE_DESCRIPTORS

        surface = SurfaceSettings()
        extra["surface_descriptors"] = NOISE_FREE_DESCRIPTORS if descriptors in ("surface", "both") else ()
    return PipelineSettings(radius_m=radius_m, point_features=tuple(point_features or PAPER_FEATURES),
                            split=split or SplitSettings(), paper_descriptors=descriptors in ("paper", "both"),
                            surface=surface, per_point_lod=per_point_lod and descriptors != "surface", **extra)


def settings_for_descriptors(names: Sequence[str], radius_m: float, split: dict | None = None,
                             stored: dict | None = None, **kw) -> PipelineSettings:
    """Settings that produce the descriptor columns `names` (those a model was trained on);
    `stored`: the model's stored pipeline settings (surface settings, per-point LoD, ...).

    Refuses a column that no point feature or change produces: a model for other features."""
    feats, bad = [], []
    known = registry.names()
    surface_cols = [c for c in names if c in known]
    for col in names:
        if col == "share_changed" or col in known:
            continue
        base, _, stat = col.rpartition("_")
        if stat not in STATISTICS or not (base in FEATURES or base in EXTRA_CHANGES):
            bad.append(col)
        elif base in FEATURES and base not in feats:
            feats.append(base)
    if bad:
        raise PipelineError(f"the model asks for descriptors {bad} that this QuakeScan cannot compute "
                            f"(point features: {', '.join(FEATURES)}; statistics: {', '.join(STATISTICS)}; "
                            f"surface descriptors: {', '.join(known)})")
    newer = _newer_keys(stored or {})
    newer["paper_descriptors"] = "share_changed" in names
    newer["surface_descriptors"] = tuple(surface_cols)  # none: surface settings only for per-point LoDs
    if surface_cols and newer["surface"] is None:
        newer["surface"] = SurfaceSettings()
    if not surface_cols and not newer["per_point_lod"]:
        newer["surface"] = None
    for key in list(newer):
        if key in kw:
            newer.pop(key)
    try:
        split_settings = SplitSettings(**(split or {}))
    except TypeError as e:  # a key this QuakeScan does not know
        raise PipelineError(f"split settings {split!r}: {e}") from None
    except QuakeScanError as e:
        raise PipelineError(str(e)) from None
    return PipelineSettings(radius_m=radius_m, point_features=tuple(feats), split=split_settings, **newer, **kw)
