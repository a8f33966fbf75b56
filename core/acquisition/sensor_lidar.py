"""Laser scanning as registered sensors: `uls` (UAV laser scanning) and `als` (airborne
laser scanning from an aircraft), both a `quakescan.acquisition.survey.Survey` flown by
`quakescan.acquisition.scan.scan`, with the scan's cost estimate and its flight-line checkpoint as their
hooks, and the flight trajectory a scan's survey flies (`write_trajectory`).

Ranges of their random settings (`quakescan.acquisition.acquire.random_acquisition`; rates and
densities log-uniformly, since their effects are multiplicative, everything else uniformly;
the flight-line direction first, `quakescan.acquisition.sensors.LINE_DIRECTION_DEG`):

- `uls` (the paper's preset otherwise: VUX-1UAV-like rotating polygon, 120° FOV, 8 m/s):
  altitude 50–150 m above ground (the span of published post-earthquake UAV-LiDAR
  flights; below 50 m obstacles, above 150 m the legal ceiling in most countries); pulse
  rate 100–600 kHz (UAV scanners' range, the paper's 300 kHz inside it); range noise
  0.01–0.03 m (UAV scanners' specified precision 5–10 mm plus trajectory noise); strip
  misalignment 0–0.05 m per axis (0 = perfectly adjusted strips, 5 cm = an unadjusted
  UAV trajectory); strip overlap 30–70 % (flight plans from economical to the paper's 60 %
  and beyond).
- `als` (the `als` preset otherwise, see `quakescan.acquisition.survey.als_for_density`): nominal density
  2–30 pts/m² (national archives: older blocks 1–4, AHN2/3 6–15, others up to 30; the
  sparse end matters: a building the model never saw that sparse is 'not assessable'); range noise
  0.02–0.04 m (aircraft scanners' ranging precision plus GNSS/INS noise at 500 m);
  strip misalignment 0.02–0.08 m (residuals of archive strip adjustment are a few
  centimetres; older blocks reach decimetres).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..runtime.atomic import open_replacing
from . import scan as _scan
from .raycast import ground_level
from .sensors import LINE_DIRECTION_DEG, Sensor, log_uniform, register, uniform
from .survey import Survey, als_for_density, load_survey, plan_flight, preset

ULS_ALTITUDE_M = (50.0, 150.0)
ULS_PULSE_RATE_HZ = (100_000.0, 600_000.0)
ULS_RANGE_NOISE_M = (0.01, 0.03)
ULS_MISALIGNMENT_M = (0.0, 0.05)
ULS_OVERLAP_PCT = (30.0, 70.0)
ALS_DENSITY_PTS_M2 = (2.0, 30.0)
ALS_RANGE_NOISE_M = (0.02, 0.04)
ALS_MISALIGNMENT_M = (0.02, 0.08)


def random_uls(rng) -> Survey:
    """ULS settings drawn from the ranges in the module docstring."""
    direction = uniform(rng, LINE_DIRECTION_DEG, 1)
    return preset("paper").replace(
        name="uls-random", line_direction_deg=direction,
        altitude_agl_m=uniform(rng, ULS_ALTITUDE_M, 1),
        pulse_rate_hz=round(log_uniform(rng, ULS_PULSE_RATE_HZ, 0), -3),
        range_noise_sigma_m=uniform(rng, ULS_RANGE_NOISE_M, 4),
        strip_misalignment_m=uniform(rng, ULS_MISALIGNMENT_M, 4),
        strip_overlap_pct=uniform(rng, ULS_OVERLAP_PCT, 1))


def random_als(rng) -> Survey:
    """ALS settings drawn from the ranges in the module docstring."""
    direction = uniform(rng, LINE_DIRECTION_DEG, 1)
    density = log_uniform(rng, ALS_DENSITY_PTS_M2, 2)
    return als_for_density(density).replace(
        name="als-random", line_direction_deg=direction,
        range_noise_sigma_m=uniform(rng, ALS_RANGE_NOISE_M, 4),
        strip_misalignment_m=uniform(rng, ALS_MISALIGNMENT_M, 4))


def label_uls(s: Survey) -> str:
    """E.g. 'uls 80m 300kHz noise 0.020 mis 0.030'."""
    return f"uls {s.altitude_agl_m:.0f}m {s.pulse_rate_hz / 1e3:.0f}kHz {_errors(s)}"


def label_als(s: Survey) -> str:
    """E.g. 'als 10.0pts/m2 noise 0.030 mis 0.050'."""
    return f"als {s.nominal_density_pts_m2:.1f}pts/m2 {_errors(s)}"


def _errors(s: Survey) -> str:
    return f"noise {s.range_noise_sigma_m:.3f} mis {s.strip_misalignment_m:.3f}"


def _simulate(scene, survey: Survey, out_path, *, seed, workers, progress, source, checkpoint=None, fingerprint=""):
    # Looked up on the module at call time, so that what replaces `quakescan.acquisition.scan.scan` (a test
    # that must see no scan) replaces it here too.
    return _scan.scan(scene, survey, out_path, seed=seed, workers=workers, progress=progress, source=source,
                      checkpoint=checkpoint, fingerprint=fingerprint)


def _estimate(scene, survey: Survey, out_path):
    return _scan.estimate_scan(scene, survey, laz=Path(out_path).suffix.lower() == ".laz")


def line_checkpoint(out_path) -> Path:
    """OUT.lines beside the cloud OUT: the scan's finished flight lines (`quakescan.acquisition.scan_checkpoint`)."""
    out = Path(out_path)
    return out.with_name(out.name + ".lines")


def write_trajectory(scene, survey: Survey, path: str | os.PathLike) -> None:
    """The trajectory of the survey's flight plan over `scene` as CSV (world coordinates:
    gps_time_s, x_m, y_m, z_m, heading_deg, line), written whole or not at all."""
    plan = plan_flight(survey, scene.bounds(), ground_level(scene))
    traj = plan.trajectory()
    traj[:, 1:4] += scene.origin
    with open_replacing(Path(path), "wb") as f:
        np.savetxt(f, traj, delimiter=",", fmt=["%.6f", "%.3f", "%.3f", "%.3f", "%.3f", "%d"],
                   header="gps_time_s,x_m,y_m,z_m,heading_deg,line", comments="")


register(Sensor("uls", Survey, _simulate, preset, label_uls, default_preset="paper", settings_name="survey",
                load=load_survey, random=random_uls, estimate=_estimate, checkpoint=line_checkpoint))
register(Sensor("als", Survey, _simulate, preset, label_als, default_preset="als", settings_name="survey",
                load=load_survey, random=random_als, estimate=_estimate, checkpoint=line_checkpoint))
