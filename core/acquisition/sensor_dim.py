"""Dense image matching of a UAV photo flight as a registered sensor: `dim`, a
`quakescan.acquisition.dim_settings.PhotoSurvey` flown by `quakescan.acquisition.dim.simulate_dim`.

Ranges of its random settings (`quakescan.acquisition.acquire.random_acquisition`; the flight-line
direction first, `quakescan.acquisition.sensors.LINE_DIRECTION_DEG`), the paper's photo survey otherwise
(45 MP camera, 24 mm nadir, four 35 mm obliques at 45°): altitude 80–150 m above ground,
i.e. a nadir ground sampling distance of 1.47–2.75 cm; matching noise 0.5–1.5 px
(well-textured to poorly textured façades); one point per 6–12 px (Metashape between
"medium" and "lowest"); a quarter of the flights are nadir-only (rapid mapping often has
no oblique camera). The flown area grows by altitude · tan(oblique tilt) when there are
obliques (so they see the scene's edge facades, as in the paper preset), not at all
without them.
"""
from __future__ import annotations

import math

from . import dim as _dim
from .dim_settings import PhotoSurvey, load_photo_survey, preset_dim
from .sensors import LINE_DIRECTION_DEG, Sensor, register, uniform

DIM_ALTITUDE_M = (80.0, 150.0)
DIM_NOISE_PX = (0.5, 1.5)
DIM_POINT_STEP_PX = (6.0, 12.0)
DIM_NADIR_ONLY_SHARE = 0.25


def random_photo_survey(rng) -> PhotoSurvey:
    """DIM settings drawn from the ranges in the module docstring."""
    direction = uniform(rng, LINE_DIRECTION_DEG, 1)
    base = preset_dim("paper")
    altitude = uniform(rng, DIM_ALTITUDE_M, 1)
    noise_px = uniform(rng, DIM_NOISE_PX, 2)
    step = uniform(rng, DIM_POINT_STEP_PX, 1)
    obliques = 0 if rng.random() < DIM_NADIR_ONLY_SHARE else 4
    margin = round(altitude * math.tan(math.radians(base.oblique_tilt_deg)), 1) if obliques else 0.0
    return base.replace(name="dim-random", line_direction_deg=direction, altitude_agl_m=altitude,
                        noise_px=noise_px, point_step_px=step, oblique_cameras=obliques, margin_m=margin)


def label(s: PhotoSurvey) -> str:
    """E.g. 'dim 120m gsd 2.2cm noise 1.00px step 8px oblique'."""
    cams = "oblique" if s.oblique_cameras else "nadir"
    return (f"dim {s.altitude_agl_m:.0f}m gsd {100 * s.gsd_m:.1f}cm noise {s.noise_px:.2f}px "
            f"step {s.point_step_px:g}px {cams}")


def _simulate(scene, survey: PhotoSurvey, out_path, *, seed, workers, progress, source):
    # Looked up on the module at call time, so that what replaces `quakescan.acquisition.dim.simulate_dim`
    # (a test that must see no simulation) replaces it here too.
    return _dim.simulate_dim(scene, survey, out_path, seed=seed, progress=progress, workers=workers, source=source)


register(Sensor("dim", PhotoSurvey, _simulate, preset_dim, label, default_preset="paper",
                settings_name="photo survey", load=load_photo_survey, random=random_photo_survey))
