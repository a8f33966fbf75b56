"""Acquisitions: which sensor flew, with which settings — the one seam where simulated
training data varies the sensor the way real pre/post pairs do.

An `Acquisition` is a kind and the full settings that kind uses: `uls` (UAV laser
scanning) and `als` (airborne laser scanning from an aircraft) are a `quakescan.survey.Survey`,
`dim` (dense image matching of a UAV photo flight) is a `quakescan.dim.PhotoSurvey`.
`acquire` runs it on a scene; `thin_to_density` makes a sparser copy of an epoch.

Ranges of `random_acquisition` (each value drawn independently; rates and densities
log-uniformly, since their effects are multiplicative, everything else uniformly):

- every kind: flight-line direction 0–180°. Lines are planned along a block's long axis,
  not along a building's, so which facades a strip sees differs from flight to flight.
- `uls` (the paper's preset otherwise: VUX-1UAV-like rotating polygon, 120° FOV, 8 m/s):
  altitude 50–150 m above ground (the span of published post-earthquake UAV-LiDAR
  flights; below 50 m obstacles, above 150 m the legal ceiling in most countries); pulse
  rate 100–600 kHz (UAV scanners' range, the paper's 300 kHz inside it); range noise
  0.01–0.03 m (UAV scanners' specified precision 5–10 mm plus trajectory noise); strip
  misalignment 0–0.05 m per axis (0 = perfectly adjusted strips, 5 cm = an unadjusted
  UAV trajectory); strip overlap 30–70 % (flight plans from economical to the paper's 60 %
  and beyond).
- `als` (the `als` preset otherwise, see `quakescan.survey.als_for_density`): nominal density
  2–30 pts/m² (national archives: older blocks 1–4, AHN2/3 6–15, others up to 30; the
  sparse end matters: a building the model never saw that sparse is 'not assessable'); range noise
  0.02–0.04 m (aircraft scanners' ranging precision plus GNSS/INS noise at 500 m);
  strip misalignment 0.02–0.08 m (residuals of archive strip adjustment are a few
  centimetres; older blocks reach decimetres).
- `dim` (the paper's photo survey otherwise: 45 MP camera, 24 mm nadir, four 35 mm
  obliques at 45°): altitude 80–150 m above ground, i.e. a nadir ground sampling distance
  of 1.47–2.75 cm; matching noise 0.5–1.5 px (well-textured to poorly textured façades);
  one point per 6–12 px (Metashape between "medium" and "lowest"); a quarter of the
  flights are nadir-only (rapid mapping often has no oblique camera). The flown area grows
  by altitude · tan(oblique tilt) when there are obliques (so they see the scene's edge
  facades, as in the paper preset), not at all without them.

Density of an epoch (`measured_density`, the quantity `thin_to_density` aims at): the
planimetric density of building roofs. Building points (ASPRS class 6, or building_id > 0
in a file without class 6) are binned into 1 m × 1 m cells of the world grid (x, y floored
to whole metres); only interior cells count (all 8 neighbours hold building points too,
so a cell cut by a roof outline or holding the wall below it does not), and in each cell
only the points within 1 m below its highest building point (roofs up to 45° count whole;
wall points below the eaves and the lower part of a step do not). The density is the
interquartile mean (mean of the middle half) of those counts per m²: robust to chimneys
and leftover walls, and not stuck to whole numbers as a median of counts would be.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__, settings_file
from .dim import PhotoSurvey, preset_dim, simulate_dim
from .errors import PointCloudError, QuakeScanError, SceneError, SurveyError, read_json_file
from .pointcloud import BUILDING_CLASS, Epoch, read_epoch, read_las
from .scan import scan
from .scene import Scene, read_scene
from .survey import Survey, als_for_density, preset

log = logging.getLogger(__name__)

KINDS = ("uls", "als", "dim")
FORMAT = "quakescan-acquisition"
VERSION = 1
RECORD_FORMAT = "quakescan-acquisition-record"
SIDECAR_SUFFIX = ".acquisition.json"

# Ranges of random_acquisition (see the module docstring for why).
LINE_DIRECTION_DEG = (0.0, 180.0)
ULS_ALTITUDE_M = (50.0, 150.0)
ULS_PULSE_RATE_HZ = (100_000.0, 600_000.0)
ULS_RANGE_NOISE_M = (0.01, 0.03)
ULS_MISALIGNMENT_M = (0.0, 0.05)
ULS_OVERLAP_PCT = (30.0, 70.0)
ALS_DENSITY_PTS_M2 = (2.0, 30.0)
ALS_RANGE_NOISE_M = (0.02, 0.04)
ALS_MISALIGNMENT_M = (0.02, 0.08)
DIM_ALTITUDE_M = (80.0, 150.0)
DIM_NOISE_PX = (0.5, 1.5)
DIM_POINT_STEP_PX = (6.0, 12.0)
DIM_NADIR_ONLY_SHARE = 0.25

# Density measurement (see the module docstring): the one measure of quakescan.surface.
from .surface import DENSITY_CELL_M  # noqa: E402


@dataclass(frozen=True)
class Acquisition:
    """A sensor kind ('uls', 'als', 'dim') and the full settings it flies with."""

    kind: str
    settings: Survey | PhotoSurvey

    def __post_init__(self):
        if self.kind not in KINDS:
            raise SurveyError(f"acquisition kind must be one of {KINDS}, got {self.kind!r}")
        want = PhotoSurvey if self.kind == "dim" else Survey
        if not isinstance(self.settings, want):
            raise SurveyError(f"a {self.kind!r} acquisition needs a {want.__name__}, "
                              f"got {type(self.settings).__name__}")

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'uls 80m 300kHz noise 0.020 mis 0.030'."""
        s = self.settings
        if self.kind == "dim":
            cams = "oblique" if s.oblique_cameras else "nadir"
            return (f"dim {s.altitude_agl_m:.0f}m gsd {100 * s.gsd_m:.1f}cm noise {s.noise_px:.2f}px "
                    f"step {s.point_step_px:g}px {cams}")
        size = (f"{s.altitude_agl_m:.0f}m {s.pulse_rate_hz / 1e3:.0f}kHz" if self.kind == "uls"
                else f"{s.nominal_density_pts_m2:.1f}pts/m2")
        return f"{self.kind} {size} noise {s.range_noise_sigma_m:.3f} mis {s.strip_misalignment_m:.3f}"

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "kind": self.kind, "label": self.label,
                "settings": dataclasses.asdict(self.settings)}

    @classmethod
    def from_json(cls, data, source: str = "acquisition") -> Acquisition:
        """The acquisition of a `to_json` document (the label is ignored: it is derived)."""
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise SurveyError(f"{source}: not an acquisition (format must be {FORMAT!r})")
        if data.get("version") != VERSION:
            raise SurveyError(f"{source}: acquisition version {data.get('version')!r} not supported "
                              f"(expected {VERSION})")
        kind = data.get("kind")
        if kind not in KINDS:
            raise SurveyError(f"{source}: acquisition kind must be one of {KINDS}, got {kind!r}")
        values = data.get("settings")
        if not isinstance(values, dict):
            raise SurveyError(f"{source}: 'settings' must be an object of survey fields")
        if kind == "dim":
            settings = settings_file.from_values(values, cls=PhotoSurvey, kind="photo survey",
                                                 preset=preset_dim, source=source)
        else:
            settings = settings_file.from_values(values, cls=Survey, kind="survey", preset=preset, source=source)
        return cls(kind, settings)


