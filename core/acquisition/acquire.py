"""Acquisitions: which sensor flew, with which settings — the one seam where simulated
training data varies the sensor the way real pre/post pairs do.

An `Acquisition` is a sensor kind and the full settings that kind uses; the kinds and
what each needs are those of the sensor registry `quakescan.acquisition.sensors` (built in: `uls` and
`als`, a `quakescan.acquisition.survey.Survey`; `dim`, a `quakescan.acquisition.dim_settings.PhotoSurvey`). `acquire` runs
one on a scene, resumably; `random_acquisition` draws one for the training set from the
ranges its sensor documents (`quakescan.acquisition.sensor_lidar`, `quakescan.acquisition.sensor_dim`); `thin_to_density`
makes a sparser copy of an epoch.

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
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__

from . import sensors
from ..runtime.atomic import replacing, write_json
from ..errors import PointCloudError, QuakeScanError, SurveyError
from ..runtime.fingerprint import Fingerprint, make, scene_fingerprint
from ..formats.pointcloud import BUILDING_CLASS, Epoch, read_epoch, read_las
from ..runtime.progress import ProgressCallback
from ..formats.scene import Scene, read_scene
from ..runtime.workers import accepts_old_threads

log = logging.getLogger(__name__)

FORMAT = "quakescan-acquisition"
VERSION = 1
RECORD_FORMAT = "quakescan-acquisition-record"
SIDECAR_SUFFIX = ".acquisition.json"


def __getattr__(name):
    # KINDS follows the registry: a sensor registered after this module was imported is in it.
    if name == "KINDS":
        return sensors.kinds()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# Density measurement (see the module docstring): the one measure of quakescan.change.surface.
from ..change.surface import DENSITY_CELL_M  # noqa: E402


@dataclass(frozen=True)
class Acquisition:
    """A sensor kind (one of `quakescan.acquisition.sensors.kinds()`) and the full settings it flies with."""

    kind: str
    settings: object

    def __post_init__(self):
        sensors.check_settings(self.kind, self.settings)

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'uls 80m 300kHz noise 0.020 mis 0.030'."""
        return sensors.get(self.kind).label(self.settings)

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
        try:
            sensor = sensors.get(data.get("kind"))
        except SurveyError as e:
            raise SurveyError(f"{source}: {e}") from None
        values = data.get("settings")
        if not isinstance(values, dict):
            raise SurveyError(f"{source}: 'settings' must be an object of survey fields")
        return cls(sensor.kind, sensor.from_values(values, source))


def random_acquisition(kind: str, rng) -> Acquisition:
    """An acquisition of `kind` with settings drawn from the ranges its sensor documents.

    `rng` is a numpy Generator or a seed; the same seed gives the same acquisition. Values
    are rounded to a resolution that matters (0.1 m, 0.1 mm, 1 kHz, …) so labels and
    sidecars stay readable."""
    sensor = sensors.get(kind)
    return Acquisition(kind, sensor.draw(np.random.default_rng(rng)))


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


def _record(acquisition: Acquisition, seed: int, scene_source: str, fingerprint: str) -> dict:
    return {"format": RECORD_FORMAT, "version": 1, "acquisition": acquisition.to_json(), "seed": seed,
            "scene": {"source": scene_source, "fingerprint": fingerprint}, "quakescan_version": __version__}


def _fingerprint(record: dict) -> Fingerprint:
    """What an acquisition record says the cloud depends on: its kind, settings and seed, the
    scene and the QuakeScan that made it (not the label, summary or the scene's path)."""
    return make("acquisition", inputs={"scene": record["scene"]["fingerprint"]},
                settings={"kind": record["acquisition"]["kind"], "settings": record["acquisition"]["settings"],
                          "seed": record["seed"]},
                code={"record": record["format"], "quakescan": record.get("quakescan_version")})


def _same_acquisition(old: dict, new: dict) -> bool:
    try:
        return _fingerprint(old).digest == _fingerprint(new).digest
    except (KeyError, TypeError):  # a record of another format or edited
        return False


def _same_size(record: dict, out: Path) -> bool:
    """The cloud is the size its record says: a cut or replaced one is acquired again (a record
    written before sizes were recorded: its settings decide)."""
    size = out.stat().st_size
    return record.get("output_bytes", size) == size


def _read_record(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


@accepts_old_threads
def acquire(scene: str | os.PathLike | Scene, acquisition: Acquisition, out_path: str | os.PathLike,
            seed: int = 0, workers: int = -1, progress: ProgressCallback | None = None) -> Acquired:
    """Acquire `scene` (a bundle folder or a Scene) with `acquisition` into `out_path`
    (.las/.laz) with its sensor (`quakescan.acquisition.sensors.simulate`).

    Resumable (`quakescan.runtime.fingerprint`'s rule): when `out_path` exists with the size and its
    sidecar OUT.acquisition.json records the same acquisition, seed, scene (fingerprint) and
    QuakeScan version, nothing is simulated.
    Atomic: the cloud appears under its name only when complete, and its sidecar only
    after it (a stale sidecar is removed first), so an interrupted run is redone, never
    half-used."""
    if not isinstance(acquisition, Acquisition):
        raise QuakeScanError(f"acquire: acquisition must be an Acquisition (kind one of {sensors.kinds()}), "
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
    if old is not None and _same_acquisition(old, record) and _same_size(old, out):
        log.info("%s: up to date (%s, seed %d)", out, acquisition.label, seed)
        return Acquired(out, old, True)
    sidecar.unlink(missing_ok=True)
    loaded = scene if isinstance(scene, Scene) else read_scene(scene)
    summary = sensors.simulate(acquisition.kind, loaded, acquisition.settings, out, seed=int(seed),
                               workers=workers, progress=progress, source=source)
    record["summary"] = summary.to_json()
    record["output_bytes"] = out.stat().st_size  # a cut or replaced cloud is acquired again
    write_json(sidecar, record, ensure_ascii=False)
    log.info("%s: %s, seed %d, %d points in %.1f s", out, acquisition.label, seed, summary.points,
             summary.wall_time_s)
    return Acquired(out, record, False)


# Density ------------------------------------------------------------------------------

def _roof_cell_density(cells: np.ndarray, z: np.ndarray) -> tuple[float, int]:
    """The one density measure of the project (`quakescan.change.surface.roof_cell_density`)."""
    from ..change.surface import roof_cell_density

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
    with replacing(out, PointCloudError) as tmp:
        thinned.write(tmp, do_compress=out.suffix.lower() == ".laz")
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
