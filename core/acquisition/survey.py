"""Survey = flight plan + scanner model for a virtual UAV laser scanning (ULS) flight.

A survey is a JSON file (`quakescan survey-template` writes a documented one). Every field
name ends in its unit. The preset `paper` reproduces the acquisition parameters of Zahs et
al. (Table: 89 lines/s, 300 kHz, 60 % strip overlap, 120° FOV, 100 m AGL, 8 m/s).

Geometry conventions (all in the scene's local frame, metres, z up):
- Flight lines are parallel, `line_direction_deg` counter-clockwise from +x, flown
  back and forth (serpentine) at `altitude_agl_m` above the scene's ground level.
- The scanner deflects the beam in the plane perpendicular to the heading (optionally
  pitched forward by `scan_pitch_deg`); the scan angle is 0 at nadir, positive to the
  right of the heading.
- `rotating_polygon`: the angle sweeps linearly from -FOV/2 to +FOV/2 `scan_rate_hz`
  times per second, always in the same direction (saw-tooth). `oscillating_mirror`:
  the sweep alternates direction every line (triangle wave). Every pulse at
  `pulse_rate_hz` is emitted inside the FOV (effective pulse rate).
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import SurveyError
from ..runtime import settings_file

FORMAT = "quakescan-survey"
VERSION = 1
DEFLECTORS = ("rotating_polygon", "oscillating_mirror")
BEAM_MODES = ("single", "adaptive", "full")
PATTERNS = ("parallel", "crosshatch")

# name → (meaning, unit); the survey JSON template carries this table as "_doc".
FIELD_DOC = {
    "altitude_agl_m": ("flight altitude above the scene's ground level", "m"),
    "speed_m_s": ("platform ground speed", "m/s"),
    "strip_overlap_pct": ("overlap of neighbouring strips on flat ground at ground level", "%"),
    "line_direction_deg": ("direction of the flight lines, counter-clockwise from the scene's +x axis", "deg"),
    "run_in_m": ("length flown beyond the scene's extent at both ends of every line", "m"),
    "pattern": ("'parallel' lines, or 'crosshatch' (a second set perpendicular to the first)", "-"),
    "gps_start_s": ("GPS time of the first pulse (adjusted standard GPS time)", "s"),
    "deflector": ("'rotating_polygon' (saw-tooth sweep) or 'oscillating_mirror' (triangle sweep)", "-"),
    "scan_rate_hz": ("scan lines per second", "lines/s"),
    "pulse_rate_hz": ("pulse repetition rate (effective, all pulses inside the FOV)", "Hz"),
    "fov_deg": ("full field of view across track; pulses outside it are not emitted", "deg"),
    "sweep_deg": ("rotating_polygon: angle the mirror sweeps per scan line (pulse_rate_hz is spread "
                  "over it; only the part inside fov_deg is recorded); ignored by oscillating_mirror, "
                  "which sweeps exactly the FOV", "deg"),
    "scan_pitch_deg": ("forward tilt of the scan plane (0 = vertical, perpendicular to the heading)", "deg"),
    "range_noise_sigma_m": ("standard deviation of the Gaussian range noise (seeded)", "m"),
    "strip_misalignment_m": (("registration error between flight lines: every point of a line is moved by one "
                             "3-D offset drawn per line (Gaussian, this standard deviation per axis, seeded "
                             "by the scan seed and the line number); 0 = strips perfectly registered"), "m"),
    "max_range_m": ("maximum range; farther surfaces give no return", "m"),
    "intensity_reference_range_m": ("range at which a white face (reflectance 1) at normal incidence has "
                                    "intensity 65535; intensity falls with range², so only closer faces "
                                    "saturate", "m"),
    "beam_divergence_mrad": ("full beam divergence at 1/e² intensity", "mrad"),
    "beam": ("'single' (one ray per pulse), 'full' (sub-rays over the footprint for every pulse) or "
             "'adaptive' (sub-rays only for pulses next to a depth discontinuity)", "-"),
    "beam_rings": ("rings of sub-rays over the footprint: 1 + 6 + 12 + … rays (2 rings = 19 rays)", "-"),
    "echo_separation_m": ("minimum range difference between two returns of one pulse", "m"),
    "min_echo_energy": ("share of the pulse energy a return needs to be detected", "fraction"),
    "max_returns": ("maximum number of returns recorded per pulse", "-"),
    "adaptive_edge_m": ("adaptive mode: distance of a neighbouring pulse's hit from the plane of this "
                        "pulse's hit above which the pulse lies at a discontinuity", "m"),
    "acquisition_date": ("date written to the LAS header (fixed so that reruns are byte-identical)", "YYYY-MM-DD"),
}


# Bounds of the fields beyond which no real survey goes: crewed aircraft fly ALS at up to
# ~5 km and 150 m/s, UAVs at down to ~1 m/s; today's fastest scanners emit a few MHz at up
# to a few hundred lines/s. Without them a typo (1e12 Hz, 99.999 % overlap, 1e-6 m/s) makes
# a scan of hours and tens of GB. quakescan scan also refuses a plan beyond
# quakescan.acquisition.scan.MAX_SCAN_POINTS unless forced.
FIELD_RANGES = {
    "altitude_agl_m": (1.0, 6000.0),
    "speed_m_s": (0.5, 150.0),
    "strip_overlap_pct": (0.0, 95.0),
    "line_direction_deg": (-360.0, 360.0),
    "run_in_m": (0.0, 5000.0),
    "gps_start_s": (0.0, 1e10),
    "scan_rate_hz": (1.0, 2000.0),
    "pulse_rate_hz": (1000.0, 10_000_000.0),
    "max_range_m": (1.0, 10_000.0),
    "range_noise_sigma_m": (0.0, 1.0),
    "strip_misalignment_m": (0.0, 10.0),
    "beam_divergence_mrad": (0.0, 20.0),
    "echo_separation_m": (0.0, 100.0),
    "adaptive_edge_m": (0.0, 100.0),
    "intensity_reference_range_m": (0.1, 10_000.0),
}


@dataclass(frozen=True)
class Survey:
    name: str = "paper"
    # platform and flight plan
    altitude_agl_m: float = 100.0
    speed_m_s: float = 8.0
    strip_overlap_pct: float = 60.0
    line_direction_deg: float = 0.0
    run_in_m: float = 10.0
    pattern: str = "parallel"
    gps_start_s: float = 0.0
    # scanner
    deflector: str = "rotating_polygon"
    scan_rate_hz: float = 89.0
    pulse_rate_hz: float = 300_000.0
    fov_deg: float = 120.0
    # RIEGL VUX-1UAV, the UAV scanner of HELIOS++: its mirror turns through 330° per line.
    sweep_deg: float = 330.0
    scan_pitch_deg: float = 0.0
    range_noise_sigma_m: float = 0.01
    strip_misalignment_m: float = 0.0
    max_range_m: float = 400.0
    intensity_reference_range_m: float = 20.0
    # beam model
    beam_divergence_mrad: float = 0.5
    beam: str = "single"
    beam_rings: int = 2
    echo_separation_m: float = 0.8
    min_echo_energy: float = 0.05
    max_returns: int = 5
    adaptive_edge_m: float = 0.1
    acquisition_date: str = "2020-01-01"

    def __post_init__(self):
        self.validate()

    def validate(self, source: str = "survey") -> None:
        def bad(msg):
            raise SurveyError(f"{source}: {msg}")

        def number(name):
            v = getattr(self, name)
            # JSON true/false are not numbers (Python would read true as 1)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(f"{name} must be a finite number [{FIELD_DOC[name][1]}], got {v!r}")
            return v

        for name in ("name", "pattern", "deflector", "beam", "acquisition_date"):
            if not isinstance(getattr(self, name), str):
                bad(f"{name} must be a string, got {getattr(self, name)!r}")
        positive = ["altitude_agl_m", "speed_m_s", "scan_rate_hz", "pulse_rate_hz", "fov_deg", "max_range_m",
                    "sweep_deg", "intensity_reference_range_m"]
        for name in positive:
            if number(name) <= 0:
                bad(f"{name} must be a positive number [{FIELD_DOC[name][1]}], got {getattr(self, name)!r}")
        for name in ("run_in_m", "range_noise_sigma_m", "strip_misalignment_m", "beam_divergence_mrad",
                     "echo_separation_m", "adaptive_edge_m", "min_echo_energy", "gps_start_s"):
            if number(name) < 0:
                bad(f"{name} must be a number >= 0 [{FIELD_DOC[name][1]}], got {getattr(self, name)!r}")
        for name in ("strip_overlap_pct", "line_direction_deg", "scan_pitch_deg"):
            number(name)
        for name, (lo, hi) in FIELD_RANGES.items():
            v = getattr(self, name)
            if not lo <= v <= hi:
                bad(f"{name} must lie in [{lo:g}, {hi:g}] {FIELD_DOC[name][1]} (the range of real surveys; "
                    f"outside it a scan runs for hours or writes nothing useful), got {v!r}")
        if not 0 < self.fov_deg < 180:
            bad(f"fov_deg must be in (0, 180), got {self.fov_deg!r}")
        if not -60 <= self.scan_pitch_deg <= 60:
            bad(f"scan_pitch_deg must be in [-60, 60], got {self.scan_pitch_deg!r}")
        if self.deflector == "rotating_polygon" and not self.fov_deg <= self.sweep_deg <= 360:
            bad(f"sweep_deg must lie between fov_deg ({self.fov_deg}) and 360, got {self.sweep_deg!r}")
        if self.deflector not in DEFLECTORS:
            bad(f"deflector must be one of {DEFLECTORS}, got {self.deflector!r}")
        if self.beam not in BEAM_MODES:
            bad(f"beam must be one of {BEAM_MODES}, got {self.beam!r}")
        if self.pattern not in PATTERNS:
            bad(f"pattern must be one of {PATTERNS}, got {self.pattern!r}")
        if isinstance(self.beam_rings, bool) or not isinstance(self.beam_rings, int) or not 0 <= self.beam_rings <= 6:
            bad(f"beam_rings must be an integer 0..6, got {self.beam_rings!r}")
        if isinstance(self.max_returns, bool) or not isinstance(self.max_returns, int) \
                or not 1 <= self.max_returns <= 15:
            bad(f"max_returns must be an integer 1..15 (LAS 1.4 limit), got {self.max_returns!r}")
        if self.min_echo_energy >= 1:
            bad(f"min_echo_energy must be < 1, got {self.min_echo_energy!r}")
        if self.pulse_rate_hz / self.scan_rate_hz < 2:
            bad("pulse_rate_hz / scan_rate_hz must give at least 2 pulses per scan line")
        try:
            y, m, d = (int(x) for x in self.acquisition_date.split("-"))
            import datetime
            datetime.date(y, m, d)
        except Exception:
            bad(f"acquisition_date must be YYYY-MM-DD, got {self.acquisition_date!r}")

    # Derived quantities -------------------------------------------------------------
    @property
    def pulses_per_line(self) -> float:
        """Pulses per scan line over the whole sweep (inside and outside the FOV)."""
        return self.pulse_rate_hz / self.scan_rate_hz

    @property
    def sweep_rad(self) -> float:
        return math.radians(self.sweep_deg if self.deflector == "rotating_polygon" else self.fov_deg)

    @property
    def fov_fraction(self) -> float:
        """Share of the pulses that leave the scanner inside the FOV."""
        return math.radians(self.fov_deg) / self.sweep_rad

    @property
    def angle_step_rad(self) -> float:
        """Angle between consecutive pulses of a scan line."""
        return self.sweep_rad / self.pulses_per_line

    @property
    def swath_m(self) -> float:
        """Strip width on flat ground at ground level: the FOV's, or the narrower width within
        `max_range_m` when the FOV's edges lie beyond it (the flight plan spaces its lines by
        what the scanner records, so a short range gives closer lines, not gaps). When even
        nadir is out of range the FOV's width stands (and the scan records nothing)."""
        half = self.altitude_agl_m * math.tan(math.radians(self.fov_deg / 2))
        if self.max_range_m > self.altitude_agl_m:
            half = min(half, math.sqrt(self.max_range_m ** 2 - self.altitude_agl_m ** 2))
        return 2 * half

    @property
    def line_spacing_m(self) -> float:
        return self.swath_m * (1 - self.strip_overlap_pct / 100)

    @property
    def nominal_density_pts_m2(self) -> float:
        """Mean points per m² of flat ground at ground level inside a block of strips: pulses
        leaving the scanner per second / (speed × line spacing). Near nadir and on roofs (closer
        to the scanner) the density is a few per cent higher."""
        return self.pulse_rate_hz * self.fov_fraction / (self.speed_m_s * self.line_spacing_m)

    @property
    def sub_rays(self) -> int:
        return 1 + sum(6 * k for k in range(1, self.beam_rings + 1))

    def replace(self, **changes) -> Survey:
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        return settings_file.to_json(self, FORMAT, VERSION, FIELD_DOC)


