"""A training set made for transfer (`quakescan training-set`): many cities, every acquisition
randomised, cross-source pairs, undamaged buildings beside collapses.

A classifier trained on one simulator's clean, dense, same-sensor pairs learns that
simulator's habits; on a real pair (another sensor, another density, noise, strip errors)
every building looks changed. This training set varies what real pairs vary:

- **buildings**: generic European towns, L'Aquila-like historic centres and the real
  Rotterdam LoD2 shapes (`../shared/data/rotterdam_subset.json`, damaged by the add-on's
  generator through `--set bundle`), each city with its own seed;
- **damage context**: mixed post-event cities (every grade side by side, EMS-98 1–2
  included and trained as "no damage": undamaged and slightly damaged buildings next to
  collapses, with a neighbour's debris on their walls), and the paper's design (every
  building heavy / extreme / destroyed) for more damaged examples;
- **acquisition**: every cloud drawn by `quakescan.acquisition.acquire.random_acquisition` (ULS altitude,
  pulse rate, range noise 1–3 cm, strip misalignment; ALS-like 4–30 pts/m²; DIM GSD,
  matching noise, nadir-only flights), and the pre-/post-event sensors of a pair cycle
  through same-source and cross-source combinations (an ALS archive before and a drone
  after is what responders really have);
- **labels**: the post-event scene's grade per building (grades 1–2 → 0).

`build` generates the scenes (the add-on's generator, `quakescan.generator.generate`), acquires the
clouds (`quakescan.acquisition.acquire.acquire`), describes every pair (`quakescan.change.pipeline.describe_pair`)
and keeps one descriptor table per pair. Every step is resumable: a scene with the same
generator settings, a cloud whose sidecar records the same acquisition, seed and scene,
and a table whose fingerprint (`quakescan.runtime.fingerprint`: the pair, its scenes, the settings) is
the one it would get now are not made again; anything else is made again. The same plan and seed
give the same table.
With a dask.distributed client, `build` runs one task per city and one per pair (`pair_table`,
the function the single-process run calls) on its cluster: the same tables, resumable alike.

The Zurich city model in `../shared/data` is reserved for evaluation and never used here.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime import fingerprint
from ..runtime.atomic import open_replacing, replacing, write_json
from ..runtime.progress import ProgressCallback, stage_log

log = logging.getLogger(__name__)

FORMAT = "quakescan-training-set"
VERSION = 1
SOURCES = ("generic", "region", "rotterdam", "small")
# Same-source and cross-source sensor combinations, cycled through the pairs of a plan
# (pre-event sensor, post-event sensor).
SENSOR_PAIRS = (("uls", "uls"), ("dim", "dim"), ("als", "uls"), ("als", "dim"), ("uls", "dim"), ("als", "als"),
                ("dim", "uls"))
ROTTERDAM = Path(__file__).resolve().parents[3] / "shared" / "data" / "rotterdam_subset.json"
CLUSTER_RADIUS_M = 150.0
LABELS = ("simulator", "footprints")
SCENES = ("clean", "realistic")
SMALL_SENSOR_PAIRS = (("als", "als"), ("als", "uls"), ("als", "dim"))
DAMAGES = ("patterns", "both")
# Mixed cities that get a twin whose grade-4/5 buildings collapse by rigid-body simulation
# (same seed, buildings, grades and acquisitions: the twins differ only in how the damage was
# made). Not all: a collapse costs ~8 s of Blender per building (bench_physics). The large
# plan twins four of its added cities too (measured against four twins in bench_transfer's ablation).
PHYSICS_TWINS = {"full": ("generic_m0", "generic_m1", "region_m0", "region_m1"),
                 "large": ("generic_m0", "generic_m1", "region_m0", "region_m1",
                           "generic_m6", "generic_m7", "region_m6", "region_m7"),
                 "quick": ("generic_m0",)}


class TrainingSetError(QuakeScanError):
    """A training set cannot be planned or built as asked."""


@dataclass(frozen=True)
class CitySpec:
    """One generated city: its pre-event scene and one or more post-event scenes."""

    name: str
    source: str  # generic | region | rotterdam
    dataset: str  # mixed | paper
    seed: int
    buildings: int | None = None  # None with rotterdam: every building of the model
    grade_mix: dict | None = None  # mixed: exact counts per grade
    details: str = "none"  # roof and facade detail of the generator: none | typical
    streetscape: str = "none"  # trees, hedges, cars, street furniture: none | typical
    damage: str = "patterns"  # how grades 4-5 are made: the add-on's patterns | physics (rigid-body collapse)

    @property
    def post_scenes(self) -> tuple:
        return ("post",) if self.dataset == "mixed" else ("post_heavy", "post_extreme", "post_destruction")


@dataclass(frozen=True)
class PairSpec:
    """One training pair: a post-event scene of a city (or its pre-event scene again, a
    no-change pair) acquired with two acquisitions."""

    city: str
    post_scene: str
    pre: dict  # Acquisition.to_json()
    post: dict
    pre_seed: int
    post_seed: int

    @property
    def name(self) -> str:
        return f"{self.city}.{self.post_scene}.{self.pre['kind']}-{self.post['kind']}.{self.pre_seed}-{self.post_seed}"


@dataclass
class TrainingPlan:
    cities: list = field(default_factory=list)
    pairs: list = field(default_factory=list)
    seed: int = 0
    name: str = "custom"
    # where building IDs of the clouds come from: the simulator's perfect per-point IDs, or
    # the pre-event scene's footprints as on real data (everything inside a polygon that is
    # not ground is the building's: a tree crown over the roof, a car under the eaves)
    labels: str = "simulator"

    def __post_init__(self):
        if self.labels not in LABELS:
            raise TrainingSetError(f"labels must be one of {LABELS}, got {self.labels!r}")

    def to_json(self) -> dict:
        return {"name": self.name, "seed": self.seed, "labels": self.labels,
                "cities": [_city_json(c) for c in self.cities], "pairs": [asdict(p) for p in self.pairs]}


def _city_json(city: CitySpec) -> dict:
    """A city's record; `damage` only where it is not the patterns, so that the records (and
    the manifests holding them) of plans made before physics twins read as they did."""
    d = asdict(city)
    if d["damage"] == "patterns":
        del d["damage"]
    return d


def _mix(n: int) -> dict:
    """Grades of a mixed training city of n buildings: about a quarter per trained class,
    a tenth of the 'no damage' quarter at EMS-98 1 and 2 (invisible damage, trained as 0)."""
    slight = max(1, round(0.05 * n))
    rest = n - 2 * slight
    base, extra = divmod(rest, 4)
    counts = [base + (1 if k < extra else 0) for k in range(4)]
    return {0: counts[0], 1: slight, 2: slight, 3: counts[1], 4: counts[2], 5: counts[3]}


def default_plan(seed: int = 0, size: str = "full", scenes: str = "clean", damage: str = "patterns",
                 small: bool = False) -> TrainingPlan:
    """The training set of the shipped model (`full`, ~2,900 building rows), a larger one
    (`large`) or a small one for tests and smoke runs (`quick`, 2 small cities).

    full: 6 generic and 6 region-specific mixed cities of 64 buildings, 2 mixed cities of the
    Rotterdam buildings (the 15 of its dense cluster), one generic and one region-specific city in the paper's design
    (64 buildings, heavy / extreme / destruction) with a no-change pair each; three pairs per
    mixed city, one per post-event scene of a paper-design city, sensors cycling through
    SENSOR_PAIRS, every acquisition drawn at random. With `small`, also 2 mixed cities of the
    generator's small set (sheds, garages, row houses: most footprints under 40 m²) with an
    ALS-like pre-event epoch and ALS, ULS and DIM post-event ones (SMALL_SENSOR_PAIRS): the
    full plan's smallest footprint spans 32 raster cells, half of a real Dutch district's
    fewer. Not in the shipped model: measured (bench_transfer), they did not change the real
    no-change rows and cost 1-5 points on the realistic city's pairs. large: the full plan's cities and pairs
    (the same draws: a built full set is reused) and as many again (6 + 6 mixed cities, one
    more paper-design city of each kind): ~5,700 rows.

    scenes: `clean` (the generator's bare buildings, the simulator's building IDs) or
    `realistic` (the same cities and acquisitions with roof and facade detail, trees, hedges,
    cars and street furniture, building IDs from the pre-event footprints as on real data).

    damage: `patterns` (the add-on's parametric damage only) or `both`: the clean plan also
    holds a physics twin (`NAME-physics`) of each PHYSICS_TWINS city, its grade-4/5 buildings
    collapsed by rigid-body simulation, acquired exactly as its twin (same acquisitions and
    seeds). A realistic plan has no twins (collapses of detailed roofs are not simulated)."""
    from ..acquisition.acquire import random_acquisition

    if size not in ("full", "quick", "large"):
        raise TrainingSetError(f"plan size must be 'full', 'large' or 'quick', got {size!r}")
    if scenes not in SCENES:
        raise TrainingSetError(f"scenes must be one of {SCENES}, got {scenes!r}")
    if damage not in DAMAGES:
        raise TrainingSetError(f"damage must be one of {DAMAGES}, got {damage!r}")
    rng = np.random.default_rng([seed, 7001])
    cities = []
    if size in ("full", "large"):
        for k in range(6):
            cities.append(CitySpec(f"generic_m{k}", "generic", "mixed", seed * 1000 + 100 + k, 64, _mix(64)))
            cities.append(CitySpec(f"region_m{k}", "region", "mixed", seed * 1000 + 200 + k, 64, _mix(64)))
        for k in range(2):
            cities.append(CitySpec(f"rotterdam_m{k}", "rotterdam", "mixed", seed * 1000 + 300 + k, None, _mix(15)))
        cities.append(CitySpec("generic_p0", "generic", "paper", seed * 1000 + 400, 64))
        cities.append(CitySpec("region_p0", "region", "paper", seed * 1000 + 401, 64))
        if small:
            for k in range(2):
                cities.append(CitySpec(f"small_m{k}", "small", "mixed", seed * 1000 + 500 + k, 64, _mix(64)))
        per_mixed = 3
        if size == "large":  # the full plan's cities first (the same draws), then as many again
            for k in range(6, 12):
                cities.append(CitySpec(f"generic_m{k}", "generic", "mixed", seed * 1000 + 100 + k, 64, _mix(64)))
                cities.append(CitySpec(f"region_m{k}", "region", "mixed", seed * 1000 + 200 + k, 64, _mix(64)))
            cities.append(CitySpec("generic_p1", "generic", "paper", seed * 1000 + 402, 64))
            cities.append(CitySpec("region_p1", "region", "paper", seed * 1000 + 403, 64))
    else:
        cities.append(CitySpec("generic_m0", "generic", "mixed", seed * 1000 + 100, 12, _mix(12)))
        cities.append(CitySpec("region_m0", "region", "mixed", seed * 1000 + 200, 12, _mix(12)))
        per_mixed = 2
    pairs, turn = [], 0

    def add(city, post_scene, combo=None):
        nonlocal turn
        if combo is None:
            a, b = SENSOR_PAIRS[turn % len(SENSOR_PAIRS)]
            turn += 1
        else:
            a, b = combo
        pre, post = random_acquisition(a, rng), random_acquisition(b, rng)
        s1, s2 = (int(v) for v in rng.integers(1, 2 ** 31 - 1, 2))
        pairs.append(PairSpec(city.name, post_scene, pre.to_json(), post.to_json(), s1, s2))

    for city in cities:
        if city.source == "small":  # what real small buildings have: an airborne archive before
            for combo in SMALL_SENSOR_PAIRS:
                add(city, "post", combo)
        elif city.dataset == "mixed":
            for _ in range(per_mixed):
                add(city, "post")
        else:
            for scene in city.post_scenes:
                add(city, scene)
            add(city, "pre")  # the same city acquired twice: every building grade 0
    if scenes == "clean":
        if damage == "both":
            twins = {c.name: replace(c, name=f"{c.name}-physics", damage="physics")
                     for c in cities if c.name in PHYSICS_TWINS[size]}
            pairs += [replace(p, city=twins[p.city].name) for p in pairs if p.city in twins]
            cities += list(twins.values())
        return TrainingPlan(cities, pairs, seed, f"default-{size}" + ("+physics" if damage == "both" else ""))
    # the same cities, grades and acquisitions, made to look like a real city: the two
    # variants differ only in what the scenes hold, so their models compare like for like
    real = {c.name: replace(c, name=f"{c.name}-real", details="typical", streetscape="typical") for c in cities}
    return TrainingPlan(list(real.values()), [replace(p, city=real[p.city].name) for p in pairs], seed,
                        f"default-{size}-realistic", labels="footprints")


@dataclass
class TransferTable:
    """Descriptor rows of a training set: one per assessable building of every pair."""

    x: np.ndarray
    y: np.ndarray  # target grade 0/3/4/5
    names: list
    city: np.ndarray  # (n,) index into `cities`
    pair: np.ndarray  # (n,) index into `pairs`
    building_id: np.ndarray
    density: np.ndarray  # (n, 2) pre/post planimetric density of the building (pts/m²)
    cities: list
    pairs: list  # PairSpec.name per index
    sensors: list  # "pre-post" kinds per pair index
    cells: np.ndarray | None = None  # (n,) raster cells of the building's footprint (older tables: None)
    # (n, 3) the share of grades 3, 4, 5's forms each row's data could not show
    # (`quakescan.learning.unseen_damage.unseen_shares`; NaN where not recorded, None: no row has it)
    unseen: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> "TransferTable":
        """The rows where `keep` (a boolean mask) holds; the city, pair and sensor lists stay."""
        from dataclasses import replace as _replace

        return _replace(self, x=self.x[keep], y=self.y[keep], city=self.city[keep], pair=self.pair[keep],
                        building_id=self.building_id[keep], density=self.density[keep],
                        cells=None if self.cells is None else self.cells[keep],
                        unseen=None if self.unseen is None else self.unseen[keep])

    @property
    def pair_city(self) -> np.ndarray:
        """(n,) the city each row's pair was acquired in (a physics twin's own name, unlike `city`)."""
        return np.array([name.split(".")[0] for name in self.pairs], dtype=object)[self.pair]

    @property
    def groups(self) -> np.ndarray:
        """One group per building of a city: its rows of several pairs stay on one side of a split."""
        return self.city.astype(np.int64) * 1_000_000 + self.building_id.astype(np.int64)


def combine_tables(clean: TransferTable, realistic: TransferTable) -> TransferTable:
    """One table of a clean and a realistic build of the same plan. A realistic city's rows take
    the index of the clean city it was made from (its name without "-real"): the same buildings,
    grades and acquisitions, so a cross-validation that holds out cities keeps both versions of
    a building on the same side."""
    if clean.names != realistic.names:
        raise TrainingSetError("the clean and realistic tables have different descriptor columns")
    index = {name: i for i, name in enumerate(clean.cities)}
    try:
        city = np.array([index[realistic.cities[i].removesuffix("-real")] for i in realistic.city], np.int64)
    except KeyError as e:
        raise TrainingSetError(f"the realistic table's city {e} has no clean counterpart") from None
    return TransferTable(
        x=np.vstack([clean.x, realistic.x]), y=np.concatenate([clean.y, realistic.y]), names=list(clean.names),
        city=np.concatenate([clean.city, city]), pair=np.concatenate([clean.pair, realistic.pair + len(clean.pairs)]),
        building_id=np.concatenate([clean.building_id, realistic.building_id]),
        density=np.vstack([clean.density, realistic.density]), cities=list(clean.cities),
        pairs=list(clean.pairs) + list(realistic.pairs), sensors=list(clean.sensors) + list(realistic.sensors),
        cells=None if clean.cells is None or realistic.cells is None
        else np.concatenate([clean.cells, realistic.cells]))


def _settings_key(settings, labels: str = "simulator") -> str:
    """Tables are reused only for the same settings, labels and descriptor code."""
    from ..change.descriptors import code_versions

    versions = code_versions(settings.surface_descriptors)
    doc = {"settings": settings.to_json(), "descriptor_version": versions.pop("descriptors"),
           "openings": versions.pop("openings")}
    if versions:  # registered families' versions (the built-in ones alone keep the keys they had)
        doc["families"] = versions
    if labels != "simulator":  # keeps the keys of tables made before labels were a choice
        doc["labels"] = labels
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:12]


def _table_fingerprint(pair: PairSpec, scenes: Path, settings, labels: str):
    """What a pair's table depends on (`quakescan.runtime.fingerprint`): the pair (its two acquisitions and
    seeds), the scenes' scene.json by content (it records the generator's settings and every
    building's grade, and its mesh follows from them: hashing meshes on every rerun would cost
    more than it guards), the descriptor settings, the labels and the descriptor code."""
    from ..change.descriptors import code_versions

    return fingerprint.make("transfer-table",
                            inputs={"pre": fingerprint.content(scenes / "pre" / "scene.json"),
                                    "post": fingerprint.content(scenes / pair.post_scene / "scene.json")},
                            settings={"pair": asdict(pair), "settings": settings.to_json(), "labels": labels},
                            code=code_versions(settings.surface_descriptors))


def city_job(city: CitySpec, folder: Path):
    """The generator's job for the city's scene bundles under `folder` (a
    `quakescan.generator.GenerationSpec`): `force`, since the folder is this training set's
    own cache, so bundles another generator version or other settings made are made again."""
    from ..generator import GenerationSpec

    if city.source == "rotterdam":
        from ..formats.cityjson import IMPORT_VERSION

        source = folder.parent / f"{city.name}_source_v{IMPORT_VERSION}"
        job = GenerationSpec("bundle", city.dataset, city.buildings, city.seed, folder, source=source)
    else:
        job = GenerationSpec(city.source, city.dataset, None if city.grade_mix else city.buildings, city.seed, folder)
    return replace(job, grade_mix=city.grade_mix, details=city.details, streetscape=city.streetscape,
                   damage=city.damage, force=True)


def generate_city(city: CitySpec, folder: Path) -> None:
    """The city's scene bundles under `folder` (`city_job`): skipped by the generator when up
    to date; a Rotterdam city's source bundle imported first where it is missing."""
    from ..generator import generate

    job = city_job(city, folder)
    if city.source == "rotterdam" and not (job.source / "scene.json").is_file():
        from ..formats.cityjson import import_cityjson
        from ..formats.scene import write_scene

        if not ROTTERDAM.is_file():
            raise TrainingSetError(f"{ROTTERDAM}: the Rotterdam CityJSON model is missing (the shared "
                                   "data folder sits beside the repository)")
        with replacing(job.source, TrainingSetError) as tmp:
            write_scene(densest_cluster(import_cityjson(ROTTERDAM)), tmp)
    generate(job)


