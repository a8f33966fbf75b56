"""The camera network of a DIM photo flight: exposure stations along serpentine lines and
the nadir and oblique cameras of each (step 1 of the model in `quakescan.acquisition.dim`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .dim_settings import PhotoSurvey


@dataclass
class Cameras:
    """The camera network in the scene's local frame (float64).

    `rotation[i]` has rows x (image width), y (image height), z (viewing axis) of camera i;
    a point p is in front of camera i when z · (p - position) > 0."""

    position: np.ndarray  # (n, 3)
    rotation: np.ndarray  # (n, 3, 3)
    focal_m: np.ndarray  # (n,)
    tan_half_w: np.ndarray  # (n,) half image width / focal length
    tan_half_h: np.ndarray  # (n,)
    time_s: np.ndarray  # (n,) image time
    line: np.ndarray  # (n,) flight line, 0-based
    kind: np.ndarray  # (n,) 0 nadir, 1 front, 2 back, 3 left, 4 right
    stations: int = 0
    lines: int = 0

    def __len__(self):
        return len(self.position)


def _camera_axes(view: np.ndarray, heading: np.ndarray) -> np.ndarray:
    z = view / np.linalg.norm(view)
    ref = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else heading
    x = np.cross(z, ref)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.array([x, y, z])


def plan_cameras(survey: PhotoSurvey, bounds: np.ndarray, ground_z: float) -> Cameras:
    """Exposure stations over `bounds` ((2, 3) local min/max) grown by `margin_m`, five
    (or one) cameras each, serpentine lines centred on the scene."""
    a = math.radians(survey.line_direction_deg)
    u = np.array([math.cos(a), math.sin(a)])
    v = np.array([-u[1], u[0]])
    corners = np.array([[x, y] for x in bounds[:, 0] for y in bounds[:, 1]])
    along, across = corners @ u, corners @ v
    m = survey.margin_m
    a0, a1 = along.min() - m, along.max() + m
    c0, c1 = across.min() - m, across.max() + m
    ns = max(1, math.ceil((a1 - a0) / survey.station_spacing_m) + 1)
    nl = max(1, math.ceil((c1 - c0) / survey.line_spacing_m) + 1)
    a_mid, c_mid = 0.5 * (a0 + a1), 0.5 * (c0 + c1)
    z = ground_z + survey.altitude_agl_m
    tilt = math.radians(survey.oblique_tilt_deg)
    pitch = survey.pixel_pitch_um * 1e-6
    down = np.array([0.0, 0.0, -1.0])
    pos, rot, foc, tw, th, tim, lin, kind = [], [], [], [], [], [], [], []
    t = survey.gps_start_s
    prev = None
    for k in range(nl):
        c = c_mid + (k - (nl - 1) / 2) * survey.line_spacing_m
        forward = k % 2 == 0
        h2 = u if forward else -u
        heading = np.array([h2[0], h2[1], 0.0])
        right = np.array([h2[1], -h2[0], 0.0])
        views = [(0, down, survey.focal_length_mm)]
        if survey.oblique_cameras == 4:
            for kk, hd in ((1, heading), (2, -heading), (3, -right), (4, right)):
                views.append((kk, math.cos(tilt) * down + math.sin(tilt) * hd, survey.oblique_focal_length_mm))
        axes = [(kk, _camera_axes(vw, heading), f * 1e-3) for kk, vw, f in views]
        for j in range(ns):
            s = a_mid + (j - (ns - 1) / 2) * survey.station_spacing_m
            s = s if forward else 2 * a_mid - s
            p = np.array([*(s * u + c * v), z])
            if prev is not None:
                t += float(np.linalg.norm(p - prev)) / survey.speed_m_s
            prev = p
            for kk, r, f in axes:
                pos.append(p)
                rot.append(r)
                foc.append(f)
                tw.append(survey.image_width_px * pitch / 2 / f)
                th.append(survey.image_height_px * pitch / 2 / f)
                tim.append(t)
                lin.append(k)
                kind.append(kk)
    return Cameras(np.array(pos), np.array(rot), np.array(foc), np.array(tw), np.array(th), np.array(tim),
                   np.array(lin, np.int64), np.array(kind, np.uint8), stations=ns * nl, lines=nl)
