"""Levels of detection of the changed/unchanged split, measured on a rescan of one source.

The split (`quakescan.change.split.split_changed`) only calls a point changed when its change in
height or in curvature exceeds a level of detection (LoD). What an undamaged surface shows
as "change" depends on how the clouds were made: on the paper's laser scanning the
curvature of a rescanned roof moves by at most 0.14 1/m (99.9th percentile), on simulated
photogrammetry by 0.5 1/m (depth noise and edge smoothing fit other quadrics at every
crease). LoDs chosen on one source therefore flag every undamaged building of the other.

`calibrate` measures them the way change-detection practice does (a level of detection
from repeated acquisitions of stable surfaces): the same undamaged buildings acquired twice
with the source at hand, every sampled building point mapped to its nearest point of the
second acquisition exactly as the pipeline does, and the LoD of each change set to its
`quantile` over those points, never below the floor (the defaults of SplitSettings,
measured on ULS: a coarser LoD than the physics needs is not asked for). In a real
deployment the second acquisition is any undamaged area flown twice with the same
camera or scanner; in the experiment it is the region-specific training set's pre-event
scene acquired twice.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import QuakeScanError
from ..formats.pointcloud import Epoch
from ..runtime.progress import ProgressCallback, no_progress
from .split import SplitSettings

DEFAULT_QUANTILE = 0.999
DEFAULT_SAMPLE = 200_000


class CalibrationError(QuakeScanError):
    """A rescan pair cannot give levels of detection."""


@dataclass
class LevelsOfDetection:
    lod_height_m: float
    lod_curvature: float
    quantile: float
    height_at_quantile_m: float  # |Δheight| at `quantile` over the sampled points
    curvature_at_quantile: float  # |Δcurvature| at `quantile` (1/m)
    points: int  # sampled building points with a finite curvature change
    radius_m: float

    def split(self, base: SplitSettings | None = None) -> SplitSettings:
        """`base` (default SplitSettings()) with these levels of detection."""
        d = (base or SplitSettings()).to_json()
        d.update(lod_height_m=self.lod_height_m, lod_curvature=self.lod_curvature)
        return SplitSettings(**d)

    def to_json(self) -> dict:
        return asdict(self)


def calibrate(pre: Epoch, rescan: Epoch, radius_m: float = 1.5, *, quantile: float = DEFAULT_QUANTILE,
              floor: SplitSettings | None = None, sample: int = DEFAULT_SAMPLE, seed: int = 0,
              workers: int = -1, progress: ProgressCallback | None = None) -> LevelsOfDetection:
    """Levels of detection from two acquisitions of the same undamaged buildings.

    Both epochs in one local frame (read the rescan with the first one's origin).
    `progress(done, 3)` after each step: the first cloud's features, the nearest points, the
    second cloud's features."""
    from .paper_descriptors import exact_nearest, features_at
    from .settings import PipelineSettings
    from .tiling import GridIndex, box_of

    if not 0.5 < quantile < 1.0:
        raise CalibrationError(f"quantile must lie in (0.5, 1), got {quantile!r}")
    floor = floor or SplitSettings()
    for e, name in ((pre, "first"), (rescan, "second")):
        if e.building_id is None or not np.any(e.building_id > 0):
            raise CalibrationError(f"{e.source}: the {name} acquisition has no building points "
                                   "(levels of detection are measured on buildings)")
    if not np.array_equal(pre.origin, rescan.origin):
        raise CalibrationError(f"{rescan.source}: epochs are in different local frames; read the second "
                               "acquisition with the first one's origin")
    settings = PipelineSettings(radius_m=radius_m, point_features=(floor.curvature_feature,))
    candidates = np.flatnonzero(pre.building_id > 0)
    rng = np.random.default_rng(seed)
    q = np.sort(rng.choice(candidates, size=min(sample, len(candidates)), replace=False)).astype(np.int64)
    pre_index = GridIndex(pre.xyz[:, :2], settings.tile_m / 4)
    post_index = GridIndex(rescan.xyz[:, :2], settings.tile_m / 4)
    curv = floor.curvature_feature
    step = progress or no_progress
    pre_f = features_at(pre, pre_index, q, settings, workers)[curv]
    step(1, 3)
    nn, _ = exact_nearest(pre.xyz[q], rescan, post_index, box_of(pre.xyz[q, :2], radius_m), workers)
    step(2, 3)
    uniq, inv = np.unique(nn, return_inverse=True)
    post_f = features_at(rescan, post_index, uniq, settings, workers)[curv][inv]
    step(3, 3)
    d_curv = np.abs(post_f - pre_f)
    d_curv = d_curv[np.isfinite(d_curv)]
    d_height = np.abs(rescan.xyz[nn, 2] - pre.xyz[q, 2])
    if len(d_curv) == 0:
        raise CalibrationError(f"{pre.source}: no sampled building point has a finite {curv} "
                               f"at r = {radius_m} m (too sparse?)")
    h = float(np.quantile(d_height, quantile))
    c = float(np.quantile(d_curv, quantile))
    return LevelsOfDetection(lod_height_m=max(floor.lod_height_m, h), lod_curvature=max(floor.lod_curvature, c),
                             quantile=quantile, height_at_quantile_m=h, curvature_at_quantile=c,
                             points=len(d_curv), radius_m=radius_m)
