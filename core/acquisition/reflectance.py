"""Reflectance of the scene's faces and the scanner's intensity (the LAS `intensity` field).

Intensity follows the radar (lidar) equation for an extended, Lambertian target that fills
the beam: received power P ∝ ρ · cos(θ_inc) / R², ρ the target's reflectance at the laser's
wavelength, θ_inc the angle between the ray and the face's normal, R the range. The LAS
field is that power scaled to uint16:

    intensity = min(65535, round(65535 · ρ · cos θ_inc · (R_ref / R)²))

with R_ref = the survey's `intensity_reference_range_m`: a white (ρ = 1) face at normal
incidence at R_ref gives 65535, so only faces closer than R_ref can saturate. The presets
put R_ref well below their flight altitude (paper 20 m at 100 m above ground, als 100 m
at 500 m), where no surface of a scene comes.

Reflectance ρ: a building's `reflectance` in scene.json when it has one (0 < ρ <= 1; used
for all its faces), else by its `material`, and for faces that are not buildings by
surface. The defaults are typical values at 1550 nm (the VUX-1UAV's wavelength) from the
lidar radiometry literature, rounded: they give the surfaces plausible contrasts, not a
calibration.

A full-beam return's intensity is that of its strongest sub-ray's face along the central
ray, as if that face caught the whole footprint (the echo's energy share is not applied).
"""
from __future__ import annotations

import math

import numpy as np

from ..formats.scene import DEBRIS, GROUND, INTERIOR, OBJECT, ROOF, VEGETATION, WALL, Scene

INTENSITY_MAX = 65535

# Reflectance of non-building faces by surface code.
SURFACE_REFLECTANCE = {GROUND: 0.20,  # asphalt, soil, grass mixed
                       VEGETATION: 0.30,  # leaves at 1550 nm (water absorbs; 0.5 at 905 nm)
                       OBJECT: 0.15,  # car paint, street furniture
                       ROOF: 0.30, WALL: 0.30, DEBRIS: 0.30, INTERIOR: 0.30}
# Reflectance of building faces (roof, wall, debris, interior) by material.
MATERIAL_REFLECTANCE = {"masonry": 0.35,  # brick, plaster, clay tiles
                        "reinforced_concrete": 0.30}


def building_reflectance(building) -> float:
    """ρ of one building: its scene.json `reflectance`, else its material's."""
    rho = building.extra.get("reflectance")
    if rho is not None:
        return float(rho)
    return MATERIAL_REFLECTANCE.get(building.material, MATERIAL_REFLECTANCE["masonry"])


def face_reflectance(scene: Scene) -> np.ndarray:
    """(m,) float64 ρ of every face of the scene."""
    by_surface = np.full(int(max(SURFACE_REFLECTANCE)) + 1, SURFACE_REFLECTANCE[GROUND])
    for code, rho in SURFACE_REFLECTANCE.items():
        by_surface[code] = rho
    surface = np.minimum(scene.face_surface.astype(np.int64), len(by_surface) - 1)
    rho = by_surface[surface]
    if scene.buildings:
        lut = np.zeros(int(max(int(scene.face_building.max(initial=0)), max(b.id for b in scene.buildings))) + 1)
        for b in scene.buildings:
            lut[b.id] = building_reflectance(b)
        is_building = scene.face_building > 0
        rho[is_building] = lut[scene.face_building[is_building]]
    return rho


def check_reflectance(value, where: str) -> str | None:
    """None when `value` is a valid reflectance, else what is wrong with it (for the scene reader)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0 < value <= 1:
        return f"{where}: reflectance must be a number in (0, 1] (share of the laser light returned), got {value!r}"
    return None


def intensity(reflectance: np.ndarray, normals: np.ndarray, directions: np.ndarray, ranges: np.ndarray,
              reference_range_m: float) -> np.ndarray:
    """Numpy reference of the compiled `_scan_kernels._intensity` (same arithmetic, same order).

    reflectance (n,), normals (n, 3) unit face normals, directions (n, 3) unit rays,
    ranges (n,) m → (n,) uint16."""
    cos = np.abs(normals[:, 0] * directions[:, 0] + normals[:, 1] * directions[:, 1]
                 + normals[:, 2] * directions[:, 2])
    v = 65535.0 * reflectance * cos * (reference_range_m * reference_range_m) / (ranges * ranges)
    return np.where(v >= INTENSITY_MAX, INTENSITY_MAX, np.rint(np.minimum(v, INTENSITY_MAX))).astype(np.uint16)
