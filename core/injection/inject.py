"""`quakescan inject`: EMS-98 damage injected into a real point cloud.

A real cloud and its footprints become a post-event cloud with known grades:

1. every footprint with enough points gets a proxy block (`quakescan.injection.proxy`);
2. the add-on's scene generator damages the proxies with the same catalogue patterns (and
   rigid-body collapses, `damage="physics"|"both"`) the training set is made with
   (`blender_scripts/generate_scenes.py --set bundle --grades`): the model learns the
   catalogue, not the injector;
3. the cloud's own pulses (`quakescan.injection.pulses`) are re-cast against the damaged
   proxies (`quakescan.injection.recast`): the real cloud where the surface still stands,
   new returns where the damage put or uncovered a surface, at the real density and pattern.

OUT holds `post.las` (or `post.laz` for a compressed input), `truth.csv` (building_id,
grade, what was done to it: `quakescan evaluate --truth` reads it), `inject.json` (the record:
inputs, settings, flight lines, per-building counts; written last, with the run's
fingerprint) and `scenes/` (the proxy bundle, the generator's pre- and post-event bundles).
The same inputs and seed give the same bytes; a finished run with the same inputs is not
redone, an interrupted one redoes only what it had not finished (the generator keeps its
finished bundles).
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime import fingerprint
from ..runtime.atomic import replacing, write_json, write_text
from ..runtime.progress import stage_log

FORMAT = "quakescan-injection"
VERSION = 2  # 2: a building's ground from farther off where none lies within 10 m
# the grades a mix draws, and the buildings eligible for damage in a mix (the independent
# benchmark's choice: a building needs points enough to be graded at all)
DAMAGE_GRADES = (3, 4, 5)
DEFAULT_MIN_POINTS = 200
KINDS = ("auto", "lidar", "dim")
DAMAGE_MODES = ("patterns", "physics", "both")
# range noise is estimated from the spread of ground returns in 1 m cells, within these bounds
NOISE_CELL_M = 1.0
NOISE_RANGE_M = (0.005, 0.2)


class InjectionError(QuakeScanError):
    """Damage cannot be injected as asked; the message names the input."""


@dataclass(frozen=True)
class InjectSettings:
    seed: int = 0
    grades: dict | None = None  # {building ID: grade}: exactly these (others 0)
    grade_mix: dict | None = None  # {grade: count} among the eligible buildings (others 0)
    min_points: int = DEFAULT_MIN_POINTS
    damage: str = "patterns"
    kind: str = "auto"
    range_noise_m: float | None = None  # None: estimated from the cloud
    id_field: str | None = None

    def __post_init__(self):
        if (self.grades is None) == (self.grade_mix is None):
            raise InjectionError("give either grades per building or a grade mix (one of them)")
        if self.damage not in DAMAGE_MODES:
            raise InjectionError(f"damage must be one of {DAMAGE_MODES}, got {self.damage!r}")
        if self.kind not in KINDS:
            raise InjectionError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if isinstance(self.min_points, bool) or not isinstance(self.min_points, int) or self.min_points < 1:
            raise InjectionError(f"min_points must be a positive integer, got {self.min_points!r}")
        if self.range_noise_m is not None and not (math.isfinite(self.range_noise_m) and self.range_noise_m >= 0):
            raise InjectionError(f"range_noise_m must be a number >= 0, got {self.range_noise_m!r}")
        for g, n in (self.grade_mix or {}).items():
            if g not in DAMAGE_GRADES or isinstance(n, bool) or not isinstance(n, int) or n < 0:
                raise InjectionError(f"a grade mix counts buildings of grades {DAMAGE_GRADES} (the rest stay 0); "
                                     f"got {g!r}: {n!r}")
        for b, g in (self.grades or {}).items():
            if isinstance(g, bool) or not isinstance(g, int) or not 0 <= g <= 5:
                raise InjectionError(f"building {b}: grade must be an integer 0-5, got {g!r}")

    def to_json(self) -> dict:
        return {"seed": self.seed, "grades": None if self.grades is None else {str(b): g for b, g in
                                                                              sorted(self.grades.items())},
                "grade_mix": None if self.grade_mix is None else {str(g): n for g, n in sorted(self.grade_mix.items())},
                "min_points": self.min_points, "damage": self.damage, "kind": self.kind,
                "range_noise_m": self.range_noise_m, "id_field": self.id_field}


@dataclass
class InjectResult:
    post: Path
    truth: Path
    record: Path
    reused: bool
    grades: dict  # {building ID: grade} of every footprint
    counts: dict  # {"moved": n, "removed": n, "kept": n}


def post_name(cloud: Path) -> str:
    return "post.laz" if cloud.name.lower().endswith(".laz") else "post.las"


def inject(cloud, footprints, out_dir, settings: InjectSettings) -> InjectResult:
    """Inject damage into `cloud` (LAS/LAZ) with its `footprints` (GeoJSON) and write OUT
    (module docstring)."""
    from ..formats.footprints import read_footprints
    from ..formats.pointcloud import read_las

    cloud, footprints_path, out = Path(cloud), Path(footprints), Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InjectionError(f"{out}: exists and is not a folder; give an output folder")
    post_path, truth_path, record_path = out / post_name(cloud), out / "truth.csv", out / "inject.json"
    for own in (post_path, truth_path, record_path):
        if own.resolve() in (cloud.resolve(), footprints_path.resolve()):
            raise InjectionError(f"{own}: is an input of this run; give another output folder")
    fp = fingerprint.make("inject", {"cloud": fingerprint.stat(cloud), "footprints": fingerprint.content(footprints_path)},
                          settings.to_json(), {"injection": VERSION})
    done = _finished(record_path, fp, (post_path, truth_path))
    if done is not None:
        stage_log.info("inject: %s is up to date with these inputs and settings", out)
        return InjectResult(post_path, truth_path, record_path, True,
                            {int(b): int(g) for b, g in done["grades"].items()}, done["counts"])
    las = read_las(cloud)
    fps = read_footprints(footprints_path, id_field=settings.id_field)
    xyz = np.c_[np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)].astype(np.float64)
    if len(xyz) == 0:
        raise InjectionError(f"{cloud}: has no points")
    cls = np.asarray(las.classification)
    from ..formats.footprints import assign_buildings
    from .proxy import build_proxy

    building_of_point = assign_buildings(xyz[:, 0], xyz[:, 1], fps)
    if not building_of_point.any():
        raise InjectionError(f"{footprints_path}: no footprint contains a point of {cloud} "
                             "(are they in the same coordinate system?)")
    origin = np.floor(xyz.min(axis=0))
    crs = _crs_name(las)
    stage_log.info("inject: proxy blocks of %d footprints", len(fps))
    model = build_proxy(xyz, cls, building_of_point, fps, origin, seed=settings.seed, crs=crs)
    grades = choose_grades(settings, model, fps)
    scenes = out / "scenes"
    pre_scene, post_scene = _damaged_scenes(model, grades, settings, scenes)
    from .pulses import lidar_pulses, nadir_pulses
    from .recast import KEPT, MOVED, REMOVED, moved_class, recast

    kind = _kind(settings.kind, las)
    if kind == "lidar":
        pulses = lidar_pulses(xyz, _field(las, "gps_time"), _scan_angle(las), _field(las, "point_source_id"))
    else:
        pulses = nadir_pulses(len(xyz))
    noise = settings.range_noise_m if settings.range_noise_m is not None else estimate_range_noise(xyz, cls)
    damaged = {b: _roof_relief(xyz[building_of_point == b], model.buildings[b].roof_z)
               for b, g in grades.items() if g > 0}
    stage_log.info("inject: re-casting the pulses near %d damaged buildings", len(damaged))
    result = recast(xyz, pulses.directions, building_of_point, pre_scene, post_scene, damaged, noise, settings.seed)
    _write_post(las, result, post_path, moved_class)
    per_building = _per_building(building_of_point, result.fate, (KEPT, MOVED, REMOVED))
    patterns = {b.id: [p.get("name") for p in b.patterns] for b in post_scene.buildings}
    write_text(truth_path, truth_csv(fps.ids, grades, model, patterns, per_building), error=InjectionError)
    counts = {"kept": int((result.fate == KEPT).sum()), "moved": int((result.fate == MOVED).sum()),
              "removed": int((result.fate == REMOVED).sum())}
    record = {"format": FORMAT, "version": VERSION, "fingerprint": fp.digest, "inputs": fp.inputs,
              "settings": settings.to_json(), "kind": kind, "range_noise_m": noise,
              "pulses": {"lines": [line.to_json() for line in pulses.lines],
                         "methods": {name: int((pulses.method == code).sum()) for code, name in
                                     ((0, "trajectory"), (1, "scan angle"), (2, "nadir"))}},
              "proxies": len(model.buildings), "skipped": {str(b): why for b, why in sorted(model.skipped.items())},
              "grades": {str(b): g for b, g in sorted(grades.items())}, "counts": counts,
              "outputs": {"post": post_path.name, "post_bytes": post_path.stat().st_size,
                          "truth": truth_path.name, "truth_bytes": truth_path.stat().st_size}}
    write_json(record_path, record, error=InjectionError)
    return InjectResult(post_path, truth_path, record_path, False, grades, counts)


def _finished(record_path: Path, fp, outputs) -> dict | None:
    try:
        doc = json.loads(record_path.read_bytes())
    except (OSError, ValueError):
        return None
    if not fingerprint.matches(doc, fp):
        return None
    sizes = doc.get("outputs", {})
    post, truth = outputs
    if not (post.is_file() and truth.is_file() and post.stat().st_size == sizes.get("post_bytes")
            and truth.stat().st_size == sizes.get("truth_bytes")):
        return None
    return doc


def choose_grades(settings: InjectSettings, model, fps) -> dict:
    """{building ID: grade} of every footprint: the given grades, or the mix drawn (seeded)
    among the proxies with at least `min_points` points; 0 elsewhere."""
    known = set(int(b) for b in fps.ids)
    grades = {b: 0 for b in sorted(known)}
    if settings.grades is not None:
        for b, g in sorted(settings.grades.items()):
            if int(b) not in known:
                raise InjectionError(f"grades: building {b} is not one of the footprints' IDs")
            if g > 0 and int(b) not in model.buildings:
                raise InjectionError(f"grades: building {b} cannot be damaged: {model.skipped.get(int(b), 'no proxy')}")
            grades[int(b)] = int(g)
        return grades
    eligible = sorted(b for b, p in model.buildings.items() if p.n_points >= settings.min_points)
    want = sum(settings.grade_mix.values())
    if want > len(eligible):
        raise InjectionError(f"the grade mix damages {want} buildings but only {len(eligible)} have a proxy and at "
                             f"least {settings.min_points} points")
    rng = np.random.default_rng([int(settings.seed), 4403])
    picked = rng.permutation(eligible)
    k = 0
    for g, n in sorted(settings.grade_mix.items()):
        for b in picked[k:k + n].tolist():
            grades[int(b)] = int(g)
        k += n
    return grades


def _damaged_scenes(model, grades: dict, settings: InjectSettings, scenes: Path):
    """The generator's pre- and post-event bundles of the proxies with these grades."""
    from ..generator import GenerationSpec, generate
    from ..formats.scene import read_scene, write_scene

    proxy_dir = scenes / "proxy"
    write_scene(model.scene, proxy_dir)
    grades_file = scenes / "grades.json"
    write_json(grades_file, {str(b): g for b, g in sorted(grades.items()) if g > 0 and b in model.buildings},
               error=InjectionError)
    stage_log.info("inject: damaging the proxies with the add-on's patterns (%s)", settings.damage)
    generate(GenerationSpec("bundle", "mixed", None, settings.seed, scenes / "generated", source=proxy_dir,
                            damage=settings.damage, grades=grades_file))
    return read_scene(scenes / "generated" / "pre"), read_scene(scenes / "generated" / "post")


