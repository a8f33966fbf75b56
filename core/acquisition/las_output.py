"""What the simulated sensors write the same way: the LAS offset of a scene (the epoch
contract: offset = scene origin) and the per-surface, per-building point counts of a
summary."""
from __future__ import annotations

import logging

import numpy as np

from ..formats.scene import SURFACE_NAMES, Scene
from .raycast import RayCaster

log = logging.getLogger(__name__)


def las_offset(scene: Scene, caster: RayCaster):
    """LAS offset = scene origin (contract). Points are local + shift, shift = local origin.

    When a scene stores large coordinates relative to a zero origin the offset moves to the
    whole metre nearest the local origin, so that int32 millimetres still reach."""
    lo = caster.local_origin
    if np.all(np.abs(caster.bounds_local) + np.abs(lo) < 2.0e6):
        return scene.origin.copy(), lo
    step = np.round(lo)
    log.warning("scene coordinates reach %s m from its origin; LAS offset moved by %s", np.abs(lo).max(),
                step.tolist())
    return scene.origin + step, lo - step


def label_counts(scene: Scene, caster: RayCaster, points_by_face: np.ndarray, source: str = "scene",
                 kind: str = "points") -> tuple[dict, dict]:
    """Points per surface name and per building ID from points per face; warns about
    buildings that got none (shared by the ULS and DIM simulators)."""
    by_surface = np.bincount(caster.face_surface, weights=points_by_face, minlength=len(SURFACE_NAMES))
    surfaces = {SURFACE_NAMES.get(k, str(k)): int(c) for k, c in enumerate(by_surface) if c}
    by_building = np.bincount(caster.face_building, weights=points_by_face)
    buildings = {int(k): int(by_building[k]) for k in np.flatnonzero(by_building) if k > 0}
    missing = [b.id for b in scene.buildings if b.id not in buildings]
    if missing:
        log.warning("%s: %d buildings got no %s: %s", source, len(missing), kind, missing[:10])
    return surfaces, buildings
