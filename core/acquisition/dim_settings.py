"""Settings of a virtual UAV photo flight and its dense image matching (`PhotoSurvey`):
fields, their documentation table (`FIELD_DOC`, the `_doc` of a JSON file), the ranges of
real photo flights, presets and the JSON files (`quakescan.runtime.settings_file`). The simulator that
flies them is `quakescan.acquisition.dim`."""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass

from ..errors import SurveyError
from ..runtime import settings_file

FORMAT = "quakescan-photo-survey"
VERSION = 1

# name → (meaning, unit); the JSON template carries this table as "_doc".
FIELD_DOC = {
    "altitude_agl_m": ("flight altitude above the scene's ground level", "m"),
    "speed_m_s": ("platform ground speed (sets the image times only)", "m/s"),
    "forward_overlap_pct": ("overlap of consecutive nadir images along a line, on flat ground", "%"),
    "side_overlap_pct": ("overlap of nadir images of neighbouring lines, on flat ground", "%"),
    "line_direction_deg": ("direction of the flight lines, counter-clockwise from the scene's +x axis", "deg"),
    "margin_m": (("the flown area is the scene's xy extent grown by this on every side; about "
                 "altitude · tan(oblique tilt) lets the obliques see the facades at the scene's edges"), "m"),
    "gps_start_s": ("GPS time of the first image", "s"),
    "image_width_px": ("image width (across track for the nadir camera)", "px"),
    "image_height_px": ("image height (along track for the nadir camera)", "px"),
    "pixel_pitch_um": ("sensor pixel size", "µm"),
    "focal_length_mm": ("focal length of the nadir camera", "mm"),
    "oblique_cameras": ("oblique cameras per station: 0 (nadir only) or 4 (front, back, left, right)", "-"),
    "oblique_tilt_deg": ("tilt of the oblique cameras' axes from nadir", "deg"),
    "oblique_focal_length_mm": ("focal length of the oblique cameras", "mm"),
    "point_step_px": (("DIM keeps about one point per point_step_px × point_step_px image pixels of the "
                      "best view (Metashape quality: 1 ultra high, 2 high, 4 medium, 8 low, 16 lowest)"), "px"),
    "min_views": ("cameras that must see a point for it to be reconstructed", "-"),
    "max_incidence_deg": (("a camera sees a surface point only below this angle between its ray and "
                          "the surface normal (grazing cut-off)"), "deg"),
    "max_candidate_views": ("cameras ranked per mesh piece and tried per point, best first", "-"),
    "probe_spacing_m": (("visibility is first probed on every mesh piece (its centre and a grid of this "
                        "spacing); a piece whose probes fewer than min_views cameras see gets no points, and a "
                        "point tries only the cameras that see a probe of its piece: surfaces seen only "
                        "through openings narrower than this can be missed"), "m"),
    "visibility_tolerance_m": ("a hit closer than this before the point does not occlude it", "m"),
    "noise_px": (("depth noise: sigma = noise_px · GSD / cos(incidence)^noise_angle_exponent "
                 "along the best view's ray, GSD of the best view at the point"), "px"),
    "noise_angle_exponent": ("growth of the depth noise with the incidence angle (see noise_px)", "-"),
    "smoothing_radius_m": (("points this close to a crease are pulled towards their neighbours' mean "
                           "(rounded edges and corners); 0 = off"), "m"),
    "crease_angle_deg": ("mesh edges whose faces meet at more than this are creases", "deg"),
    "acquisition_date": ("date written to the LAS header (fixed so that reruns are byte-identical)", "YYYY-MM-DD"),
}


# Bounds beyond which no UAV photo flight goes (see quakescan.acquisition.survey.FIELD_RANGES): without them a
# typo (99.999 % overlap, a point per 10⁻⁶ pixels, probes every nanometre) plans millions of
# images or points and runs for hours.
DIM_FIELD_RANGES = {
    "altitude_agl_m": (1.0, 6000.0),
    "speed_m_s": (0.5, 150.0),
    "forward_overlap_pct": (0.0, 95.0),
    "side_overlap_pct": (0.0, 95.0),
    "line_direction_deg": (-360.0, 360.0),
    "margin_m": (0.0, 5000.0),
    "gps_start_s": (0.0, 1e10),
    "image_width_px": (2, 100_000),
    "image_height_px": (2, 100_000),
    "pixel_pitch_um": (0.5, 100.0),
    "focal_length_mm": (1.0, 2000.0),
    "oblique_focal_length_mm": (1.0, 2000.0),
    "point_step_px": (0.5, 1000.0),
    "probe_spacing_m": (0.01, 100.0),
    "visibility_tolerance_m": (0.0, 10.0),
    "noise_px": (0.0, 100.0),
    "noise_angle_exponent": (0.0, 10.0),
    "smoothing_radius_m": (0.0, 10.0),
}