def _kind(kind: str, las) -> str:
    if kind != "auto":
        return kind
    t, a = _field(las, "gps_time"), _scan_angle(las)
    return "lidar" if t is not None and a is not None and np.ptp(t) > 0 and np.ptp(a) > 0 else "dim"


def _field(las, name):
    if name not in set(las.point_format.dimension_names):
        return None
    return np.asarray(las[name])


def _scan_angle(las):
    """Scan angle in degrees: LAS 1.4's `scan_angle` (0.006 degree steps) or the older rank."""
    names = set(las.point_format.dimension_names)
    if "scan_angle" in names:
        return np.asarray(las.scan_angle, dtype=np.float64) * 0.006
    if "scan_angle_rank" in names:
        return np.asarray(las.scan_angle_rank, dtype=np.float64)
    return None


def _crs_name(las) -> str | None:
    try:
        crs = las.header.parse_crs()
    except Exception:  # a broken CRS record is not this command's business: the proxy needs none
        return None
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else None


def estimate_range_noise(xyz: np.ndarray, cls: np.ndarray) -> float:
    """The sensor's range noise: the median spread (standard deviation) of ground returns in
    1 m cells (all returns without a ground class), within NOISE_RANGE_M."""
    pts = xyz[cls == 2] if (cls == 2).sum() >= 100 else xyz
    key = np.floor(pts[:, :2] / NOISE_CELL_M).astype(np.int64)
    key = (key[:, 0] - key[:, 0].min()) * (int(np.ptp(key[:, 1])) + 1) + (key[:, 1] - key[:, 1].min())
    _, inv, n = np.unique(key, return_inverse=True, return_counts=True)
    s1 = np.bincount(inv, pts[:, 2])
    s2 = np.bincount(inv, pts[:, 2] ** 2)
    ok = n >= 3
    if not ok.any():
        return NOISE_RANGE_M[0]
    var = (s2[ok] - s1[ok] ** 2 / n[ok]) / (n[ok] - 1)
    return float(np.clip(np.sqrt(np.median(np.maximum(var, 0))), *NOISE_RANGE_M))