def densest_cluster(scene, radius_m: float = CLUSTER_RADIUS_M, margin_m: float = 20.0):
    """The scene cropped to the buildings within `radius_m` of the building with the most such
    neighbours, and the terrain around them: one outlying building of a city model would
    otherwise make every survey cover the empty terrain between (the Rotterdam subset has one
    building 500 m from the other 15)."""
    from ..formats.scene import crop_to_buildings

    ids = scene.building_ids
    centres = np.array([scene.vertices[np.unique(scene.faces[scene.face_building == b])][:, :2].mean(axis=0)
                        for b in ids])
    d = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=2)
    best = int(np.argmax((d <= radius_m).sum(axis=1)))
    return crop_to_buildings(scene, ids[d[best] <= radius_m], margin_m)


def scene_footprints(city_dir: Path) -> Path:
    """The city's footprints (from its pre-event scene: a cadastre predates the event),
    written beside the scenes, again only when that scene changed."""
    from ..formats.footprints import footprints_from_scene, write_footprints
    from ..formats.scene import read_scene

    path = city_dir / "footprints.geojson"
    fingerprint.reuse_or_make(path, fingerprint.make("footprints", inputs={
        "pre": fingerprint.content(city_dir / "pre" / "scene.json")}),
        lambda: write_footprints(footprints_from_scene(read_scene(city_dir / "pre")), path))
    return path


