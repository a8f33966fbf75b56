"""The pulse behind each return of a real cloud: where the sensor was and which way it looked.

To damage a real cloud as its own sensor would have seen the damage, each return is
re-cast along its own pulse. An airborne or drone laser file rarely carries its trajectory,
but the LAS point records do: per flight line (`point_source_id`) the returns' horizontal
positions advance with `gps_time` at the aircraft's speed, and across the track they lie at
`H · tan(scan angle)` from it, H the flying height above them. A least-squares fit of both
gives the line's track, across-track offset and height (the two AHN3 Delft tiles: 48-69 m/s,
400-435 m above the returns, residuals of 4-8 m from the whole-degree scan angles, i.e.
under 1.2 degrees of direction). The pulse of a return is then the ray from the sensor's
position at its time to the return.

Where a line cannot be fitted (too few returns, too short, one scan angle) its returns keep
the scan angle across the line's heading, or across the mean heading of the file, and
without any usable time or angle they look straight down. Photogrammetric clouds have no
pulses: a dense matching surface is what the cameras above saw, so `kind="dim"` casts every
point from straight above, at the cloud's own spacing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# a flight line is fitted only from this many returns over this many seconds and degrees of scan angle
MIN_LINE_POINTS = 200
MIN_LINE_SECONDS = 0.2
MIN_ANGLE_SPREAD_DEG = 5.0
# a fit outside these is no aircraft or drone: the line falls back to its scan angles
SPEED_RANGE_M_S = (2.0, 150.0)
HEIGHT_RANGE_M = (20.0, 6000.0)

TRAJECTORY, SCAN_ANGLE, NADIR = 0, 1, 2
METHOD_NAMES = {TRAJECTORY: "trajectory", SCAN_ANGLE: "scan angle", NADIR: "nadir"}


@dataclass(frozen=True)
class FlightLine:
    source_id: int
    points: int
    speed_m_s: float
    height_m: float | None  # None: not fitted, directions from scan angles
    method: int

    def to_json(self) -> dict:
        return {"point_source_id": self.source_id, "points": self.points, "speed_m_s": round(self.speed_m_s, 3),
                "height_m": None if self.height_m is None else round(self.height_m, 2),
                "method": METHOD_NAMES[self.method]}


@dataclass
class Pulses:
    directions: np.ndarray  # (n, 3) unit vectors from the sensor towards each return
    method: np.ndarray  # (n,) uint8: TRAJECTORY, SCAN_ANGLE or NADIR
    lines: list  # FlightLine per point_source_id (lidar)


def nadir_pulses(n: int) -> Pulses:
    d = np.zeros((n, 3))
    d[:, 2] = -1.0
    return Pulses(d, np.full(n, NADIR, np.uint8), [])


def lidar_pulses(xyz: np.ndarray, gps_time, scan_angle_deg, source_id) -> Pulses:
    """Pulse directions of a laser cloud from its own records (module docstring)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    out = nadir_pulses(n)
    if gps_time is None or scan_angle_deg is None or n == 0:
        return out
    t = np.asarray(gps_time, dtype=np.float64)
    angle = np.radians(np.asarray(scan_angle_deg, dtype=np.float64))
    sid = np.zeros(n, np.int64) if source_id is None else np.asarray(source_id, dtype=np.int64)
    fits = {}
    for s in np.unique(sid).tolist():
        m = np.flatnonzero(sid == s)
        fits[s] = _fit_line(xyz[m], t[m], angle[m])
    headings = [f[0] for f in fits.values() if f is not None]
    mean_heading = _mean_heading(headings)
    for s, fit in fits.items():
        m = np.flatnonzero(sid == s)
        if fit is not None and fit[3] is not None:
            heading, speed, track, height = fit
            sensor = _sensor_positions(t[m], track, height)
            d = xyz[m] - sensor
            out.directions[m] = d / np.linalg.norm(d, axis=1, keepdims=True)
            out.method[m] = TRAJECTORY
            out.lines.append(FlightLine(int(s), len(m), speed, height, TRAJECTORY))
            continue
        heading = fit[0] if fit is not None else mean_heading
        speed = fit[1] if fit is not None else float("nan")
        if heading is None or not np.any(angle[m]):
            out.lines.append(FlightLine(int(s), len(m), speed, None, NADIR))
            continue
        out.directions[m] = scan_angle_directions(angle[m], heading)
        out.method[m] = SCAN_ANGLE
        out.lines.append(FlightLine(int(s), len(m), speed, None, SCAN_ANGLE))
    return out


def scan_angle_directions(angle_rad: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Unit pulse directions at these scan angles across a line flown along `heading` (unit
    2-vector): ASPRS angles are positive to the right of the aircraft."""
    right = np.array([heading[1], -heading[0]])
    d = np.empty((len(angle_rad), 3))
    d[:, 0] = np.sin(angle_rad) * right[0]
    d[:, 1] = np.sin(angle_rad) * right[1]
    d[:, 2] = -np.cos(angle_rad)
    return d


def _mean_heading(headings):
    if not headings:
        return None
    # a line and its return leg are the same axis: average doubled angles
    a = np.array([np.arctan2(h[1], h[0]) for h in headings])
    mean = 0.5 * np.arctan2(np.sin(2 * a).mean(), np.cos(2 * a).mean())
    return np.array([np.cos(mean), np.sin(mean)])


def _fit_line(xyz, t, angle):
    """(heading, speed, track, height) of one flight line; height None where only the heading
    could be fitted; None where not even that. `track` = (t0, position at t0, velocity,
    across-track offset vector, reference height)."""
    if len(t) < MIN_LINE_POINTS or np.ptp(t) < MIN_LINE_SECONDS:
        return None
    t0 = float(t.mean())
    A = np.c_[np.ones(len(t)), t - t0]
    (x0, vx), (y0, vy) = (np.linalg.lstsq(A, xyz[:, k], rcond=None)[0] for k in range(2))
    speed = float(np.hypot(vx, vy))
    if not SPEED_RANGE_M_S[0] <= speed <= SPEED_RANGE_M_S[1]:
        return None
    heading = np.array([vx, vy]) / speed
    right = np.array([heading[1], -heading[0]])
    if np.degrees(np.ptp(angle)) < MIN_ANGLE_SPREAD_DEG:
        return heading, speed, None, None
    rel = xyz[:, :2] - (np.array([x0, y0]) + np.outer(t - t0, [vx, vy]))
    offset = rel @ right
    (centre, height), *_ = np.linalg.lstsq(np.c_[np.ones(len(t)), np.tan(angle)], offset, rcond=None)
    if not HEIGHT_RANGE_M[0] <= height <= HEIGHT_RANGE_M[1]:
        return heading, speed, None, None
    track = (t0, np.array([x0, y0]) + centre * right, np.array([vx, vy]), float(xyz[:, 2].mean()))
    return heading, speed, track, float(height)


def _sensor_positions(t, track, height):
    t0, p0, v, z_ref = track
    xy = p0 + np.outer(t - t0, v)
    return np.c_[xy, np.full(len(t), z_ref + height)]