@dataclass(frozen=True)
class PhotoSurvey:
    """A UAV photo flight and the dense image matching settings (defaults: preset `paper`).

    The `paper` preset is a 45 MP full-frame UAV camera (8192 × 5460 px, 4.4 µm, like the
    DJI Zenmuse P1) with a 24 mm nadir and 35 mm oblique lenses tilted 45°, 120 m above
    ground, 80 %/70 % overlap, one point per 8 × 8 pixels (Metashape "low" quality):
    chosen so that a box city gets the point spacing of the L'Aquila DIM clouds in Zahs et
    al. (measured on a 3 × 4 box city: roofs 0.086 m, std 0.028; facades 0.121 m, std 0.041;
    paper: roofs 0.09 m, std 0.03; facades 0.12 m, std 0.04)."""

    name: str = "paper"
    altitude_agl_m: float = 120.0
    speed_m_s: float = 10.0
    forward_overlap_pct: float = 80.0
    side_overlap_pct: float = 70.0
    line_direction_deg: float = 0.0
    margin_m: float = 120.0
    gps_start_s: float = 0.0
    image_width_px: int = 8192
    image_height_px: int = 5460
    pixel_pitch_um: float = 4.4
    focal_length_mm: float = 24.0
    oblique_cameras: int = 4
    oblique_tilt_deg: float = 45.0
    oblique_focal_length_mm: float = 35.0
    point_step_px: float = 8.0
    min_views: int = 2
    max_incidence_deg: float = 75.0
    max_candidate_views: int = 12
    probe_spacing_m: float = 0.5
    visibility_tolerance_m: float = 0.01
    noise_px: float = 1.0
    noise_angle_exponent: float = 2.0
    smoothing_radius_m: float = 0.15
    crease_angle_deg: float = 30.0
    acquisition_date: str = "2020-01-01"

    def __post_init__(self):
        self.validate()

    def validate(self, source: str = "photo survey") -> None:
        def bad(msg):
            raise SurveyError(f"{source}: {msg}")

        def num(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(f"{name} must be a finite number [{FIELD_DOC[name][1]}], got {v!r}")
            return v

        for name in ("altitude_agl_m", "speed_m_s", "pixel_pitch_um", "focal_length_mm",
                     "oblique_focal_length_mm", "point_step_px", "probe_spacing_m"):
            if num(name) <= 0:
                bad(f"{name} must be a positive number [{FIELD_DOC[name][1]}], got {getattr(self, name)!r}")
        for name in ("margin_m", "gps_start_s", "visibility_tolerance_m", "noise_px", "noise_angle_exponent",
                     "smoothing_radius_m", "line_direction_deg"):
            if name != "line_direction_deg" and num(name) < 0:
                bad(f"{name} must be a number >= 0 [{FIELD_DOC[name][1]}], got {getattr(self, name)!r}")
            num(name)
        for name in ("forward_overlap_pct", "side_overlap_pct"):
            if not 0 <= num(name) < 100:
                bad(f"{name} must be in [0, 100), got {getattr(self, name)!r}")
        for name in ("image_width_px", "image_height_px"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 2:
                bad(f"{name} must be an integer >= 2 [px], got {v!r}")
        for name, (lo, hi) in DIM_FIELD_RANGES.items():
            v = getattr(self, name)
            if not lo <= v <= hi:
                bad(f"{name} must lie in [{lo:g}, {hi:g}] {FIELD_DOC[name][1]} (the range of real photo flights; "
                    f"outside it a simulation runs for hours or sees nothing), got {v!r}")
        if self.oblique_cameras not in (0, 4) or isinstance(self.oblique_cameras, bool):
            bad(f"oblique_cameras must be 0 or 4, got {self.oblique_cameras!r}")
        if not 0 < num("oblique_tilt_deg") < 80:
            bad(f"oblique_tilt_deg must be in (0, 80), got {self.oblique_tilt_deg!r}")
        if not 0 < num("max_incidence_deg") < 90:
            bad(f"max_incidence_deg must be in (0, 90), got {self.max_incidence_deg!r}")
        if not 0 < num("crease_angle_deg") < 180:
            bad(f"crease_angle_deg must be in (0, 180), got {self.crease_angle_deg!r}")
        if not isinstance(self.min_views, int) or isinstance(self.min_views, bool) or self.min_views < 1:
            bad(f"min_views must be an integer >= 1, got {self.min_views!r}")
        k = self.max_candidate_views
        if not isinstance(k, int) or isinstance(k, bool) or not self.min_views <= k <= 64:
            bad(f"max_candidate_views must be an integer between min_views ({self.min_views}) and 64, got {k!r}")
        try:
            import datetime

            datetime.date.fromisoformat(self.acquisition_date)
        except (TypeError, ValueError):
            bad(f"acquisition_date must be YYYY-MM-DD, got {self.acquisition_date!r}")

    # Derived quantities -------------------------------------------------------------
    @property
    def gsd_m(self) -> float:
        """Nadir ground sampling distance on flat ground at ground level."""
        return self.altitude_agl_m * self.pixel_pitch_um * 1e-6 / (self.focal_length_mm * 1e-3)

    @property
    def footprint_m(self) -> tuple[float, float]:
        """(across, along) track size of the nadir image on flat ground at ground level."""
        return self.gsd_m * self.image_width_px, self.gsd_m * self.image_height_px

    @property
    def station_spacing_m(self) -> float:
        return self.footprint_m[1] * (1 - self.forward_overlap_pct / 100)

    @property
    def line_spacing_m(self) -> float:
        return self.footprint_m[0] * (1 - self.side_overlap_pct / 100)

    def replace(self, **changes) -> PhotoSurvey:
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        return settings_file.to_json(self, FORMAT, VERSION, FIELD_DOC)


def preset_dim(name: str) -> PhotoSurvey:
    """Named photo survey presets: 'paper' (L'Aquila DIM point spacing of Zahs et al.)."""
    if name == "paper":
        return PhotoSurvey()
    raise SurveyError(f"unknown photo survey preset {name!r}; known: 'paper', or give a photo survey JSON file")


def load_photo_survey(spec: str | os.PathLike) -> PhotoSurvey:
    """A preset name or the path of a photo survey JSON file (fields missing from the file
    take the values of its `preset`, default 'paper')."""
    return settings_file.load(spec, cls=PhotoSurvey, fmt=FORMAT, version=VERSION, kind="photo survey",
                              preset=preset_dim)


def write_photo_survey_template(path: str | os.PathLike, survey: PhotoSurvey | None = None) -> None:
    """A photo survey JSON file with every field and its documentation (`_doc`)."""
    settings_file.write_template(path, (survey or preset_dim("paper")).to_json())