def _grades(scene_dir: Path) -> dict:
    doc = json.loads((scene_dir / "scene.json").read_text())
    return {int(b["id"]): int(b["grade"]) for b in doc["buildings"]}


def pair_table(out_dir, pair: dict, settings: dict, labels: str = "simulator", workers: int = -1,
               discard: tuple = ()) -> dict:
    """The descriptor table of one pair of the training set under `out_dir`, whose city's
    scenes are made: read when its file is current (fingerprint), else the pair's clouds
    acquired (each reused when its sidecar records the same acquisition), described, and the
    table written under its name only when complete, with its fingerprint after it.

    Plain arguments (the pair's `PairSpec` and the `PipelineSettings` as their JSON) and no
    state of the process, so that the sequential `build` and a Dask worker run the same call
    and get the same table; a worker killed while it runs leaves at most temporary files,
    which the task run again replaces. Returns the table's arrays: x, y, building_id,
    density, cells, seconds (acquisition and description). `discard`: clouds (paths) that no
    later pair reads, removed with their sidecars once the table is written (or found)."""
    from ..acquisition.acquire import Acquisition, acquire
    from ..change.pipeline import describe_pair, descriptor_matrix
    from ..change.settings import PipelineSettings
    from ..results.evaluation import to_target_grade
    from ..formats.pair import load_pair

    out, spec, config = Path(out_dir), PairSpec(**pair), PipelineSettings.from_json(settings)
    scenes = out / "scenes" / spec.city
    table_path = out / "tables" / f"{spec.name}.{_settings_key(config, labels)}.npz"
    clouds = out / "clouds" / spec.city
    clouds.mkdir(parents=True, exist_ok=True)
    part = None
    table_fp = _table_fingerprint(spec, scenes, config, labels)
    found = fingerprint.state(table_path, table_fp)
    if found == "changed":
        log.warning("%s: unreadable table (cut or replaced since it was written), discarded: recomputing it",
                    table_path)
    elif found == "current":
        try:
            with np.load(table_path) as d:
                part = {k: d[k] for k in d.files}
        except Exception as e:  # foreign: recomputed, never a traceback on every rerun
            log.warning("%s: unreadable table (%s), discarded: recomputing it", table_path, e)
            table_path.unlink(missing_ok=True)
    if part is not None:
        _discard_clouds(discard)
        return part
    fingerprint.forget(table_path)
    t = time.perf_counter()
    paths = _cloud_paths(out, spec)
    for (scene, acq, seed, role), path in zip(_epochs(spec), paths):
        acquire(scenes / scene, Acquisition.from_json(acq, f"{spec.name} {role}"), path, seed=seed, workers=workers)
    t_acq = time.perf_counter() - t
    data = load_pair(*paths, footprints_path=scene_footprints(scenes) if labels == "footprints" else None)
    truth = _grades(scenes / spec.post_scene)
    rows = [r for r in describe_pair(data.pre, data.post, config, workers=workers)
            if r.assessable and r.building_id in truth]
    part = {"x": descriptor_matrix(rows, config.descriptor_names()),
            "y": to_target_grade(np.array([truth[r.building_id] for r in rows], np.int64)),
            "building_id": np.array([r.building_id for r in rows], np.int64),
            "density": np.array([[r.quality.get("density_pre", np.nan), r.quality.get("density_post", np.nan)]
                                 for r in rows], dtype=np.float64).reshape(len(rows), 2),
            "cells": np.array([r.quality.get("cells", 0) for r in rows], np.int64),
            "seconds": np.array([t_acq, time.perf_counter() - t - t_acq])}
    with open_replacing(table_path, "wb") as f:
        np.savez(f, **part)
    fingerprint.record(table_path, table_fp)
    _discard_clouds(discard)
    return part