def _als() -> Survey:
    """Manned-aircraft airborne laser scanning as a national archive holds it (AHN3, the
    Netherlands: 8–15 pts/m², oscillating-mirror and polygon scanners flown by aeroplane).

    500 m above ground at 60 m/s (117 kn), oscillating mirror over a 50° FOV (swath 466 m),
    50 % strip overlap (so every point lies in two strips, on a scene of any size: the density
    of a small scene equals that of a large block), 140 kHz at 140 lines/s (along-track and
    across-track spacing both ≈ 0.44 m per strip at nadir), range noise 2.5 cm, divergence
    0.3 mrad (15 cm footprint), returns up to 2 000 m. Nominal density
    (`nominal_density_pts_m2`) 10.0 pts/m²; measured (`quakescan.acquisition.density.measured_density`,
    roof cells of a 3 × 3 box city, 9 m roofs, seed 1): 10.35 pts/m², true roof points per
    roof area 10.37. `als_for_density` moves it to other densities."""
    return Survey(name="als", altitude_agl_m=500.0, speed_m_s=60.0, strip_overlap_pct=50.0, run_in_m=50.0,
                  deflector="oscillating_mirror", scan_rate_hz=140.0, pulse_rate_hz=140_000.0, fov_deg=50.0,
                  range_noise_sigma_m=0.025, max_range_m=2000.0, beam_divergence_mrad=0.3,
                  intensity_reference_range_m=100.0)


