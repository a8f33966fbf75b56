"""Training rows from real points: damage injected into real archives (`quakescan inject`).

The simulated training set teaches the catalogue's damage on simulated sampling; these rows
teach it on real sampling: real roofs, real density, real scan pattern and real noise, with
the catalogue's damage re-cast along the archive's own pulses (`quakescan.injection`).

Sources are real clouds the project may train on: AHN3 tile 2 of Delft with its footprints,
and PDAL's `sample_c.las` (another sensor, another country, 5 pts/m², no outline file: its
footprints are derived from its building class, `quakescan.formats.class_footprints`).
**AHN3 tile 1 never enters** (it is reserved for evaluation, `bench/bench_real_damage.py`):
`REAL_PLAN` is checked against `RESERVED` when a table is built. Pairs (`RealPair`), both
epochs real:

- `halves`: the tile's two random halves (one before, the other after, with damage injected);
- `thinned`: the whole tile before and a random quarter of it after (an archive at 15
  pts/m² against a sparse post-event flight), damage injected into the quarter;
- `rescan`: the halves without damage (real no-change rows: every building grade 0);
- `drone`: a real half before (the archive), and after a simulated drone (`sensor`: ULS or
  DIM, its settings drawn at random from the sensor's ranges) flown over the 2.5D surface of
  the other half (`quakescan.injection.surface_model`), damage injected into the drone's
  returns: the responder's usual pair, an airborne archive and a drone flight, with the
  real city's roofs, trees and gaps under both;
- `drone_rescan`: the same without damage (no-change rows across sources).

Grade mixes, seeds, splits and patterns or rigid-body collapses vary by pair, so no pair
repeats another's damage. Each pair's rows are cached under WORK/<pair>/ with the fingerprint
of its inputs, settings and descriptor version; the table of all pairs is a
`quakescan.learning.trainset.TransferTable` whose "cities" are the sources (a source is held
out whole in the cross-validation: its buildings' rows of every pair stay on one side).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime import fingerprint
from ..runtime.atomic import open_replacing, replacing
from ..runtime.progress import stage_log

log = logging.getLogger(__name__)
VERSION = 3  # 3: rows carry what their detectability is computed from
RESERVED = ("ahn3_cropped_1",)  # evaluation only: never trained or tuned on
# real rows are few beside the simulated ones (a few hundred against twelve thousand): each is
# repeated this many times in the shipped model's training table
REAL_REPEAT = 4


class RealSetError(QuakeScanError):
    """The real-point training rows cannot be built as asked."""


@dataclass(frozen=True)
class RealSource:
    name: str
    cloud: str  # file name in the data folder
    footprints: str  # file name in the data folder, or "" to derive them from the building class


@dataclass(frozen=True)
class RealPair:
    source: str
    kind: str  # halves | thinned | rescan
    split: int  # seed of the random split
    seed: int  # inject seed
    mix: tuple = ()  # ((grade, count), ...)
    damage: str = "patterns"
    min_points: int = 60
    sensor: str = ""  # the drone's, for the drone kinds (uls | dim)

    @property
    def name(self) -> str:
        sensor = f"_{self.sensor}" if self.sensor else ""
        return f"{self.source}_{self.kind}{sensor}_s{self.split}_i{self.seed}"

    @property
    def sensor_pair(self) -> str:
        return f"real-{self.kind}" + (f"-{self.sensor}" if self.sensor else "")

    def spec(self) -> dict:
        """The fields that make the pair's rows (`sensor` only for a pair with a drone: the
        cached rows of a pair without one do not depend on the field)."""
        d = asdict(self)
        if not d["sensor"]:
            del d["sensor"]
        return d


KINDS = ("halves", "thinned", "rescan", "drone", "drone_rescan")
DRONE_KINDS = ("drone", "drone_rescan")
NO_CHANGE_KINDS = ("rescan", "drone_rescan")
DRONE_SENSORS = ("uls", "dim")


SOURCES = (RealSource("ahn3_tile2", "ahn3_cropped_2.laz", "ahn3_footprints_rd.geojson"),
           RealSource("sample_c", "sample_c.las", ""))
REAL_PLAN = (
    RealPair("ahn3_tile2", "halves", 11, 1, ((3, 6), (4, 5), (5, 5))),
    RealPair("ahn3_tile2", "halves", 12, 2, ((3, 8), (4, 4), (5, 3)), "both"),
    RealPair("ahn3_tile2", "halves", 13, 3, ((3, 5), (4, 6), (5, 4))),
    RealPair("ahn3_tile2", "halves", 14, 4, ((3, 7), (4, 4), (5, 4)), "both"),
    RealPair("ahn3_tile2", "halves", 15, 5, ((3, 10), (4, 3), (5, 2))),
    RealPair("ahn3_tile2", "thinned", 16, 6, ((3, 6), (4, 5), (5, 5)), min_points=30),
    RealPair("ahn3_tile2", "thinned", 17, 7, ((3, 8), (4, 4), (5, 3)), "both", min_points=30),
    RealPair("ahn3_tile2", "rescan", 18, 0),
    RealPair("ahn3_tile2", "rescan", 19, 0),
    RealPair("ahn3_tile2", "drone", 21, 21, ((3, 6), (4, 5), (5, 5)), sensor="uls"),
    RealPair("ahn3_tile2", "drone", 22, 22, ((3, 8), (4, 4), (5, 3)), "both", sensor="uls"),
    RealPair("ahn3_tile2", "drone", 23, 23, ((3, 6), (4, 5), (5, 4)), sensor="dim"),
    RealPair("ahn3_tile2", "drone", 24, 24, ((3, 7), (4, 4), (5, 4)), "both", sensor="dim"),
    RealPair("ahn3_tile2", "drone_rescan", 25, 25, sensor="uls"),
    RealPair("ahn3_tile2", "drone_rescan", 26, 26, sensor="dim"),
    # one building large enough to damage: each pair grades it
    RealPair("sample_c", "halves", 31, 31, ((3, 1),)),
    RealPair("sample_c", "halves", 32, 32, ((5, 1),)),
    RealPair("sample_c", "halves", 33, 33, ((4, 1),), "both"),
    RealPair("sample_c", "thinned", 34, 34, ((3, 1),), min_points=30),
    RealPair("sample_c", "rescan", 35, 0),
    RealPair("sample_c", "drone", 36, 36, ((3, 1),), sensor="uls"),
    RealPair("sample_c", "drone", 37, 37, ((4, 1),), sensor="dim"),
)


def check_plan(plan=REAL_PLAN, sources=SOURCES) -> None:
    by_name = {s.name: s for s in sources}
    for p in plan:
        s = by_name.get(p.source)
        if s is None:
            raise RealSetError(f"real pair {p.name}: no source {p.source!r}")
        if any(r in s.cloud for r in RESERVED):
            raise RealSetError(f"real pair {p.name}: {s.cloud} is reserved for evaluation and never trained on")
        if p.kind not in KINDS:
            raise RealSetError(f"real pair {p.name}: kind must be one of {', '.join(KINDS)}, got {p.kind!r}")
        if (p.kind in DRONE_KINDS) != (p.sensor in DRONE_SENSORS):
            raise RealSetError(f"real pair {p.name}: a drone kind needs a sensor of {', '.join(DRONE_SENSORS)} "
                               f"and only a drone kind has one, got kind {p.kind!r} sensor {p.sensor!r}")


def epochs(cloud: Path, pair: RealPair, folder: Path, footprints: Path | None = None) -> tuple[Path, Path]:
    """The pair's pre- and post-event clouds (before injection), written once; a drone pair's
    post-event cloud is flown over the surface of `footprints`' buildings in the other half
    (`acquire` keeps it when it is current)."""
    import laspy

    pre, post = folder / "pre.las", folder / "post_real.las"
    drone = pair.kind in DRONE_KINDS
    if pre.is_file() and post.is_file() and not drone:
        return pre, post
    las = laspy.read(cloud)
    n = len(las.points)
    u = np.random.default_rng(pair.split).random(n)
    # every kind but `thinned` splits the tile into halves
    masks = (np.ones(n, bool), u < 0.25) if pair.kind == "thinned" else (u < 0.5, u >= 0.5)
    for path, mask in zip((pre, post), masks):
        sub = laspy.LasData(las.header)
        sub.points = las.points[mask]
        if drone and path == post:
            _fly_drone(sub, pair, path, footprints)
        elif not path.is_file():
            with replacing(path, RealSetError) as tmp:
                sub.write(tmp)
    return pre, post


def _fly_drone(half, pair: RealPair, path: Path, footprints: Path | None) -> None:
    """The pair's drone (settings drawn with its seed) flown over the surface of `half`."""
    from ..acquisition.acquire import acquire, random_acquisition
    from ..formats.footprints import read_footprints
    from ..injection.surface_model import surface_scene

    if footprints is None:
        raise RealSetError(f"real pair {pair.name}: a drone pair needs the source's footprints")
    fp = read_footprints(footprints)
    xyz = np.c_[half.x, half.y, half.z]
    scene = surface_scene(xyz, np.asarray(half.classification), fp,
                          np.r_[np.floor(xyz[:, :2].min(axis=0)), 0.0], crs=fp.crs)
    acquire(scene, random_acquisition(pair.sensor, pair.seed), path, seed=pair.seed)