def _discard_clouds(paths) -> None:
    """Remove clouds no later pair reads, sidecar first (a cloud without its sidecar is made
    again, never trusted). Only a cloud its sidecar records as made: a file there without one
    is not the build's to delete."""
    from ..acquisition.acquire import sidecar_path

    for p in paths:
        sidecar = sidecar_path(p)
        if not sidecar.is_file() or sidecar.is_symlink():
            continue
        sidecar.unlink()
        Path(p).unlink(missing_ok=True)


def _last_readers(plan) -> list[list[str]]:
    """Per pair of the plan, the clouds (paths under the build's folder) it is the last pair
    to read: pairs share a cloud when they name the same scene, acquisition and seed."""
    last = {}
    for i, pair in enumerate(plan.pairs):
        for p in _cloud_paths(Path(), pair):
            last[str(p)] = i
    out = [[] for _ in plan.pairs]
    for p, i in last.items():
        out[i].append(p)
    return out


def _epochs(pair: PairSpec) -> tuple:
    """(scene, acquisition, seed, role) of the pair's pre- and post-event clouds."""
    return (("pre", pair.pre, pair.pre_seed, "pre"), (pair.post_scene, pair.post, pair.post_seed, "post"))


def _cloud_paths(out: Path, pair: PairSpec) -> list:
    return [out / "clouds" / pair.city / f"{scene}.{acq['kind']}.{seed}.las" for scene, acq, seed, _ in _epochs(pair)]