# Random acquisitions ------------------------------------------------------------------

def _uniform(rng, lo_hi, digits):
    return round(float(rng.uniform(*lo_hi)), digits)


def _log_uniform(rng, lo_hi, digits):
    lo, hi = lo_hi
    return round(float(math.exp(rng.uniform(math.log(lo), math.log(hi)))), digits)


def random_acquisition(kind: str, rng) -> Acquisition:
    """An acquisition of `kind` with settings drawn from the ranges in the module docstring.

    `rng` is a numpy Generator or a seed; the same seed gives the same acquisition. Values
    are rounded to a resolution that matters (0.1 m, 0.1 mm, 1 kHz, …) so labels and
    sidecars stay readable."""
    if kind not in KINDS:
        raise SurveyError(f"acquisition kind must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng(rng)
    direction = _uniform(rng, LINE_DIRECTION_DEG, 1)
    if kind == "uls":
        s = preset("paper").replace(
            name="uls-random", line_direction_deg=direction,
            altitude_agl_m=_uniform(rng, ULS_ALTITUDE_M, 1),
            pulse_rate_hz=round(_log_uniform(rng, ULS_PULSE_RATE_HZ, 0), -3),
            range_noise_sigma_m=_uniform(rng, ULS_RANGE_NOISE_M, 4),
            strip_misalignment_m=_uniform(rng, ULS_MISALIGNMENT_M, 4),
            strip_overlap_pct=_uniform(rng, ULS_OVERLAP_PCT, 1))
        return Acquisition("uls", s)
    if kind == "als":
        density = _log_uniform(rng, ALS_DENSITY_PTS_M2, 2)
        s = als_for_density(density).replace(
            name="als-random", line_direction_deg=direction,
            range_noise_sigma_m=_uniform(rng, ALS_RANGE_NOISE_M, 4),
            strip_misalignment_m=_uniform(rng, ALS_MISALIGNMENT_M, 4))
        return Acquisition("als", s)
    base = preset_dim("paper")
    altitude = _uniform(rng, DIM_ALTITUDE_M, 1)
    noise_px = _uniform(rng, DIM_NOISE_PX, 2)
    step = _uniform(rng, DIM_POINT_STEP_PX, 1)
    obliques = 0 if rng.random() < DIM_NADIR_ONLY_SHARE else 4
    margin = round(altitude * math.tan(math.radians(base.oblique_tilt_deg)), 1) if obliques else 0.0
    s = base.replace(name="dim-random", line_direction_deg=direction, altitude_agl_m=altitude,
                     noise_px=noise_px, point_step_px=step, oblique_cameras=obliques, margin_m=margin)
    return Acquisition("dim", s)


# Acquiring ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Acquired:
    """What `acquire` made (or found): the cloud, its sidecar's record, and whether the
    cloud was already there (`resumed`: nothing was simulated)."""

    path: Path
    record: dict
    resumed: bool


def sidecar_path(out_path: str | os.PathLike) -> Path:
    """OUT.acquisition.json beside the cloud OUT."""
    out = Path(out_path)
    return out.with_name(out.name + SIDECAR_SUFFIX)


def scene_fingerprint(scene: str | os.PathLike | Scene) -> str:
    """A hash of the scene: the bytes of scene.json and its mesh for a bundle folder, the
    arrays and manifest for a Scene object (the same scene in the two forms hashes
    differently: an output acquired from one is acquired again from the other)."""
    h = hashlib.sha256()
    if isinstance(scene, Scene):
        h.update(b"scene-object")
        for a in (scene.vertices, scene.faces, scene.face_building, scene.face_surface, scene.origin):
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        h.update(json.dumps([b.to_json() for b in scene.buildings], sort_keys=True).encode())
        h.update(json.dumps([scene.crs, scene.epoch, scene.units]).encode())
        if scene.has_porous:  # only then: fingerprints of scenes without vegetation stay what they were
            h.update(np.ascontiguousarray(scene.face_porous, dtype=bool).tobytes())
            h.update(json.dumps(scene.transmission).encode())
        return h.hexdigest()
    folder = Path(scene)
    manifest = folder / "scene.json"
    data = read_json_file(manifest, "scene manifest", SceneError)
    mesh = data.get("mesh", "mesh.ply") if isinstance(data, dict) else "mesh.ply"
    h.update(b"scene-bundle")
    for path in (manifest, folder / str(mesh)):
        h.update(path.read_bytes() if path.is_file() else b"<missing>")
    return h.hexdigest()


def _record(acquisition: Acquisition, seed: int, scene_source: str, fingerprint: str) -> dict:
    return {"format": RECORD_FORMAT, "version": 1, "acquisition": acquisition.to_json(), "seed": seed,
            "scene": {"source": scene_source, "fingerprint": fingerprint}, "quakescan_version": __version__}


def _same_acquisition(old: dict, new: dict) -> bool:
    """Same settings, kind, seed, scene and QuakeScan version (the label, summary and the
    scene's path may differ)."""
    try:
        return (old["format"] == RECORD_FORMAT and old["seed"] == new["seed"]
                and old["acquisition"]["kind"] == new["acquisition"]["kind"]
                and old["acquisition"]["settings"] == new["acquisition"]["settings"]
                and old["scene"]["fingerprint"] == new["scene"]["fingerprint"]
                and old.get("quakescan_version") == new["quakescan_version"])
    except (KeyError, TypeError):
        return False


def _read_record(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def acquire(scene: str | os.PathLike | Scene, acquisition: Acquisition, out_path: str | os.PathLike,
            seed: int = 0, threads: int | None = None, progress=None) -> Acquired:
    """Acquire `scene` (a bundle folder or a Scene) with `acquisition` into `out_path`
    (.las/.laz) through `quakescan.scan.scan` (uls, als) or `quakescan.dim.simulate_dim` (dim).

    Resumable: when `out_path` exists and its sidecar OUT.acquisition.json records the same
    acquisition, seed, scene (fingerprint) and QuakeScan version, nothing is simulated.
    Atomic: the cloud appears under its name only when complete, and its sidecar only
    after it (a stale sidecar is removed first), so an interrupted run is redone, never
    half-used."""
    if not isinstance(acquisition, Acquisition):
        raise QuakeScanError(f"acquire: acquisition must be an Acquisition (kind one of {KINDS}), "
                             f"got {type(acquisition).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise QuakeScanError(f"acquire: seed must be an integer >= 0, got {seed!r}")
    out = Path(out_path)
    if out.suffix.lower() not in (".las", ".laz"):
        raise PointCloudError(f"{out}: output must end in .las or .laz")
    source = "scene object" if isinstance(scene, Scene) else str(scene)
    record = _record(acquisition, int(seed), source, scene_fingerprint(scene))
    sidecar = sidecar_path(out)
    old = _read_record(sidecar) if out.is_file() and sidecar.is_file() else None
    if old is not None and _same_acquisition(old, record):
        log.info("%s: up to date (%s, seed %d)", out, acquisition.label, seed)
        return Acquired(out, old, True)
    sidecar.unlink(missing_ok=True)
    loaded = scene if isinstance(scene, Scene) else read_scene(scene)
    if acquisition.kind == "dim":
        summary = simulate_dim(loaded, acquisition.settings, out, seed=int(seed), progress=progress,
                               threads=threads, source=source)
    else:
        summary = scan(loaded, acquisition.settings, out, seed=int(seed), threads=threads, progress=progress,
                       source=source)
    record["summary"] = summary.to_json()
    _write_json_atomic(sidecar, record)
    log.info("%s: %s, seed %d, %d points in %.1f s", out, acquisition.label, seed, summary.points,
             summary.wall_time_s)
    return Acquired(out, record, False)


# Density ------------------------------------------------------------------------------

def _roof_cell_density(cells: np.ndarray, z: np.ndarray) -> tuple[float, int]:
    """The one density measure of the project (`quakescan.surface.roof_cell_density`)."""
    from .surface import roof_cell_density

    return roof_cell_density(cells, z)


def _building_mask(classification: np.ndarray, building_id: np.ndarray | None) -> np.ndarray:
    m = np.asarray(classification) == BUILDING_CLASS
    if not m.any() and building_id is not None:
        m = np.asarray(building_id) > 0
    return m


_NO_ROOF = ("{source}: no roof to measure the density on: no 1 m cell of building points (class 6 or "
            "building_id > 0) is surrounded by such cells")


def _cells(xyz: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Integer cells of the world grid from local xyz and their origin (the cell size's whole
    multiples in the origin drop out, so a large origin costs no precision; cell indices are
    relative, only their neighbourhood matters)."""
    frac = np.asarray(origin[:2], dtype=np.float64) % DENSITY_CELL_M
    return np.floor((xyz[:, :2] + frac) / DENSITY_CELL_M).astype(np.int64)


def _las_cells(las, mask) -> tuple[np.ndarray, np.ndarray]:
    """Cells and heights of the masked points of a LAS file: coordinates relative to its
    offset (integers × scale), as `read_epoch` gives them."""
    h = las.header
    xyz = np.column_stack([np.asarray(las.points[c][mask], dtype=np.float64) * h.scales[k]
                           for k, c in enumerate("XYZ")])
    return _cells(xyz, np.asarray(h.offsets, dtype=np.float64)), xyz[:, 2]


def measured_density(cloud: str | os.PathLike | Epoch) -> float:
    """Planimetric density of the building roofs of an epoch (a LAS/LAZ path or an Epoch),
    in points per m², as defined in the module docstring. Raises PointCloudError when the
    cloud has no interior roof cell to measure."""
    epoch = cloud if isinstance(cloud, Epoch) else read_epoch(cloud)
    m = _building_mask(epoch.classification, epoch.building_id)
    density, cells = _roof_cell_density(_cells(epoch.xyz[m], epoch.origin), epoch.xyz[m, 2])
    if cells == 0:
        raise PointCloudError(_NO_ROOF.format(source=epoch.source))
    return density


@dataclass(frozen=True)
class Thinning:
    """What `thin_to_density` did: densities before and after (measured), the share of
    points kept and the point counts."""

    density_before: float
    density_after: float
    keep_fraction: float
    points_before: int
    points_after: int


def thin_to_density(in_las: str | os.PathLike, out_las: str | os.PathLike, pts_per_m2: float,
                    seed: int = 0) -> Thinning:
    """Write a random, seeded thinning of the epoch `in_las` to `out_las` whose
    `measured_density` is `pts_per_m2` (within about 1 %; it reports what it reached).

    Every point is kept independently with one probability, the same for ground, roofs and
    walls (the whole acquisition gets sparser); that probability is found by a few
    measure-and-rescale steps on nested subsets (point i is kept when u_i < p, u_i drawn
    once from `seed`). Every point attribute, the header's scales, offsets, CRS and extra
    dimensions are kept; the file appears only when complete. Thinning cannot add points:
    a target above the measured density is refused. Random thinning leaves a less regular
    pattern than a sparser scan would (Poisson-like gaps instead of a wider grid)."""
    import laspy

    if isinstance(pts_per_m2, bool) or not isinstance(pts_per_m2, (int, float)) or not math.isfinite(pts_per_m2) \
            or pts_per_m2 <= 0:
        raise PointCloudError(f"thin_to_density: pts_per_m2 must be a positive number [pts/m²], got {pts_per_m2!r}")
    in_las, out = Path(in_las), Path(out_las)
    if out.suffix.lower() not in (".las", ".laz"):
        raise PointCloudError(f"{out}: output must end in .las or .laz")
    if out.resolve() == in_las.resolve():
        raise PointCloudError(f"{out}: thin_to_density would overwrite its input; write to another file")
    las = read_las(in_las)
    names = set(las.point_format.dimension_names)
    m = _building_mask(las.classification, las["building_id"] if "building_id" in names else None)
    cells, z = _las_cells(las, m)
    before, n_cells = _roof_cell_density(cells, z)
    if n_cells == 0:
        raise PointCloudError(_NO_ROOF.format(source=in_las))
    if pts_per_m2 > before:
        raise PointCloudError(f"{in_las}: measured density {before:.2f} pts/m² is below the target "
                              f"{pts_per_m2} pts/m²; thinning cannot add points")
    u = np.random.default_rng(seed).random(len(las.points))
    p, after = _keep_probability(cells, z, u[m], pts_per_m2, pts_per_m2 / before)
    if not math.isfinite(after):
        raise PointCloudError(f"{in_las}: thinned to {pts_per_m2} pts/m² no roof cell would be left to measure; "
                              "choose a higher density")
    keep = u < p
    thinned = laspy.LasData(las.header)
    thinned.points = las.points[keep]
    tmp = out.with_name(out.name + ".part")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        thinned.write(tmp, do_compress=out.suffix.lower() == ".laz")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return Thinning(before, after, p, len(las.points), int(keep.sum()))


def _keep_probability(cells, z, u, target, p) -> tuple[float, float]:
    """(p, density) with the measured density of the building points with u < p closest to
    `target` found in a few rescaling steps from the first guess `p` (stops within 1 %)."""
    best = (p, math.nan)
    for _ in range(12):
        kept = u < p
        d = _roof_cell_density(cells[kept], z[kept])[0]
        if math.isfinite(d) and (math.isnan(best[1]) or abs(d - target) < abs(best[1] - target)):
            best = (p, d)
        if not math.isfinite(d) or d <= 0:
            p = min(1.0, 2 * p)
            continue
        if abs(d - target) <= 0.01 * target:
            break
        p = min(1.0, p * target / d)
    return best


__all__ = ["KINDS", "Acquired", "Acquisition", "Thinning", "acquire", "measured_density", "random_acquisition",
           "scene_fingerprint", "sidecar_path", "thin_to_density"]