def derived_footprints(cloud: Path, folder: Path) -> Path:
    """FOLDER/footprints.geojson: the footprints of `cloud`'s building class (written once per
    content of the cloud)."""
    import laspy

    from ..formats.class_footprints import VERSION as CLASS_FOOTPRINTS_VERSION
    from ..formats.class_footprints import footprints_from_class
    from ..formats.footprints import write_footprints

    path = folder / "footprints.geojson"
    fp = fingerprint.make("class-footprints", {"cloud": fingerprint.content(cloud)}, {},
                          {"class_footprints": CLASS_FOOTPRINTS_VERSION})
    if fingerprint.is_current(path, fp):
        return path
    las = laspy.read(cloud)
    crs = las.header.parse_crs()
    fps = footprints_from_class(np.c_[las.x, las.y, las.z], np.asarray(las.classification),
                                crs=crs.to_string() if crs is not None else None, source=str(cloud))
    folder.mkdir(parents=True, exist_ok=True)
    fingerprint.forget(path)
    write_footprints(fps, path)
    fingerprint.record(path, fp)
    return path


def _drone_versions(pair: RealPair) -> dict:
    """What else a drone pair's rows are made from: the surface model and the simulators."""
    if pair.kind not in DRONE_KINDS:
        return {}
    from .. import __version__
    from ..injection.surface_model import VERSION as SURFACE_VERSION

    return {"surface_model": SURFACE_VERSION, "quakescan": __version__}