def _roof_relief(own: np.ndarray, roof_z: float) -> float:
    """How far above the flat proxy roof the building's own returns reach (98th percentile)."""
    if len(own) == 0:
        return 0.0
    return max(0.0, float(np.percentile(own[:, 2], 98)) - roof_z)


def _write_post(las, result, path: Path, moved_class) -> None:
    """The real records, with moved returns' coordinates (and class) changed and removed ones dropped."""
    from .recast import MOVED, REMOVED

    rec = las.points.array.copy()
    moved = np.flatnonzero(result.fate == MOVED)
    scale, offset = las.header.scales, las.header.offsets
    for k, name in enumerate("XYZ"):
        ints = np.round((result.xyz[moved, k] - offset[k]) / scale[k])
        if len(ints) and (ints.min() < np.iinfo(np.int32).min or ints.max() > np.iinfo(np.int32).max):
            raise InjectionError(f"{path}: a new return lies outside what the file's scale and offset can store")
        rec[name][moved] = ints.astype(rec[name].dtype)
    if len(moved):
        _set_class(rec, moved, moved_class(result.surface[moved], np.asarray(las.classification)[moved]))
    keep = result.fate != REMOVED
    import laspy

    out = laspy.LasData(las.header)
    out.points = laspy.ScaleAwarePointRecord(rec[keep], las.header.point_format, las.header.scales,
                                             las.header.offsets)
    with replacing(path, InjectionError) as tmp:
        out.write(tmp, do_compress=path.suffix.lower() == ".laz")


