"""The pulses of a flight line: when each leaves the scanner and at which scan angle
(rotating polygon or oscillating mirror), the share of the sweep inside the FOV, the
pulses that can reach the scene's box, and their rays in the local frame."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._scan_reference import loops as choose_loops
from .survey import FlightLine, Survey


@dataclass(frozen=True)
class Batch:
    """Pulses j0 … j1 - 1 of one flight line, the scan's batch `number` (which seeds its range noise)."""

    line: FlightLine
    j0: int
    j1: int
    number: int


def pulse_count(survey: Survey, line: FlightLine) -> int:
    """Pulses the scanner fires along `line` (all of the sweep, inside the FOV or not)."""
    return int(math.floor(line.duration_s * survey.pulse_rate_hz)) + 1


def fov_runs(survey: Survey, line: FlightLine, j0: int, j1: int):
    """Runs of pulse indices lo[i]..hi[i] within [j0, j1) that may lie inside the FOV (with
    one pulse of margin either side).

    A rotating polygon spends most of its sweep outside the FOV (paper preset: 120° of
    330°); the FOV part of every scan line is a contiguous run of pulses found from the
    line's phase window, so the pulses outside are never generated."""
    if survey.deflector != "rotating_polygon" or survey.fov_fraction >= 1 or j1 <= j0:
        return np.array([j0], np.int64), np.array([j1 - 1], np.int64)
    prr, rate, g0 = survey.pulse_rate_hz, survey.scan_rate_hz, survey.gps_start_s
    f0, f1 = 0.5 - survey.fov_fraction / 2, 0.5 + survey.fov_fraction / 2
    t_a, t_b = line.t_start + j0 / prr, line.t_start + (j1 - 1) / prr
    scan_lines = np.arange(math.floor((t_a - g0) * rate), math.floor((t_b - g0) * rate) + 1)
    lo = np.ceil((g0 + (scan_lines + f0) / rate - line.t_start) * prr).astype(np.int64) - 1
    hi = np.floor((g0 + (scan_lines + f1) / rate - line.t_start) * prr).astype(np.int64) + 1
    return np.maximum(lo, j0), np.minimum(hi, j1 - 1)


class Pulses:
    """The pulses of line `line` with indices in [j0, j1) that leave the scanner inside the
    FOV and can reach the scene's box: times, scan angles, flags and their rank among all
    pulses inside the FOV (1-D, cheap); their rays on demand. `n_fov` counts all pulses
    inside the FOV, aimed at the scene or not. `loops`: the module whose loops compute them
    (`_scan_reference.loops`; default the compiled ones)."""

    def __init__(self, survey: Survey, line: FlightLine, j0: int, j1: int, local_origin: np.ndarray,
                 box: np.ndarray, loops=None):
        self.loops = choose_loops(True) if loops is None else loops
        self.line = line
        h = line.heading
        pitch = math.radians(survey.scan_pitch_deg)
        self.down = np.array([0.0, 0.0, -1.0]) * math.cos(pitch) + h * math.sin(pitch)
        self.right = np.array([h[1], -h[0], 0.0])
        self.plane_normal = np.cross(self.down, self.right)  # perpendicular to every ray of the line
        self.start_local = line.start - local_origin
        self.velocity = h * line.speed_m_s
        lo, hi = fov_runs(survey, line, j0, j1)
        half_fov = math.radians(survey.fov_deg) / 2 + 1e-12
        aim_lo, aim_hi = self._angle_window(box, line.t_start + j0 / survey.pulse_rate_hz,
                                            line.t_start + (j1 - 1) / survey.pulse_rate_hz) if j1 > j0 else (0, 0)
        self.j, self.t, self.theta, self.forward, self.edge, self.rank, self.n_fov = self.loops.fov_pulses(
            lo, hi, line.t_start, survey.pulse_rate_hz, survey.scan_rate_hz, survey.gps_start_s,
            survey.sweep_rad / 2, half_fov, survey.deflector == "oscillating_mirror", aim_lo, aim_hi)

    def _angle_window(self, box: np.ndarray, t_first: float, t_last: float) -> tuple[float, float]:
        """Scan angles that can reach the box from anywhere between two times (conservative).

        A box corner's angle in the scan plane is monotonic in the platform's position along
        the line, so the corners seen from the first and last positions bound the window.
        When the box is not entirely below the scanner every angle is kept."""
        corners = np.array([[x, y, z] for x in box[:, 0] for y in box[:, 1] for z in box[:, 2]])
        angles = []
        for t in (t_first, t_last):
            rel = corners - (self.start_local + (t - self.line.t_start) * self.velocity)
            depth = rel @ self.down
            if (depth <= 0).any():
                return -math.inf, math.inf
            angles.append(np.arctan2(rel @ self.right, depth))
        angles = np.concatenate(angles)
        return float(angles.min()), float(angles.max())

    def __len__(self):
        return len(self.j)

    def rays(self):
        """(origins, directions, origins32, directions32) of the pulses, local frame."""
        return self.loops.pulse_rays(self.t, self.theta, self.line.t_start, self.start_local, self.velocity,
                                     self.down, self.right)