PRESETS = {"paper": Survey, "als": _als}

# Realistic ranges of the knobs `als_for_density` turns: aircraft ALS pulse rates (older
# 50 kHz systems to today's MHz scanners), ground speeds (slow fixed-wing to 155 kn) and
# oscillating-mirror line rates.
ALS_PULSE_RATE_HZ = (25_000.0, 1_000_000.0)  # 25 kHz: the first ALS generations (older archives)
ALS_SPEED_M_S = (40.0, 80.0)
ALS_SCAN_RATE_HZ = (20.0, 200.0)


def preset(name: str) -> Survey:
    """Named presets: 'paper' (Zahs et al. Table: UAV laser scanning) and 'als' (airborne
    laser scanning as in national archives such as AHN3, ~10 pts/m²; see `_als`)."""
    if name in PRESETS:
        return PRESETS[name]()
    known = ", ".join(repr(k) for k in PRESETS)
    raise SurveyError(f"unknown survey preset {name!r}; known: {known}, or give a survey JSON file")


def als_for_density(pts_per_m2: float, speed_m_s: float | None = None) -> Survey:
    """The 'als' preset flown for a nominal density of `pts_per_m2` (`nominal_density_pts_m2`).

    The flight geometry (altitude, FOV, overlap) stays; the pulse rate is set to the density ×
    speed × line spacing, at `speed_m_s` (default the preset's 60 m/s). When that pulse rate
    lies outside `ALS_PULSE_RATE_HZ`, the speed moves (within `ALS_SPEED_M_S`) so that the
    rate's nearest bound gives the density, as a flight planner would. The mirror's line rate
    follows so that along- and across-track spacing agree at nadir (within `ALS_SCAN_RATE_HZ`).
    4–30 pts/m² are reached at 60 m/s with 56–420 kHz."""
    base = _als()
    if isinstance(pts_per_m2, bool) or not isinstance(pts_per_m2, (int, float)) or not math.isfinite(pts_per_m2) \
            or pts_per_m2 <= 0:
        raise SurveyError(f"als_for_density: pts_per_m2 must be a positive number [pts/m²], got {pts_per_m2!r}")
    speed = base.speed_m_s if speed_m_s is None else float(speed_m_s)
    if not ALS_SPEED_M_S[0] <= speed <= ALS_SPEED_M_S[1]:
        raise SurveyError(f"als_for_density: speed_m_s must lie in {ALS_SPEED_M_S} m/s, got {speed_m_s!r}")
    spacing = base.line_spacing_m
    prr = pts_per_m2 * speed * spacing
    if not ALS_PULSE_RATE_HZ[0] <= prr <= ALS_PULSE_RATE_HZ[1]:
        prr = min(max(prr, ALS_PULSE_RATE_HZ[0]), ALS_PULSE_RATE_HZ[1])
        speed = prr / (pts_per_m2 * spacing)
        if not ALS_SPEED_M_S[0] <= speed <= ALS_SPEED_M_S[1]:
            lo = ALS_PULSE_RATE_HZ[0] / (ALS_SPEED_M_S[1] * spacing)
            hi = ALS_PULSE_RATE_HZ[1] / (ALS_SPEED_M_S[0] * spacing)
            raise SurveyError(f"als_for_density: {pts_per_m2} pts/m² is out of reach of an aircraft ALS "
                              f"({lo:.2f}–{hi:.0f} pts/m² with pulse rates {ALS_PULSE_RATE_HZ} Hz and speeds "
                              f"{ALS_SPEED_M_S} m/s)")
    # along-track spacing speed/rate = across-track spacing altitude · FOV · rate / PRR at nadir
    rate = math.sqrt(speed * prr / (base.altitude_agl_m * math.radians(base.fov_deg)))
    rate = min(max(rate, ALS_SCAN_RATE_HZ[0]), ALS_SCAN_RATE_HZ[1])
    return base.replace(speed_m_s=speed, pulse_rate_hz=prr, scan_rate_hz=rate)