def _set_class(rec, idx, classes) -> None:
    if "classification" in rec.dtype.names:  # formats 6-10: a byte of its own
        rec["classification"][idx] = classes
    else:  # formats 0-5 pack the class in the low five bits beside three flags, which stay
        rec["raw_classification"][idx] = (rec["raw_classification"][idx] & 0b11100000) | (classes & 0b00011111)


def _per_building(building_of_point: np.ndarray, fate: np.ndarray, codes) -> dict:
    out = {}
    ids, inv = np.unique(building_of_point, return_inverse=True)
    for code in codes:
        counts = np.bincount(inv, weights=(fate == code), minlength=len(ids)).astype(int)
        for b, c in zip(ids.tolist(), counts.tolist()):
            out.setdefault(int(b), {})[code] = c
    return out


TRUTH_COLUMNS = ["building_id", "grade", "injected", "patterns", "material", "storeys", "n_points", "moved", "removed",
                 "reason"]


def truth_csv(ids, grades: dict, model, patterns: dict, per_building: dict) -> str:
    """truth.csv: one row per footprint, sorted by ID (`quakescan evaluate --truth` reads
    building_id and grade)."""
    from .recast import MOVED, REMOVED

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(TRUTH_COLUMNS)
    materials = {b.id: (b.material, b.storeys) for b in model.scene.buildings}
    for b in sorted(int(i) for i in ids):
        counts = per_building.get(b, {})
        proxy = model.buildings.get(b)
        material, storeys = materials.get(b, ("", ""))
        w.writerow([b, grades.get(b, 0), int(grades.get(b, 0) > 0), " ".join(patterns.get(b, [])) if grades.get(b) else "",
                    material, storeys, proxy.n_points if proxy else sum(counts.values()) if counts else 0,
                    counts.get(MOVED, 0), counts.get(REMOVED, 0), "" if proxy else model.skipped.get(b, "")])
    return buf.getvalue()