def pair_rows(work: Path, data: Path, pair: RealPair, settings, workers: int = -1) -> dict:
    """x, y, building_id, density, cells of one real pair (cached with its fingerprint)."""
    from ..change.pipeline import describe_pair, descriptor_matrix
    from ..change.descriptors import code_versions
    from ..injection.inject import InjectSettings, inject
    from ..results.evaluation import read_grade_csv, to_target_grade
    from ..formats.pair import load_pair

    source = {s.name: s for s in SOURCES}[pair.source]
    cloud = data / source.cloud
    for path in (cloud, data / source.footprints) if source.footprints else (cloud,):
        if not path.is_file():
            raise RealSetError(f"{path}: missing (real pair {pair.name})")
    footprints = data / source.footprints if source.footprints else derived_footprints(cloud, work / source.name)
    folder = work / pair.name
    table = folder / "rows.npz"
    fp = fingerprint.make("real-pair", {"cloud": fingerprint.content(cloud), "footprints": fingerprint.content(footprints)},
                          {"pair": pair.spec(), "pipeline": settings.to_json()},
                          {"realset": VERSION, **code_versions(settings.surface_descriptors), **_drone_versions(pair)})
    if fingerprint.is_current(table, fp):
        with np.load(table) as d:
            return {k: d[k] for k in d.files}
    folder.mkdir(parents=True, exist_ok=True)
    pre, post = epochs(cloud, pair, folder, footprints)
    if pair.kind in NO_CHANGE_KINDS:
        post_path, truth = post, {}
    else:
        r = inject(post, footprints, folder / "inject",
                   InjectSettings(seed=pair.seed, grade_mix=dict(pair.mix), damage=pair.damage,
                                  min_points=pair.min_points))
        post_path, truth = r.post, read_grade_csv(r.truth, RealSetError)
    data_pair = load_pair(pre, post_path, footprints_path=footprints)
    rows = [r for r in describe_pair(data_pair.pre, data_pair.post, settings, workers=workers) if r.assessable]
    part = {"x": descriptor_matrix(rows, settings.descriptor_names()).reshape(len(rows), -1),
            "y": to_target_grade(np.array([truth.get(r.building_id, 0) for r in rows], np.int64)),
            "building_id": np.array([r.building_id for r in rows], np.int64),
            "density": np.array([[r.quality.get("density_pre", np.nan), r.quality.get("density_post", np.nan)]
                                 for r in rows], dtype=np.float64).reshape(len(rows), 2),
            "cells": np.array([r.quality.get("cells", 0) for r in rows], np.int64),
            "sampling": sampling_rows(rows)}
    fingerprint.forget(table)
    with open_replacing(table, "wb", RealSetError) as f:
        np.savez(f, **part)
    fingerprint.record(table, fp)
    return part


