"""Whether a pair's epochs are registered, and their rigid alignment where they are not.

The post-event epoch is aligned to the pre-event one by ICP on stable points (`align`) when
asked, or when the check finds an offset beyond the model's level of detection that the
alignment markedly reduces. One process checks whole epochs (`register_pair`); a streamed run
(`quakescan.distributed`) checks the same sampled points chunk by chunk (`register_samples`).
"""
from __future__ import annotations

import logging

import numpy as np

from . import align as alignment
from .align import AlignmentError, format_alignment, sample_mask, stable_mask
from .settings import PipelineSettings

log = logging.getLogger(__name__)

# Epochs whose stable ground disagrees by more than this share of the model's level of
# detection are aligned before describing: a georeferencing offset of a few decimetres
# reads as change on every building (AHN3 shifted by 0.4 m: 134 of 134 called damaged).
# Below it the level of detection absorbs the offset, and ICP between different sensors
# finds spurious offsets of 2-8 cm on perfectly registered simulated pairs (bench_transfer's
# held-out city): aligning those would move the data, not correct it.
AUTO_ALIGN_SHARE_OF_LOD = 1.0
# ... and only when the alignment fits the stable points markedly better. On flat ground a
# shift or turn within the ground's plane changes no point-to-plane residual, so ICP's
# estimate of it is whatever it drifts to: airborne (ALS-like) vs DIM sampling of a 300 m
# city gave a 0.12° turn that moved the far corners 0.62 m and cut the rmse by 2 µm (0.0313
# m both), and aligning by it read as damage on undamaged buildings. A real offset beyond
# the level of detection shows in the residuals (AHN3 moved by 0.4 m and up 0.15 m: rmse
# 0.15 -> 0.03 m); a turn the residuals cannot see is no evidence of one.
MIN_FIT_GAIN = 0.10  # the share of the rmse an automatic alignment must remove
CHECK_MAX_POINTS = 500_000  # stable points ICP sees for the check: a rigid transform needs few
ALIGN_MAX_POINTS = 2_000_000  # and when asked to align


def registration_tolerance_m(settings: PipelineSettings) -> float:
    """The largest offset between epochs left as it is: the model's level of detection."""
    lod = settings.surface.lod_floor_m if settings.surface is not None else settings.split.lod_height_m
    return AUTO_ALIGN_SHARE_OF_LOD * lod


def register_pair(pre, post, settings: PipelineSettings, align: bool | None, summary: dict, workers: int = -1) -> dict:
    """Check (and, when asked or needed, apply) the rigid alignment of post to pre; moves
    post.xyz in place; returns what was done for the summary."""
    if align is False:
        return {"mode": "off", "checked": False}
    max_points = check_max_points(align)
    samples = []
    for e in (pre, post):
        keep = stable_mask(e.classification, e.building_id) & sample_mask(range(len(e)), len(e), max_points)
        samples.append(e.xyz[keep])
    return register_samples(samples[0], samples[1], post, settings, align, summary, workers=workers)


def check_max_points(align: bool | None) -> int:
    """How many stable points of each epoch the registration check samples."""
    return CHECK_MAX_POINTS if align is None else ALIGN_MAX_POINTS


def register_samples(pre_sample, post_sample, post, settings: PipelineSettings, align: bool | None, summary: dict,
                     post_bounds=None, workers: int = -1) -> dict:
    """`register_pair` on the epochs' sampled stable points (`sample_mask`): a streamed run
    (`quakescan.distributed`) samples the same points chunk by chunk. Moves post.xyz when
    the alignment is applied and `post` is an Epoch; returns the record."""
    mode = "on" if align else "auto"
    tolerance = registration_tolerance_m(settings)
    pre_name, post_name = str(summary.get("pre", "the pre-event epoch")), str(summary.get("post", "the post-event epoch"))
    try:
        a = alignment.align_epochs(pre_sample, post_sample, np.ones(len(pre_sample), bool),
                                   np.ones(len(post_sample), bool), max_points=check_max_points(align),
                                   pre_name=pre_name, post_name=post_name, workers=workers)
    except AlignmentError as e:
        if mode == "on":
            raise AlignmentError(f"--align: cannot align {post_name} to {pre_name}: {e}") from None
        log.warning("cannot check that the epochs are registered (%s); classifying them as they are: an offset "
                    "between them would read as damage", e)
        return {"mode": mode, "checked": False, "reason": str(e)}
    offset = max_displacement_m(a, post.xyz if post_bounds is None else post_bounds)
    record = {"mode": mode, "checked": True, "offset_m": round(offset, 4), "tolerance_m": tolerance,
              "applied": False}
    needed = offset > tolerance and a.rmse_after_m < (1.0 - MIN_FIT_GAIN) * a.rmse_before_m
    if offset > tolerance and not needed:
        record["unobserved"] = (f"the fit moved {offset:.2f} m but its rmse only {a.rmse_before_m:.4f} -> "
                                f"{a.rmse_after_m:.4f} m: not applied")
        log.info("registration check: %s", record["unobserved"])
    if mode == "on" or needed:
        if post is not None and post_bounds is None:
            post.xyz = a.apply(post.xyz)
        summary["alignment"] = a.to_json()
        record["applied"] = True
        if mode == "auto":
            log.warning("the epochs disagree on stable ground by up to %.2f m (more than the %.2f m the model "
                        "tolerates): aligned the post-event epoch to the pre-event one (%s); --no-align keeps "
                        "them as they are", offset, tolerance, format_alignment(a))
        else:
            log.info("alignment: %s", format_alignment(a))
        if a.std_after_m * 1.96 > settings.split.lod_height_m:
            log.warning("the alignment's noise (std %.3f m) exceeds what the model's level of detection "
                        "(%.2f m) tolerates: expect undamaged buildings to look changed",
                        a.std_after_m, settings.split.lod_height_m)
    return record


def max_displacement_m(a, xyz: np.ndarray) -> float:
    """How far the alignment moves any corner of the cloud's bounding box (translation and
    rotation together: a small rotation moves the far edge of a large tile the most)."""
    from ..grid.cells import column_bounds

    lo, hi = column_bounds(np.asarray(xyz, dtype=np.float64))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(np.linalg.norm(a.apply(corners) - corners, axis=1).max())
