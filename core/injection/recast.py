"""A real cloud's returns re-cast against the damaged proxy model.

Each return is cast along its own pulse (`quakescan.injection.pulses`) against the proxy
scene before and after the damage. Where both meet the same surface at the same range the
damage did not touch that pulse, and the real return is kept as it is, every byte. Where
they differ:

- the damaged model puts a surface in front of the real return (debris on the street or on
  a neighbour's roof, a tilted wall, a toppled facade): the pulse now returns from it;
- the real return came from the damaged building itself (inside its footprint, no farther
  in front of its proxy than the roof's own relief: not a tree over it) and that surface is
  gone or moved: the pulse goes on to whatever the damaged model holds behind it (the storey
  below a roof opening, a lowered slab, the rubble, the ground), and returns nothing if it
  meets nothing;
- anything else (a tree over the roof, a car beside it) is kept: the damage is behind it.

A new return lies on the damaged model at the pulse's range plus the sensor's range noise
(`range_noise_m`, a seeded normal draw), so the real density, scan pattern, shadows and
noise carry over to the new surfaces. Its other fields are the real return's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..acquisition.raycast import RayCaster
from ..formats.scene import GROUND, Scene

# two casts of the same surface agree to float64 rounding; this is far above it and far below any damage
SAME_RANGE_M = 0.01
# a damaged surface this far in front of a real return hides it
IN_FRONT_M = 0.2
# a return within the roof's relief plus this of the proxy's roof is the roof's (proxies are flat)
ROOF_TOLERANCE_M = 1.0
# pulses start this far above the highest surface of the model
START_ABOVE_M = 50.0
KEPT, MOVED, REMOVED = 0, 1, 2


@dataclass
class RecastResult:
    xyz: np.ndarray  # (n, 3) world coordinates: the real ones where kept
    fate: np.ndarray  # (n,) uint8 KEPT, MOVED or REMOVED
    surface: np.ndarray  # (n,) uint8 face surface code of a moved return's new surface (255 elsewhere)
    building: np.ndarray  # (n,) int64 building ID of a moved return's new surface (0: terrain, or kept)


def recast(xyz: np.ndarray, directions: np.ndarray, building_of_point: np.ndarray, pre: Scene, post: Scene,
           damaged: dict, range_noise_m: float, seed: int, reach_m: float = 60.0) -> RecastResult:
    """Re-cast the returns near damaged buildings (module docstring).

    `xyz` world float64 (n, 3); `directions` unit pulse directions (n, 3); `building_of_point`
    footprint ID per point (0: none); `pre`/`post`: the proxy scene before and after the damage
    (same origin); `damaged`: {building ID: the roof's relief in m (how far above its proxy roof
    its own returns reach)} of the buildings whose damage is cast; only returns within
    `reach_m` (horizontally) of their post-event faces are cast."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    out = RecastResult(xyz.copy(), np.zeros(n, np.uint8), np.full(n, 255, np.uint8), np.zeros(n, np.int64))
    if n == 0 or not damaged:
        return out
    cand = _near_damage(xyz, pre, post, list(damaged), reach_m)
    if len(cand) == 0:
        return out
    before, after = RayCaster(pre), RayCaster(post)
    origin = post.origin + after.local_origin
    p = xyz[cand] - origin
    d = np.asarray(directions, dtype=np.float64)[cand]
    top = max(before.bounds_local[1, 2], after.bounds_local[1, 2]) + START_ABOVE_M
    # from START_ABOVE_M over the model's top down to each return, along its pulse (every d_z < 0)
    reach = (top - p[:, 2]) / np.maximum(-d[:, 2], 1e-3)
    o = p - reach[:, None] * d
    o_pre = o + (after.local_origin - before.local_origin)
    far = float(reach.max()) + 1e3
    f_pre, t_pre = before.cast(o_pre, d, far)
    f_post, t_post = after.cast(o, d, far)
    hit_pre, hit_post = f_pre >= 0, f_post >= 0
    same = (hit_pre == hit_post) & (~hit_post | (np.abs(np.where(hit_post, t_post, 0) - np.where(hit_pre, t_pre, 0))
                                                 <= SAME_RANGE_M))
    changed = ~same
    in_front = changed & hit_post & (t_post < reach - IN_FRONT_M)
    owner = building_of_point[cand]
    relief = np.array([damaged.get(int(b), np.nan) for b in owner]) if len(owner) else np.zeros(0)
    own = (np.isfinite(relief) & hit_pre
           & (np.where(hit_pre, t_pre, np.inf) - reach <= np.nan_to_num(relief) + ROOF_TOLERANCE_M))
    goes_on = changed & ~in_front & own
    move = in_front | (goes_on & hit_post)
    remove = goes_on & ~hit_post
    rng = np.random.default_rng([int(seed), 4402])
    noise = rng.normal(0.0, float(range_noise_m), int(move.sum())) if range_noise_m > 0 else 0.0
    at = o[move] + (t_post[move] + noise)[:, None] * d[move] + origin
    idx = cand[move]
    out.xyz[idx] = at
    out.fate[idx] = MOVED
    out.fate[cand[remove]] = REMOVED
    out.surface[idx] = after.face_surface[f_post[move]]
    out.building[idx] = after.face_building[f_post[move]]
    return out


def _near_damage(xyz, pre: Scene, post: Scene, ids: list, reach_m: float) -> np.ndarray:
    """Indices of the points within reach_m (x/y) of the damaged buildings' faces before or after."""
    boxes = []
    for scene in (pre, post):
        faces = np.isin(scene.face_building, ids)
        if faces.any():
            v = scene.vertices[np.unique(scene.faces[faces])][:, :2] + scene.origin[:2]
            boxes.append((v.min(axis=0) - reach_m, v.max(axis=0) + reach_m))
    if not boxes:
        return np.zeros(0, np.int64)
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    inside = np.all((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi), axis=1)
    return np.flatnonzero(inside)


def moved_class(surface: np.ndarray, real_class: np.ndarray) -> np.ndarray:
    """ASPRS class of moved returns: ground where they now meet the terrain, else unclassified (1),
    what a delivery holds for rubble before anyone has classified it."""
    return np.where(surface == GROUND, 2, 1).astype(real_class.dtype)