def _city_task(out_dir: str, city: dict) -> str:
    """Dask task: the city's scenes (`generate_city`) from its plain record; returns its name."""
    spec = CitySpec(**{**city, "grade_mix": None if city["grade_mix"] is None
                       else {int(g): int(n) for g, n in city["grade_mix"].items()}})
    generate_city(spec, Path(out_dir) / "scenes" / spec.name)
    return spec.name


def _pair_task(after: list, out_dir: str, pair: dict, settings: dict, labels: str, discard: tuple = ()) -> dict:
    """Dask task: `pair_table` on a single-threaded worker. `after` holds the results of the
    tasks it must follow (its city's generation, earlier pairs writing one of its clouds):
    Dask runs it only once they are done. Every numba kernel on one thread: the worker
    processes are the parallelism."""
    from ..runtime.workers import kernel_threads

    with kernel_threads(1):
        return pair_table(out_dir, pair, settings, labels, workers=1, discard=discard)


def build(out_dir, plan: TrainingPlan, settings, *, workers: int = -1,
          progress: ProgressCallback | None = None, client=None, keep_clouds: bool = True) -> TransferTable:
    """Generate, acquire and describe everything the plan asks for under out_dir; returns the
    table of all pairs. Resumable and seeded (see the module docstring). `progress(done,
    total)` counts cities generated and pairs acquired and described; the stage messages go to
    the logger `quakescan.stages` (`quakescan.runtime.progress`).

    `client` (a dask.distributed Client): the same work as Dask tasks on its cluster, one per
    city (the generator) and one per pair (`pair_table`: acquisition and description, after
    its city), the same table; every worker must reach out_dir. Without, one process, city
    after city and pair after pair with `workers` threads.

    `keep_clouds` False: each cloud is removed once the last pair that reads it has its table
    (the large plan's clouds fill 27 GB, its tables 30 MB); a resumed build acquires again
    only the clouds of pairs without a table."""
    out = Path(out_dir)
    for sub in ("scenes", "clouds", "tables"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cities = {c.name: c for c in plan.cities}
    if len(cities) < len(plan.cities):  # one folder per name: two cities would write the same scenes
        twice = sorted({c.name for c in plan.cities if sum(d.name == c.name for d in plan.cities) > 1})
        raise TrainingSetError(f"the plan names a city more than once: {twice}")
    unknown = sorted({p.city for p in plan.pairs} - set(cities))
    if unknown:
        raise TrainingSetError(f"pairs name cities the plan does not have: {unknown}")
    names = settings.descriptor_names()
    discard = ([[] for _ in plan.pairs] if keep_clouds
               else [[str(out / p) for p in paths] for paths in _last_readers(plan)])
    if client is None:
        parts = _build_here(out, plan, settings, workers, progress, discard)
    else:
        parts = _build_on_dask(client, out, plan, settings, progress, discard)
    manifest_pairs = [{"name": pair.name, "rows": int(len(part["y"])),
                       "acquire_s": round(float(part["seconds"][0]), 1),
                       "describe_s": round(float(part["seconds"][1]), 1)} for pair, part in zip(plan.pairs, parts)]
    city_index = {c.name: i for i, c in enumerate(plan.cities)}
    for c in plan.cities:  # a physics twin holds its twin's buildings and acquisitions: one city when held out
        if c.damage != "patterns" and c.name.removesuffix(f"-{c.damage}") in city_index:
            city_index[c.name] = city_index[c.name.removesuffix(f"-{c.damage}")]
    table = TransferTable(
        x=np.vstack([p["x"] for p in parts]) if parts else np.zeros((0, len(names))),
        y=np.concatenate([p["y"] for p in parts]) if parts else np.zeros(0, np.int64),
        names=list(names),
        city=np.concatenate([np.full(len(p["y"]), city_index[pr.city]) for p, pr in zip(parts, plan.pairs)]),
        pair=np.concatenate([np.full(len(p["y"]), i) for i, p in enumerate(parts)]),
        building_id=np.concatenate([p["building_id"] for p in parts]),
        density=np.vstack([p["density"] for p in parts]),
        cities=[c.name for c in plan.cities], pairs=[p.name for p in plan.pairs],
        sensors=[f"{p.pre['kind']}-{p.post['kind']}" for p in plan.pairs],
        cells=np.concatenate([p["cells"] for p in parts]) if parts and all("cells" in p for p in parts) else None)
    write_json(out / "manifest.json", {
        "format": FORMAT, "version": VERSION, "plan": plan.to_json(), "settings": settings.to_json(),
        "rows": int(len(table.y)), "grades": {str(g): int(n) for g, n in zip(*np.unique(table.y, return_counts=True))},
        "pairs": manifest_pairs, "seconds": round(time.perf_counter() - t0, 1)})
    stage_log.info(f"training set: {len(table.y)} building rows from {len(plan.pairs)} pairs in "
                   f"{time.perf_counter() - t0:.0f} s")
    return table


def _pair_message(k: int, n: int, pair: PairSpec, part: dict) -> str:
    return (f"  [{k}/{n}] {pair.name}: {len(part['y'])} buildings "
            f"(acquire {part['seconds'][0]:.0f} s, describe {part['seconds'][1]:.0f} s)")


def _build_here(out: Path, plan: TrainingPlan, settings, workers: int, progress, discard: list) -> list:
    """The tables of every pair, made in this process: every city first, then pair by pair."""
    steps = len(plan.cities) + len(plan.pairs)
    stage_log.info(f"training set 1/3: {len(plan.cities)} cities -> {out / 'scenes'}")
    for k, city in enumerate(plan.cities, 1):
        t = time.perf_counter()
        generate_city(city, out / "scenes" / city.name)
        stage_log.info(f"  [{k}/{len(plan.cities)}] {city.name} ({city.source}, {city.dataset}) {time.perf_counter() - t:.0f} s")
        if progress:
            progress(k, steps)
    stage_log.info(f"training set 2/3 and 3/3: acquiring and describing {len(plan.pairs)} pairs")
    parts, config = [], settings.to_json()
    for k, pair in enumerate(plan.pairs, 1):
        parts.append(pair_table(out, asdict(pair), config, plan.labels, workers, tuple(discard[k - 1])))
        stage_log.info(_pair_message(k, len(plan.pairs), pair, parts[-1]))
        if progress:
            progress(len(plan.cities) + k, steps)
    return parts


def _build_on_dask(client, out: Path, plan: TrainingPlan, settings, progress, discard: list) -> list:
    """The tables of every pair as Dask tasks on `client`'s cluster: one task per city, one per
    pair after its city's. Tasks take the output folder and the plain specs and return only
    the small table arrays; the scenes and clouds stay on disk and each worker builds its own
    ray-casting scene. Progress counts tasks as they finish, in any order; the tables are put
    back in the plan's order."""
    import uuid

    from dask.distributed import as_completed

    root, config = str(out.resolve()), settings.to_json()
    # keys new in every call: a key of a run interrupted a moment ago may still be cancelling
    # on the scheduler, and a new future under it would be cancelled with it
    run = uuid.uuid4().hex[:8]
    stage_log.info(f"training set on Dask: {len(plan.cities)} cities and {len(plan.pairs)} pairs as tasks "
                   f"-> {out}")
    futures, what, made = [], {}, {}
    for city in plan.cities:
        record = asdict(city)
        f = client.submit(_city_task, root, record, key=f"trainset-city-{city.name}-{run}")
        made[city.name] = f
        futures.append(f)
        what[f.key] = ("city", city)
    # a cloud file shared by two pairs (same scene, sensor and seed) is written by the first
    # and reused or rewritten by the next, as one process does: never by two tasks at once
    last_writer, pair_futures = {}, []
    for k, pair in enumerate(plan.pairs):
        record = asdict(pair)
        paths = _cloud_paths(out, pair)
        after = [made[pair.city]] + [last_writer[p] for p in paths if p in last_writer]
        f = client.submit(_pair_task, after, root, record, config, plan.labels, tuple(discard[k]),
                          key=f"trainset-pair-{pair.name}-{run}")
        for p in paths:
            last_writer[p] = f
        futures.append(f)
        pair_futures.append(f)
        what[f.key] = ("pair", pair)
    steps, done, cities_done, pairs_done, results = len(futures), 0, 0, 0, {}
    try:
        for f in as_completed(futures):
            result = f.result()  # a task's error is raised here, with the task's traceback
            done += 1
            kind, spec = what[f.key]
            if kind == "city":
                cities_done += 1
                stage_log.info(f"  [{cities_done}/{len(plan.cities)}] {spec.name} ({spec.source}, {spec.dataset})")
            else:
                pairs_done += 1
                results[f.key] = result
                stage_log.info(_pair_message(pairs_done, len(plan.pairs), spec, result))
            if progress:
                progress(done, steps)
        return [results[f.key] for f in pair_futures]
    finally:
        client.cancel([f for f in futures if not f.done()])