def load_survey(spec: str | os.PathLike) -> Survey:
    """A preset name or the path of a survey JSON file (fields missing from the file take
    the values of its `preset`, default 'paper')."""
    return settings_file.load(spec, cls=Survey, fmt=FORMAT, version=VERSION, kind="survey", preset=preset)


# Flight planning ---------------------------------------------------------------------

@dataclass(frozen=True)
class FlightLine:
    """One straight strip, flown at constant speed; times are GPS seconds."""

    index: int
    start: np.ndarray  # (3,) float64, local frame
    heading: np.ndarray  # (3,) unit vector, horizontal
    length_m: float
    t_start: float
    speed_m_s: float

    @property
    def duration_s(self) -> float:
        return self.length_m / self.speed_m_s

    @property
    def end(self) -> np.ndarray:
        return self.start + self.heading * self.length_m

    def position(self, t: np.ndarray) -> np.ndarray:
        """(n, 3) platform positions at GPS times t."""
        return self.start + np.multiply.outer(np.asarray(t) - self.t_start, self.heading * self.speed_m_s)


@dataclass(frozen=True)
class FlightPlan:
    lines: list = field(default_factory=list)
    ground_z: float = 0.0
    flight_z: float = 0.0

    @property
    def duration_s(self) -> float:
        if not self.lines:
            return 0.0
        last = self.lines[-1]
        return last.t_start + last.duration_s - self.lines[0].t_start

    def trajectory(self, rate_hz: float = 10.0) -> np.ndarray:
        """Sampled trajectory rows (gps_time, x, y, z, heading_deg, line) in the local frame;
        `line` is the scan's `point_source_id` of that strip (line index + 1)."""
        rows = []
        for ln in self.lines:
            t = ln.t_start + np.arange(0.0, ln.duration_s + 1e-9, 1.0 / rate_hz)
            p = ln.position(t)
            hd = math.degrees(math.atan2(ln.heading[1], ln.heading[0]))
            rows.append(np.column_stack([t, p, np.full(len(t), hd), np.full(len(t), ln.index + 1)]))
        return np.concatenate(rows) if rows else np.zeros((0, 6))