def real_table(work, data, settings, *, plan=REAL_PLAN, workers: int = -1, repeat: int = 1):
    """The TransferTable of every pair of `plan` (rows repeated `repeat` times)."""
    from .trainset import TransferTable

    check_plan(plan)
    work, data = Path(work), Path(data)
    names = list(settings.descriptor_names())
    cities = [s.name for s in SOURCES]
    parts, city, pair_idx = [], [], []
    for k, pair in enumerate(plan):
        stage_log.info(f"real pair {k + 1}/{len(plan)}: {pair.name}")
        part = pair_rows(work, data, pair, settings, workers=workers)
        parts.append(part)
        city.append(np.full(len(part["y"]), cities.index(pair.source), np.int64))
        pair_idx.append(np.full(len(part["y"]), k, np.int64))
    cat = {key: np.concatenate([p[key] for p in parts]) for key in ("x", "y", "building_id", "density", "cells",
                                                                      "sampling")}
    # the shares are computed on reading, not cached: the cache keeps what they are computed from
    cat["unseen"] = unseen_of_sampling(cat["sampling"])
    reps = max(1, int(repeat))
    tile = (lambda a: np.concatenate([a] * reps)) if reps > 1 else (lambda a: a)
    return TransferTable(x=tile(cat["x"].reshape(-1, len(names))), y=tile(cat["y"]), names=names,
                         city=tile(np.concatenate(city)), pair=tile(np.concatenate(pair_idx)),
                         building_id=tile(cat["building_id"]), density=tile(cat["density"]), cities=cities,
                         pairs=[p.name for p in plan], sensors=[p.sensor_pair for p in plan],
                         cells=tile(cat["cells"]), unseen=tile(cat["unseen"].reshape(-1, len(UNSEEN_GRADES))))


UNSEEN_GRADES = (3, 4, 5)
# the quality fields a building's detectability is computed from (`detectability.of_building`)
SAMPLING_FIELDS = ("density_pre", "density_post", "area_m2", "lowering_lod_m", "wall_density_pre",
                   "wall_density_post", "facade_m2", "wall_facings_resolved")


def sampling_rows(rows) -> np.ndarray:
    """(n, 8) each BuildingRow's `SAMPLING_FIELDS` (NaN where its quality record lacks one;
    "wall_facings_resolved" 1 or 0 from its facings, `detectability.facings_resolve`)."""
    from ..change.detectability import facings_resolve

    def field(q, k):
        if k == "wall_facings_resolved":
            sides = facings_resolve(q.get("wall_facings", ()))
            return float("nan") if sides is None else float(sides)
        return _number(q.get(k))
    return np.array([[field(r.quality, k) for k in SAMPLING_FIELDS] for r in rows],
                    dtype=np.float64).reshape(len(rows), len(SAMPLING_FIELDS))


def _number(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def unseen_of_sampling(sampling: np.ndarray) -> np.ndarray:
    """(n, 3) the unseen shares of grades 3, 4, 5 (`unseen_shares`) of rows of
    `SAMPLING_FIELDS`, as `predict_rows` counts them for the same buildings."""
    from ..change.detectability import of_building
    from .unseen_damage import unseen_shares

    out = np.zeros((len(sampling), len(UNSEEN_GRADES)))
    for i, values in enumerate(np.asarray(sampling, dtype=np.float64).reshape(-1, len(SAMPLING_FIELDS))):
        quality = {k: float(v) for k, v in zip(SAMPLING_FIELDS, values) if np.isfinite(v)}
        if "lowering_lod_m" not in quality:
            quality["lowering_lod_m"] = None
        q = unseen_shares(of_building(quality), UNSEEN_GRADES)
        out[i] = [q[g] for g in UNSEEN_GRADES]
    return out


def _unseen_of(t) -> np.ndarray:
    return t.unseen if t.unseen is not None else np.full((len(t.y), len(UNSEEN_GRADES)), np.nan)


def append_tables(a, b):
    """Table `b`'s rows after `a`'s, its cities and pairs numbered after a's."""
    from .trainset import TransferTable

    if a.names != b.names:
        raise RealSetError("the tables have different descriptor columns")
    cells = None if a.cells is None or b.cells is None else np.concatenate([a.cells, b.cells])
    return TransferTable(x=np.vstack([a.x, b.x]), y=np.concatenate([a.y, b.y]), names=list(a.names),
                         city=np.concatenate([a.city, b.city + len(a.cities)]),
                         pair=np.concatenate([a.pair, b.pair + len(a.pairs)]),
                         building_id=np.concatenate([a.building_id, b.building_id]),
                         density=np.vstack([a.density, b.density]), cities=list(a.cities) + list(b.cities),
                         pairs=list(a.pairs) + list(b.pairs), sensors=list(a.sensors) + list(b.sensors), cells=cells,
                         unseen=None if a.unseen is None and b.unseen is None
                         else np.vstack([_unseen_of(a), _unseen_of(b)]))
