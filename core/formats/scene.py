"""Scene bundles: `scene.json` (manifest) + `mesh.ply` (labelled triangle mesh).

The format is QuakeScan's contract between the Blender add-on and the core; see docs/DESIGN.md
and docs/formats.md "Scene bundle". Coordinates in the mesh are float64 relative to
`origin`, so a scene at UTM coordinates keeps millimetres.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SceneError, read_json_file
from ..runtime.atomic import write_json
from .ply import MeshArrays, read_ply, write_ply

FORMAT = "quakescan-scene"
VERSION = 1
EPOCHS = ("pre", "post")
MATERIALS = ("masonry", "reinforced_concrete")
GRADES = range(0, 6)

# Face `surface` codes. Vegetation (trees, hedges) and objects (parked cars, street
# furniture) are not buildings: their faces carry building_id 0.
GROUND, ROOF, WALL, DEBRIS, INTERIOR, VEGETATION, OBJECT = 0, 1, 2, 3, 4, 5, 6
SURFACE_NAMES = {GROUND: "ground", ROOF: "roof", WALL: "wall", DEBRIS: "debris", INTERIOR: "interior",
                 VEGETATION: "vegetation", OBJECT: "object"}
MAX_SURFACE = OBJECT

# Share of a laser (sub-)ray that passes one porous face (a tree crown's surface) when the
# scene does not say otherwise (scene.json "vegetation": {"transmission": t}). Crossing a
# crown means two faces, so t = 0.5 lets t² = 25 % of the rays through a whole crown: the
# middle of the 10-40 % ground returns under leaf-on broadleaf crowns in ALS studies.
DEFAULT_TRANSMISSION = 0.5

# Faces smaller than this (m²) are degenerate: their normal is undefined and a ray hit on
# them cannot be labelled reliably.
DEGENERATE_AREA_M2 = 1e-10


@dataclass
class Building:
    id: int
    grade: int = 0
    material: str = "masonry"
    storeys: int = 1
    typology: str = "generic"
    patterns: list = field(default_factory=list)
    seed: int = 0
    extra: dict = field(default_factory=dict)  # optional keys kept through a round trip

    def to_json(self) -> dict:
        d = {"id": self.id, "grade": self.grade, "material": self.material, "storeys": self.storeys,
             "typology": self.typology, "patterns": self.patterns, "seed": self.seed}
        d.update(self.extra)
        return d


@dataclass
class Scene:
    vertices: np.ndarray  # (n, 3) float64, relative to origin
    faces: np.ndarray  # (m, 3) int64
    face_building: np.ndarray  # (m,) int32, 0 = not a building
    face_surface: np.ndarray  # (m,) uint8
    buildings: list[Building]
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    crs: str | None = None
    epoch: str = "pre"
    units: str = "m"
    # (m,) bool: faces a laser ray may pass (tree crowns; PLY face property `porous`), or
    # None when no face is porous.
    face_porous: np.ndarray | None = None
    transmission: float = DEFAULT_TRANSMISSION  # per porous face crossed

    @property
    def has_porous(self) -> bool:
        return self.face_porous is not None and bool(self.face_porous.any())

    @property
    def building_ids(self) -> np.ndarray:
        return np.array([b.id for b in self.buildings], dtype=np.int64)

    def grade_lookup(self) -> dict[int, int]:
        return {b.id: b.grade for b in self.buildings}

    def bounds(self) -> np.ndarray:
        """(2, 3) min/max of the vertices used by faces, relative to origin."""
        used = self.vertices[np.unique(self.faces)] if len(self.faces) else self.vertices
        return np.array([used.min(axis=0), used.max(axis=0)])


def crop_to_buildings(scene: Scene, building_ids, margin_m: float = 20.0) -> Scene:
    """The scene with only the given buildings and the terrain (and other non-building faces)
    within `margin_m` of their x/y extent: a city model's outlier need not make a survey fly
    over kilometres of empty terrain."""
    keep_ids = set(int(b) for b in building_ids)
    unknown = sorted(keep_ids - set(scene.building_ids.tolist()))
    if unknown:
        raise SceneError(f"crop: buildings {unknown} are not in the scene")
    tri = scene.vertices[scene.faces]  # (m, 3, 3)
    is_kept = np.isin(scene.face_building, list(keep_ids))
    lo = tri[is_kept][:, :, :2].reshape(-1, 2).min(axis=0) - margin_m
    hi = tri[is_kept][:, :, :2].reshape(-1, 2).max(axis=0) + margin_m
    near = np.all((tri[:, :, :2] >= lo) & (tri[:, :, :2] <= hi), axis=(1, 2))
    faces_kept = is_kept | ((scene.face_building == 0) & near)
    used, faces = np.unique(scene.faces[faces_kept], return_inverse=True)
    porous = scene.face_porous[faces_kept] if scene.face_porous is not None else None
    return Scene(scene.vertices[used], faces.reshape(-1, 3).astype(np.int64), scene.face_building[faces_kept],
                 scene.face_surface[faces_kept], [b for b in scene.buildings if b.id in keep_ids],
                 scene.origin.copy(), scene.crs, scene.epoch, scene.units, porous, scene.transmission)


def buildings_in_box(scene: Scene, box) -> np.ndarray:
    """IDs of the buildings whose centre (mean of their vertices' x/y, world coordinates)
    lies in `box` = (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = box
    keep = []
    for b in scene.buildings:
        v = scene.vertices[np.unique(scene.faces[scene.face_building == b.id])]
        if not len(v):
            continue
        cx, cy = v[:, :2].mean(axis=0) + scene.origin[:2]
        if x0 <= cx <= x1 and y0 <= cy <= y1:
            keep.append(b.id)
    return np.array(keep, dtype=np.int64)


# No projected CRS has coordinates beyond this (UTM northings reach 10⁷ m): an origin or a
# vertex farther out is a unit or export error, and a survey over it would never end.
MAX_COORDINATE_M = 1e8


def check_crs(crs, where: str) -> None:
    """Refuse a CRS that PROJ does not know, or whose horizontal axes are not in metres (the
    scene's coordinates are metres); None (no CRS) is allowed. Raises SceneError naming `where`."""
    if crs is None:
        return
    if not isinstance(crs, str):
        raise SceneError(f"{where}: crs must be a string like 'EPSG:2056' or null, got {crs!r}")
    import pyproj

    try:
        parsed = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError:
        raise SceneError(f"{where}: crs {crs!r} is not a coordinate reference system PROJ knows "
                         "(give an EPSG code of a projected CRS in metres, such as 'EPSG:2056', or null)") from None
    units = {a.unit_name for a in parsed.axis_info[:2]}
    if not units <= {"metre", "meter"}:
        raise SceneError(f"{where}: crs {crs!r} ({parsed.name}) has axes in {sorted(units)}; a scene's coordinates "
                         "are metres: give a projected CRS in metres")


def _manifest_error(path, msg):
    return SceneError(f"{path}: {msg}")


def read_scene(folder: str | os.PathLike, validate: bool = True) -> Scene:
    """Read a scene bundle folder; raise SceneError naming the file and the problem."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: scene bundle folder does not exist")
    manifest_path = folder / "scene.json"
    if not manifest_path.is_file():
        raise SceneError(f"{manifest_path}: scene.json is missing (a scene bundle is a folder with "
                         "scene.json and mesh.ply)")
    manifest = read_json_file(manifest_path, "scene.json", SceneError)
    if not isinstance(manifest, dict):
        raise _manifest_error(manifest_path, "top level must be a JSON object")
    if manifest.get("format") != FORMAT:
        raise _manifest_error(manifest_path, f"format is {manifest.get('format')!r}, expected {FORMAT!r}")
    if manifest.get("version") != VERSION:
        raise _manifest_error(manifest_path, f"version {manifest.get('version')!r} is not supported "
                              f"(this QuakeScan reads version {VERSION})")
    epoch = manifest.get("epoch")
    if epoch not in EPOCHS:
        raise _manifest_error(manifest_path, f"epoch must be one of {EPOCHS}, got {epoch!r}")
    origin = manifest.get("origin", [0, 0, 0])
    if (not isinstance(origin, list) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin)):
        raise _manifest_error(manifest_path, f"origin must be three finite numbers, got {origin!r}")
    if max(abs(v) for v in origin) > MAX_COORDINATE_M:
        raise _manifest_error(manifest_path, f"origin {origin} lies more than {MAX_COORDINATE_M:g} m from 0 in some "
                              "axis; no projected CRS reaches that far (a unit or export error?)")
    if manifest.get("units", "m") != "m":
        raise _manifest_error(manifest_path, f"units must be 'm', got {manifest.get('units')!r}")
    crs = manifest.get("crs")
    check_crs(crs, str(manifest_path))
    raw_buildings = manifest.get("buildings")
    if not isinstance(raw_buildings, list):
        raise _manifest_error(manifest_path, "'buildings' must be a list")
    buildings = [_parse_building(manifest_path, i, b) for i, b in enumerate(raw_buildings)]
    mesh_name = manifest.get("mesh", "mesh.ply")
    if not isinstance(mesh_name, str) or Path(mesh_name).name != mesh_name:
        raise _manifest_error(manifest_path, f"mesh must be a file name inside the bundle, got {mesh_name!r}")
    mesh_path = folder / mesh_name
    if not mesh_path.is_file():
        raise SceneError(f"{mesh_path}: mesh file named in scene.json is missing")
    transmission = _parse_vegetation(manifest_path, manifest.get("vegetation", {}))
    mesh = read_ply(mesh_path)
    scene = Scene(mesh.vertices, mesh.faces, mesh.building_id, mesh.surface, buildings,
                  origin=np.array(origin, dtype=np.float64), crs=crs, epoch=epoch,
                  face_porous=mesh.porous, transmission=transmission)
    if validate:
        validate_scene(scene, manifest_path, mesh_path)
    return scene


def _parse_vegetation(path, veg) -> float:
    """The optional "vegetation" record: {"transmission": t}, 0 <= t <= 1."""
    if not isinstance(veg, dict):
        raise _manifest_error(path, f"'vegetation' must be an object like {{\"transmission\": 0.5}}, got {veg!r}")
    t = veg.get("transmission", DEFAULT_TRANSMISSION)
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 <= t <= 1.0:
        raise _manifest_error(path, f"vegetation.transmission must be a number in [0, 1] (share of a laser ray "
                              f"passing one porous crown face), got {t!r}")
    return float(t)


_BUILDING_KEYS = {"id", "grade", "material", "storeys", "typology", "patterns", "seed"}


def _parse_building(path, i, b) -> Building:
    if not isinstance(b, dict):
        raise _manifest_error(path, f"buildings[{i}] must be an object")
    bid = b.get("id")
    if not isinstance(bid, int) or isinstance(bid, bool) or bid <= 0:
        raise _manifest_error(path, f"buildings[{i}].id must be an integer > 0, got {bid!r}")
    where = f"building {bid} (buildings[{i}])"
    grade = b.get("grade", 0)
    if isinstance(grade, bool) or not isinstance(grade, int) or grade not in GRADES:
        raise _manifest_error(path, f"{where}: grade must be an EMS-98 grade 0..5, got {grade!r}")
    material = b.get("material", "masonry")
    if material not in MATERIALS:
        raise _manifest_error(path, f"{where}: material must be one of {MATERIALS}, got {material!r}")
    storeys = b.get("storeys", 1)
    if isinstance(storeys, bool) or not isinstance(storeys, int) or storeys < 0:
        raise _manifest_error(path, f"{where}: storeys must be an integer >= 0, got {storeys!r}")
    patterns = b.get("patterns", [])
    if not isinstance(patterns, list) or not all(
            isinstance(p, dict) and isinstance(p.get("name"), str) and isinstance(p.get("params", {}), dict)
            for p in patterns):
        raise _manifest_error(path, f"{where}: patterns must be a list of {{'name': str, 'params': {{…}}}}")
    seed = b.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise _manifest_error(path, f"{where}: seed must be an integer, got {seed!r}")
    rho = b.get("reflectance")
    if rho is not None and (isinstance(rho, bool) or not isinstance(rho, (int, float)) or not math.isfinite(rho)
                            or not 0 < rho <= 1):
        raise _manifest_error(path, f"{where}: reflectance must be a number in (0, 1] (share of the laser light "
                              f"its surfaces return; absent: by material), got {rho!r}")
    extra = {k: v for k, v in b.items() if k not in _BUILDING_KEYS}
    return Building(bid, grade, material, storeys, str(b.get("typology", "generic")), patterns, seed, extra)


def validate_scene(scene: Scene, manifest_path="scene.json", mesh_path="mesh.ply") -> None:
    """Check the mesh and the manifest against each other; raise SceneError on the first problem."""
    v, f = scene.vertices, scene.faces
    if v.ndim != 2 or v.shape[1] != 3:
        raise SceneError(f"{mesh_path}: vertices must be (n, 3), got {v.shape}")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise SceneError(f"{mesh_path}: {len(idx)} vertices have NaN/inf coordinates "
                         f"(first: vertex {idx[0]} = {v[idx[0]].tolist()})")
    far = np.abs(v).max(axis=1) > MAX_COORDINATE_M if len(v) else np.zeros(0, bool)
    if far.any():
        idx = np.flatnonzero(far)
        raise SceneError(f"{mesh_path}: {len(idx)} vertices lie more than {MAX_COORDINATE_M:g} m from the origin "
                         f"(first: vertex {idx[0]} = {v[idx[0]].tolist()}); a unit or export error?")
    if not np.all(np.isfinite(scene.origin)) or np.abs(scene.origin).max() > MAX_COORDINATE_M:
        raise SceneError(f"{manifest_path}: origin {scene.origin.tolist()} must be finite and within "
                         f"{MAX_COORDINATE_M:g} m of 0")
    check_crs(scene.crs, str(manifest_path))
    if len(f):
        out = (f < 0) | (f >= len(v))
        if out.any():
            face = int(np.flatnonzero(out.any(axis=1))[0])
            raise SceneError(f"{mesh_path}: face {face} points at vertex {f[face].tolist()} "
                             f"but the mesh has only {len(v)} vertices")
        area = triangle_areas(v, f)
        degenerate = area <= DEGENERATE_AREA_M2
        if degenerate.any():
            idx = np.flatnonzero(degenerate)
            raise SceneError(f"{mesh_path}: {len(idx)} degenerate faces (area <= {DEGENERATE_AREA_M2} m², "
                             f"repeated or collinear vertices), first: face {idx[0]} "
                             f"(vertices {f[idx[0]].tolist()}); remove them before export")
    surf_bad = scene.face_surface > MAX_SURFACE
    if surf_bad.any():
        face = int(np.flatnonzero(surf_bad)[0])
        raise SceneError(f"{mesh_path}: face {face} has surface code {int(scene.face_surface[face])}; "
                         f"valid codes are {SURFACE_NAMES}")
    if scene.face_porous is not None:
        if len(scene.face_porous) != len(f):
            raise SceneError(f"{mesh_path}: {len(scene.face_porous)} porous flags for {len(f)} faces")
        not_veg = scene.face_porous.astype(bool) & (scene.face_surface != VEGETATION)
        if not_veg.any():
            face = int(np.flatnonzero(not_veg)[0])
            raise SceneError(f"{mesh_path}: face {face} is porous but its surface is "
                             f"{SURFACE_NAMES.get(int(scene.face_surface[face]))!r}; only vegetation "
                             f"(surface {VEGETATION}) can be porous")
    non_building = (scene.face_building > 0) & (scene.face_surface >= VEGETATION)
    if non_building.any():
        face = int(np.flatnonzero(non_building)[0])
        raise SceneError(f"{mesh_path}: face {face} is {SURFACE_NAMES[int(scene.face_surface[face])]} but carries "
                         f"building_id {int(scene.face_building[face])}; vegetation and objects are not "
                         "buildings (building_id 0)")
    if (scene.face_building < 0).any():
        face = int(np.flatnonzero(scene.face_building < 0)[0])
        raise SceneError(f"{mesh_path}: face {face} has negative building_id {int(scene.face_building[face])}")
    ids = scene.building_ids
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise SceneError(f"{manifest_path}: duplicate building IDs {uniq[counts > 1].tolist()}")
    mesh_ids = np.unique(scene.face_building)
    mesh_ids = mesh_ids[mesh_ids > 0]
    not_in_manifest = np.setdiff1d(mesh_ids, ids)
    if len(not_in_manifest):
        raise SceneError(f"{mesh_path}: faces carry building IDs {_short(not_in_manifest)} that "
                         f"{manifest_path} does not list")
    not_in_mesh = np.setdiff1d(ids, mesh_ids)
    if len(not_in_mesh):
        raise SceneError(f"{manifest_path}: buildings {_short(not_in_mesh)} have no faces in {mesh_path}")


def _short(a) -> str:
    a = [int(x) for x in a]
    return str(a) if len(a) <= 10 else f"{a[:10]} and {len(a) - 10} more"


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    # Edge vectors from the first vertex: differences are small even at UTM coordinates.
    a = vertices[faces[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a), axis=1)


def write_scene(scene: Scene, folder: str | os.PathLike, validate: bool = True) -> Path:
    """Write a scene bundle. The mesh is written first and scene.json last, each atomically,
    so a folder with a scene.json is always complete."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise SceneError(f"{folder}: exists and is not a folder; a scene bundle is a folder (give a new name)")
    if validate:
        validate_scene(scene, folder / "scene.json", folder / "mesh.ply")
    folder.mkdir(parents=True, exist_ok=True)
    porous = scene.face_porous.astype(np.uint8) if scene.has_porous else None
    write_ply(folder / "mesh.ply", MeshArrays(scene.vertices, scene.faces, scene.face_building, scene.face_surface,
                                              porous))
    manifest = {
        "format": FORMAT, "version": VERSION, "epoch": scene.epoch,
        "origin": [float(x) for x in scene.origin], "crs": scene.crs, "units": "m", "mesh": "mesh.ply",
        "buildings": [b.to_json() for b in scene.buildings],
    }
    if scene.has_porous or scene.transmission != DEFAULT_TRANSMISSION:
        manifest["vegetation"] = {"transmission": scene.transmission}
    write_json(folder / "scene.json", manifest, error=SceneError)
    return folder