# More lines than this in one direction is a scene or a survey set up wrongly (50 km of scene
# at the paper's 92 m spacing is 540 lines), and would take long just to plan.
MAX_FLIGHT_LINES = 10_000


def plan_flight(survey: Survey, bounds: np.ndarray, ground_z: float) -> FlightPlan:
    """Parallel lines over the scene's xy extent `bounds` ((2, 3) min/max, local frame).

    Lines are spaced by swath × (1 - overlap) and centred on the scene; the outermost lines
    lie at or beyond its edges, so with ≥ 50 % overlap every ground point is seen from at
    least two strips. Lines run beyond the extent by `run_in_m` plus the horizontal reach
    of a pitched scan plane.
    """
    directions = [survey.line_direction_deg]
    if survey.pattern == "crosshatch":
        directions.append(survey.line_direction_deg + 90.0)
    flight_z = ground_z + survey.altitude_agl_m
    reach = (flight_z - bounds[0, 2]) * abs(math.tan(math.radians(survey.scan_pitch_deg)))
    lines: list[FlightLine] = []
    t = survey.gps_start_s
    position = None
    corners = np.array([[x, y] for x in bounds[:, 0] for y in bounds[:, 1]])
    for deg in directions:
        a = math.radians(deg)
        u = np.array([math.cos(a), math.sin(a)])
        v = np.array([-u[1], u[0]])
        along = corners @ u
        across = corners @ v
        width = across.max() - across.min()
        spacing = survey.line_spacing_m
        n = max(1, math.ceil(width / spacing) + 1) if width > 0 else 1
        if n > MAX_FLIGHT_LINES:
            raise SurveyError(f"survey '{survey.name}': {width:,.0f} m of scene need {n:,} flight lines of "
                              f"{spacing:.3g} m spacing (more than {MAX_FLIGHT_LINES:,}); check the scene's extent "
                              "and the survey's altitude, field of view and overlap")
        centre = 0.5 * (across.max() + across.min())
        a0 = along.min() - survey.run_in_m - reach
        a1 = along.max() + survey.run_in_m + reach
        for k in range(n):
            c = centre + (k - (n - 1) / 2) * spacing
            forward = (len(lines) % 2 == 0)
            s_along, heading2 = (a0, u) if forward else (a1, -u)
            start = np.array([*(s_along * u + c * v), flight_z])
            if position is not None:  # transit from the previous line's end, no pulses
                t += float(np.linalg.norm(start - position)) / survey.speed_m_s
            heading = np.array([heading2[0], heading2[1], 0.0])
            ln = FlightLine(len(lines), start, heading, float(a1 - a0), t, survey.speed_m_s)
            lines.append(ln)
            t += ln.duration_s
            position = ln.end
    return FlightPlan(lines, ground_z, flight_z)


def write_survey_template(path: str | os.PathLike, survey: Survey | None = None) -> None:
    settings_file.write_template(path, (survey or preset("paper")).to_json())
