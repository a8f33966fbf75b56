"""Import real CityJSON city models (LoD1/LoD2/…) into a QuakeScan scene.

`import_cityjson` reads a CityJSON 1.0, 1.1 or 2.0 file and returns a `quakescan.formats.scene.Scene`
(write it with `quakescan.formats.scene.write_scene`):

- one building ID (1..n, in the order of the sorted CityJSON object ids) per `Building`;
  its `BuildingPart`s and `BuildingInstallation`s (also nested ones) are merged into it; a
  `BuildingPart` whose parent is absent from the file becomes a building of its own;
- every polygon (outer ring + holes) is triangulated with earcut in its own plane, keeping
  the outer ring's orientation (CityJSON surfaces face outwards);
- the per-face `surface` label comes from the CityJSON semantics, or from the face normal
  where a surface carries none;
- a terrain TIN (building_id 0, surface "ground") is laid through the bottoms of the
  buildings, one patch per cluster of buildings out to the cluster's bounding box plus a
  margin (`building_clusters`): scattered buildings do not make terrain of the whole extent;
- a building whose walls leave its shell open (wall polygons missing from the model, a
  party wall kept only above a neighbour the file does not hold) is closed by vertical walls there (`quakescan.formats.shell`), so that no
  sensor sees the terrain inside it.

Coordinates are float64 relative to the scene origin (the file's `transform.translate`), so
projected coordinates of millions of metres keep their millimetres: nothing here goes through
float32.
"""
from __future__ import annotations

import logging
import math
import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import mapbox_earcut
import numpy as np
from scipy.spatial import Delaunay, QhullError

from ..errors import SceneError, read_json_file
from .shell import close_open_edges
from .scene import (DEGENERATE_AREA_M2, GROUND, INTERIOR, MATERIALS, ROOF, WALL, Building, Scene, check_crs,
                    triangle_areas)

__all__ = ["import_cityjson", "parse_reference_system", "SUPPORTED_VERSIONS"]

log = logging.getLogger(__name__)

SUPPORTED_VERSIONS = ("1.0", "1.1", "2.0")
# Bumped whenever the same file imports into another scene (caches of imported scenes key on
# it). 2: open shells closed (`quakescan.formats.shell`); 3: slivers along an outline no
# longer hide an open edge; 4: nor do walls rising from a roof edge.
IMPORT_VERSION = 4

# Storey height used to turn a building height into a storey count (typical 2.8–3.2 m).
STOREY_HEIGHT_M = 3.0
# Without GroundSurface semantics, a building stands on its vertices this close to its lowest one.
BASE_BAND_M = 0.5
# GroundSurface vertices higher than this above the building's lowest vertex are the bottom of
# a raised part (over a passage, on a roof), not where the building meets the terrain.
GROUND_BAND_M = STOREY_HEIGHT_M
# Wall-bottom edges are sampled this densely for the terrain TIN, so that the (unconstrained)
# Delaunay triangulation follows the footprints instead of cutting across them.
TERRAIN_EDGE_SPACING_M = 2.0
# Terrain points closer than this in x/y are one point (party walls, shared corners).
TERRAIN_MERGE_M = 1e-3
# |nz| above which a face without semantics is a roof (facing up) or a ground/bottom face.
NORMAL_NZ_THRESHOLD = 0.3
# Triangles of a polygon whose normal is further than this from the polygon's are slivers.
SLIVER_MAX_ANGLE_DEG = 60.0

# Objects merged into their parent building. Rooms, storeys, units and furniture (CityJSON
# 2.0) are interior; constructive elements repeat the shell: neither is seen by a UAV.
MERGED_CHILD_TYPES = ("BuildingPart", "BuildingInstallation")

# How deep the list of surfaces sits in `boundaries` (and in `semantics.values`).
_SURFACE_DEPTH = {"MultiSurface": 1, "CompositeSurface": 1, "Solid": 2, "MultiSolid": 3, "CompositeSolid": 3}

# Semantic surface type → face `surface` code. Types not listed (Window, Door, extension types
# "+…", none at all) are classified by the face normal, because they lie in whichever wall or
# roof holds them.
_SEMANTIC_SURFACE = {
    "RoofSurface": ROOF,
    "WallSurface": WALL,
    "GroundSurface": GROUND,
    # OuterCeilingSurface: the exterior underside of a projecting storey or an arcade. It is
    # part of the building's envelope, not the footprint ("ground" would put it into the
    # building's base) and not a roof (it faces down, sheds no weather and would inflate roof
    # areas and roof-damage features), so it counts as wall: "envelope that is neither roof
    # nor footprint".
    "OuterCeilingSurface": WALL,
    # OuterFloorSurface: an exterior floor open to the sky (balcony, terrace on a lower
    # storey). A UAV sees it from above exactly like a flat roof, and roof damage (debris on
    # it, collapse) shows there, so it counts as roof.
    "OuterFloorSurface": ROOF,
    "InteriorWallSurface": INTERIOR,
    "CeilingSurface": INTERIOR,
    "FloorSurface": INTERIOR,
}
# ClosureSurfaces are virtual: they close a volume where no physical surface exists (open
# carport sides, the interface between building parts). A laser beam passes through them, so
# they are dropped rather than scanned.
_DROPPED_SEMANTICS = ("ClosureSurface",)

_EPSG_PATTERNS = (
    re.compile(r"^https?://www\.opengis\.net/def/crs/EPSG/[^/]*/(\d+)/?$", re.IGNORECASE),
    re.compile(r"^urn:ogc:def:crs:EPSG:[^:]*:(\d+)$", re.IGNORECASE),
    re.compile(r"^EPSG:{1,2}(\d+)$", re.IGNORECASE),
)


# --------------------------------------------------------------------------- public API


def import_cityjson(path: str | os.PathLike, lod: str | None = None, terrain_margin: float = 20.0,
                    crs: str | None = None, material: str = "masonry") -> Scene:
    """Read a CityJSON city model into a scene of labelled buildings on a terrain TIN.

    Parameters
    ----------
    path : str or PathLike
        CityJSON file (version 1.0, 1.1 or 2.0).
    lod : str, optional
        Level of detail to use, e.g. "2" or "2.2". "2" also accepts the highest "2.x" of an
        object that has no plain "2". Default: the highest LoD of each object.
    crs : str, optional
        The CRS ("EPSG:NNNN") of a file whose metadata names none (or names one that is not an
        EPSG code). When the file names an EPSG code, `crs` must be the same.
    material : str
        Material of every imported building (`quakescan.formats.scene.MATERIALS`), for the damage patterns
        and the scanner's reflectance.
    terrain_margin : float
        How far (m) the terrain reaches beyond the x/y bounding box of each cluster of
        buildings (buildings closer than twice this are one cluster).

    Returns
    -------
    Scene
        Buildings with IDs 1..n (sorted by CityJSON id; `extra["source_id"]` keeps the id),
        vertices (n, 3) float64 relative to `origin` (the file's transform translate), faces
        (m, 3), `face_building` (m,), `face_surface` (m,), terrain faces with building 0.

    Raises
    ------
    SceneError
        The file is missing, not JSON, not CityJSON, of an unsupported version, has no
        buildings, no building geometry at `lod`, or refers to vertices it does not have.
    """
    path = Path(path)
    if isinstance(terrain_margin, bool) or not (isinstance(terrain_margin, (int, float))
                                                and math.isfinite(terrain_margin) and 0 <= terrain_margin <= 10_000):
        raise SceneError(f"terrain margin (--buffer) must be a number of metres in [0, 10000], got {terrain_margin!r}")
    if material not in MATERIALS:
        raise SceneError(f"material (--material) must be one of {MATERIALS}, got {material!r}")
    want = None if lod is None else _normalise_lod(lod)
    doc = _load(path)
    scene_crs = _scene_crs(path, doc, crs)
    verts, origin = _vertices(path, doc)
    objects = doc.get("CityObjects")
    if not isinstance(objects, dict):
        raise SceneError(f"{path}: 'CityObjects' must be a JSON object")
    groups = _group_buildings(path, objects)
    counts: Counter = Counter()
    meshes = [_building_mesh(path, root, members, objects, verts, want, counts)
              for root, members in sorted(groups.items())]
    meshes = _keep_buildings_with_faces(path, meshes, objects, want)
    scene = _assemble(meshes, objects, verts, origin, terrain_margin, counts)
    scene.crs = scene_crs
    for b in scene.buildings:
        b.material = material
    _log_summary(path, scene, counts)
    return scene


def parse_reference_system(value, warn: bool = True) -> str | None:
    """CityJSON `metadata.referenceSystem` → "EPSG:NNNN" (None when absent or not EPSG).

    Accepts the CityJSON 1.1/2.0 form "https://www.opengis.net/def/crs/EPSG/0/2056", the
    1.0 form "urn:ogc:def:crs:EPSG::7415" and a plain "EPSG:2056".
    """
    if value is None:
        return None
    text = str(value).strip()
    for pattern in _EPSG_PATTERNS:
        m = pattern.match(text)
        if m:
            return f"EPSG:{int(m.group(1))}"
    if warn:
        log.warning("referenceSystem %r is not an EPSG code; the scene gets no CRS", value)
    return None


def _scene_crs(path: Path, doc: dict, given: str | None) -> str | None:
    """The scene's CRS: the file's EPSG code, else `given` (--crs); refuses a disagreement, a
    file's reference system that is not an EPSG code (unless `given`), and a CRS PROJ does not
    know or that is not in metres."""
    metadata = doc.get("metadata")
    raw = metadata.get("referenceSystem") if isinstance(metadata, dict) else None
    wanted = None
    if given is not None:
        wanted = parse_reference_system(given, warn=False)
        if wanted is None:
            raise SceneError(f"--crs {given!r}: expected an EPSG code such as 'EPSG:2056'")
    from_file = parse_reference_system(raw, warn=False) if raw is not None else None
    if raw is not None and from_file is None:
        if wanted is None:
            raise SceneError(f"{path}: metadata.referenceSystem {raw!r} is not an EPSG code QuakeScan can read; "
                             "give the CRS with --crs EPSG:NNNN")
        log.warning("%s: referenceSystem %r is not an EPSG code; using --crs %s", path, raw, wanted)
    if from_file is not None and wanted is not None and from_file != wanted:
        raise SceneError(f"{path}: the file names its CRS {from_file} ({raw!r}) but --crs is {given!r}; "
                         "leave --crs out, or fix the file")
    chosen = from_file or wanted
    check_crs(chosen, str(path) if from_file else f"--crs {given}")
    return chosen


# --------------------------------------------------------------------------- file, vertices


def _load(path: Path) -> dict:
    """Read and check the top level of a CityJSON file."""
    doc = read_json_file(path, "CityJSON file", SceneError)  # refuses a missing or special file too
    if not isinstance(doc, dict) or doc.get("type") != "CityJSON":
        found = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise SceneError(f"{path}: not a CityJSON file (type is {found!r}, expected 'CityJSON')")
    version = str(doc.get("version"))
    m = re.match(r"^(\d+\.\d+)", version)
    if not m or m.group(1) not in SUPPORTED_VERSIONS:
        raise SceneError(f"{path}: CityJSON version {doc.get('version')!r} is not supported "
                         f"(supported: {', '.join(SUPPORTED_VERSIONS)})")
    return doc


def _vertices(path: Path, doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """Vertices relative to the scene origin, and the origin.

    Returns
    -------
    verts : (n, 3) float64
        int * scale with a transform (the translate is the origin), else v - origin.
    origin : (3,) float64
        transform.translate, or the floor of the vertices' min corner.
    """
    try:
        raw = np.array(doc.get("vertices", []), dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{path}: 'vertices' must be a list of [x, y, z] numbers") from None
    if raw.size == 0:
        raw = raw.reshape(0, 3)
    if raw.ndim != 2 or raw.shape[1] != 3 or not np.isfinite(raw).all():
        raise SceneError(f"{path}: 'vertices' must be a list of [x, y, z] finite numbers")
    transform = doc.get("transform")
    if transform is None:
        # CityJSON 1.0 stores real coordinates when it has no transform; 1.1 and 2.0 always
        # store integers scaled by one. Integers without it have no known scale (mm? cm?):
        # reading them as metres made buildings 1000 times too large.
        version = str(doc.get("version"))
        if not version.startswith("1.0"):
            if len(raw) and np.all(raw == np.round(raw)):
                raise SceneError(f"{path}: CityJSON {version} requires 'transform' (its vertices are integers "
                                 "scaled by transform.scale) and this file has none; its scale is unknown. "
                                 "Add the transform (scale and translate) to the file")
            log.warning("%s: CityJSON %s without 'transform' (required since 1.1); its vertices are not "
                        "integers, so they are read as coordinates in metres, as CityJSON 1.0 stores them",
                        path, version)
        origin = np.floor(raw.min(axis=0)) if len(raw) else np.zeros(3)
        return raw - origin, origin
    try:
        scale = np.array(transform["scale"], dtype=np.float64).reshape(3)
        translate = np.array(transform["translate"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise SceneError(f"{path}: 'transform' must have 'scale' and 'translate' with 3 numbers each") from None
    # Python's JSON reads NaN and Infinity, which would make every vertex NaN (or one point)
    for name, values in (("scale", scale), ("translate", translate)):
        if not np.isfinite(values).all():
            raise SceneError(f"{path}: transform.{name} {values.tolist()} holds a value that is not a finite "
                             "number; fix the file's transform")
    if np.any(scale == 0):
        raise SceneError(f"{path}: transform.scale {scale.tolist()} holds a zero: every vertex would collapse "
                         "onto one plane; fix the file's transform")
    # Integers below 2**53 are exact in float64, so int * scale is as exact as float64 allows
    # and the large translate never touches the mesh coordinates.
    return raw * scale, translate


# --------------------------------------------------------------------------- buildings


def _group_buildings(path: Path, objects: dict) -> dict[str, list[str]]:
    """Map each building's root CityJSON id → its member ids (root first, then parts).

    A `Building` is always a root. A merged-type object (BuildingPart, BuildingInstallation)
    belongs to the root reached by following its parents; a BuildingPart that reaches no
    Building (its parents are absent) is a root itself.
    """
    parent = _parent_map(objects)
    groups: dict[str, list[str]] = {oid: [oid] for oid, o in objects.items() if _type(o) == "Building"}
    orphans = 0
    for oid in sorted(objects):
        if _type(objects[oid]) not in MERGED_CHILD_TYPES:
            continue
        root = _root(oid, objects, parent)
        if _type(objects[root]) == "Building":
            groups[root].append(oid)
        elif _type(objects[root]) == "BuildingPart":  # a part whose parents are absent
            group = groups.setdefault(root, [root])
            if oid != root:
                group.append(oid)
        else:
            orphans += 1
    if orphans:
        log.warning("%s: %d BuildingInstallation objects belong to no building; ignored", path, orphans)
    if not groups:
        kinds = sorted(Counter(_type(o) for o in objects.values()).items())
        raise SceneError(f"{path}: no Building objects (CityObjects has {kinds or 'nothing'})")
    return groups


def _type(obj) -> str | None:
    return obj.get("type") if isinstance(obj, dict) else None


def _parent_map(objects: dict) -> dict[str, str]:
    """child id → parent id for merged-type children, from `parents` and from `children`.

    Only Buildings and merged types count as parents: a CityObjectGroup also lists its
    members as `children` (CityJSON 1.1) but does not own them.
    """
    owner_types = ("Building",) + MERGED_CHILD_TYPES
    parent: dict[str, str] = {}
    for oid in sorted(objects):
        obj = objects[oid]
        if _type(obj) in MERGED_CHILD_TYPES:
            for p in obj.get("parents") or []:
                if p in objects and _type(objects[p]) in owner_types:
                    parent.setdefault(oid, p)
                    break
    for oid in sorted(objects):
        obj = objects[oid]
        if _type(obj) in owner_types:
            for c in obj.get("children") or []:
                if c in objects and _type(objects[c]) in MERGED_CHILD_TYPES:
                    parent.setdefault(c, oid)
    return parent


def _root(oid: str, objects: dict, parent: dict[str, str]) -> str:
    """Follow parents up to a Building or to an object without parent (cycles stop too)."""
    seen = {oid}
    while _type(objects[oid]) != "Building" and oid in parent and parent[oid] not in seen:
        oid = parent[oid]
        seen.add(oid)
    return oid


@dataclass
class _BuildingMesh:
    """One building's triangles, still indexing the file's vertex array."""

    source_id: str
    tris: np.ndarray  # (k, 3) int64, indices into the file's vertices
    surface: np.ndarray  # (k,) uint8 surface codes
    ground_semantic: np.ndarray  # (k,) bool, from a GroundSurface
    lods: set = field(default_factory=set)  # LoDs of the geometries used


def _building_mesh(path, root, members, objects, verts, want, counts) -> _BuildingMesh:
    """Triangulate the chosen geometry of every member object of one building."""
    tris, surf, ground, lods = [], [], [], set()
    for oid in members:
        geom = _pick_geometry(objects[oid], want, counts)
        if geom is None:
            continue
        lods.add(_normalise_lod(geom.get("lod")))
        t, s, g = _triangulate_geometry(path, oid, geom, verts, counts)
        tris.append(t)
        surf.append(s)
        ground.append(g)
    if not tris:
        return _BuildingMesh(root, np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, bool), lods)
    return _BuildingMesh(root, np.concatenate(tris), np.concatenate(surf), np.concatenate(ground), lods)


def _keep_buildings_with_faces(path, meshes, objects, want) -> list[_BuildingMesh]:
    """Drop (with a warning) buildings that ended up without faces; raise when none is left."""
    kept = [m for m in meshes if len(m.tris)]
    no_geometry = [m.source_id for m in meshes if not m.lods]
    all_degenerate = [m.source_id for m in meshes if m.lods and not len(m.tris)]
    if not kept:
        available = sorted({_normalise_lod(g["lod"]) for o in objects.values() if isinstance(o, dict)
                            for g in (o.get("geometry") or []) if isinstance(g, dict) and "lod" in g},
                           key=_lod_key)
        if want is not None and len(no_geometry) == len(meshes):
            raise SceneError(f"{path}: no building has geometry at LoD {want!r}; the file has LoDs "
                             f"{available or 'none'}")
        if len(no_geometry) == len(meshes):
            raise SceneError(f"{path}: none of the {len(meshes)} buildings has surface geometry "
                             f"(LoDs in the file: {available or 'none'})")
        raise SceneError(f"{path}: every polygon of every building is degenerate (fewer than 3 distinct "
                         "vertices or zero area)")
    if no_geometry:
        at = f"at LoD {want!r}" if want is not None else "at all"
        log.warning("%s: %d buildings have no surface geometry %s and are left out (first: %s)",
                    path, len(no_geometry), at, no_geometry[0])
    if all_degenerate:
        log.warning("%s: %d buildings have only degenerate polygons and are left out (first: %s)",
                    path, len(all_degenerate), all_degenerate[0])
    return kept


# --------------------------------------------------------------------------- LoD


def _normalise_lod(value) -> str:
    """LoD as a string: 2 → "2", 2.0 → "2", "2.2" → "2.2" (CityJSON 1.0 used numbers)."""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, float)):
        return str(int(value)) if float(value).is_integer() else repr(float(value))
    return str(value).strip()


def _lod_key(lod: str) -> tuple:
    """Sort key: "1" < "1.3" < "2" < "2.2" < "3"; unparseable LoDs sort first."""
    try:
        return tuple(int(p) for p in lod.split("."))
    except ValueError:
        return (-1,)


def _pick_geometry(obj: dict, want: str | None, counts: Counter) -> dict | None:
    """The object's surface geometry at LoD `want` (or its highest LoD); None if it has none.

    `want` "2" takes an exact "2" first, else the highest "2.x"; "2.2" takes only "2.2".
    """
    geoms = [g for g in (obj.get("geometry") or []) if isinstance(g, dict)]
    usable = [g for g in geoms if g.get("type") in _SURFACE_DEPTH]
    counts["unsupported_geometries"] += len(geoms) - len(usable)
    if want is not None:
        exact = [g for g in usable if _normalise_lod(g.get("lod")) == want]
        if not exact and "." not in want:
            exact = [g for g in usable if _normalise_lod(g.get("lod")).split(".")[0] == want]
        usable = exact
    if not usable:
        return None
    best = max(_lod_key(_normalise_lod(g.get("lod"))) for g in usable)
    at_best = [g for g in usable if _lod_key(_normalise_lod(g.get("lod"))) == best]
    # Two geometries at one LoD would put two shells on top of each other; keep the first.
    counts["extra_geometries_ignored"] += len(at_best) - 1
    return at_best[0]


# --------------------------------------------------------------------------- triangulation


def _iter_surfaces(boundaries, values, depth: int):
    """Yield (rings, semantic index or None) for every surface of a boundary tree."""
    if depth == 0:
        yield boundaries, values if isinstance(values, int) and not isinstance(values, bool) else None
        return
    if not isinstance(boundaries, list):
        raise TypeError("boundaries")
    for i, b in enumerate(boundaries):
        v = values[i] if isinstance(values, list) and i < len(values) else None
        yield from _iter_surfaces(b, v, depth - 1)


def _triangulate_geometry(path, oid, geom, verts, counts):
    """Triangles, surface codes and GroundSurface flags of one CityJSON geometry.

    Returns
    -------
    tris : (k, 3) int64
        Indices into `verts`, oriented like the polygons' outer rings.
    surface : (k,) uint8
    ground_semantic : (k,) bool
    """
    sem = geom.get("semantics") if isinstance(geom.get("semantics"), dict) else {}
    sem_surfaces = sem.get("surfaces") or []
    try:
        surfaces = list(_iter_surfaces(geom.get("boundaries"), sem.get("values"), _SURFACE_DEPTH[geom["type"]]))
    except TypeError:
        raise SceneError(f"{path}: CityObject {oid!r}: malformed {geom['type']} boundaries") from None
    tris, normals, sem_types = [], [], []
    for rings, sem_index in surfaces:
        sem_type = None
        if sem_index is not None and 0 <= sem_index < len(sem_surfaces) and isinstance(sem_surfaces[sem_index], dict):
            sem_type = sem_surfaces[sem_index].get("type")
        if sem_type in _DROPPED_SEMANTICS:
            counts["closure_surfaces_dropped"] += 1
            continue
        t, normal = _triangulate_polygon(verts, _ring_indices(path, oid, rings, len(verts)), counts)
        if len(t):
            tris.append(t)
            normals.append(np.broadcast_to(normal, t.shape))
            sem_types += [sem_type] * len(t)
    if not tris:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, bool)
    # Orientation, degeneracy and labels for the whole geometry at once: numpy per polygon
    # would cost more in call overhead than in arithmetic.
    tris, keep = _orient_and_filter(verts, np.concatenate(tris), np.concatenate(normals), counts)
    sem_types = [t for t, k in zip(sem_types, keep) if k]
    surface = _surface_codes(sem_types, face_normals(verts, tris))
    ground = np.array([t == "GroundSurface" for t in sem_types], dtype=bool)
    return tris, surface, ground


def _ring_indices(path, oid, rings, n_vertices: int) -> list[np.ndarray]:
    """Rings of one surface as int64 arrays, checked against the vertex count."""
    if not isinstance(rings, list):
        raise SceneError(f"{path}: CityObject {oid!r}: a surface must be a list of rings, got {rings!r}")
    out = []
    for ring in rings:
        try:
            idx = np.array(ring, dtype=np.int64).reshape(-1)
        except (TypeError, ValueError):
            raise SceneError(f"{path}: CityObject {oid!r}: a ring must be a list of vertex indices, "
                             f"got {ring!r}") from None
        bad = (idx < 0) | (idx >= n_vertices)
        if bad.any():
            raise SceneError(f"{path}: CityObject {oid!r} refers to vertex {int(idx[bad][0])} but the file "
                             f"has only {n_vertices} vertices")
        out.append(idx)
    return out


def _clean_ring(verts: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Drop consecutive repeated vertices (same position), including a closing copy of the first."""
    if len(ring) == 0:
        return ring
    pts = verts[ring]
    keep = np.any(pts != pts[np.arange(-1, len(pts) - 1)], axis=1)  # compare with the previous vertex
    return ring[keep]


def newell_normal(points: np.ndarray) -> np.ndarray:
    """Newell normal of a ring: (k, 3) points → (3,) vector of length 2 × area.

    Points are taken relative to the first one, so rings at projected coordinates of
    millions of metres keep their precision.
    """
    rel = points - points[0]
    x, y, z = rel.T
    xn, yn, zn = np.concatenate([rel[1:], rel[:1]]).T  # the next vertex, cyclically
    return np.array([np.dot(y, zn) - np.dot(z, yn), np.dot(z, xn) - np.dot(x, zn), np.dot(x, yn) - np.dot(y, xn)])


def _cross3(a, b) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~20 µs of overhead per call)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal u, v with u × v = normal / |normal|, so a ring counter-clockwise
    around the normal stays counter-clockwise in (u, v)."""
    n = normal / math.sqrt(normal @ normal)
    helper = np.zeros(3)
    helper[np.argmin(np.abs(n))] = 1.0
    u = _cross3(helper, n)
    u /= math.sqrt(u @ u)
    return np.array([u, _cross3(n, u)])


def _triangulate_polygon(verts: np.ndarray, rings: list[np.ndarray], counts: Counter):
    """Earcut one polygon (outer ring + holes) in its plane.

    Parameters
    ----------
    verts : (n, 3) float64
    rings : list of (k_i,) int64 vertex indices; the first is the outer ring.

    Returns
    -------
    tris : (t, 3) int64
        Triangles in earcut's winding (see `_orient_and_filter`); (0, 3) for a dropped polygon.
    normal : (3,) float64
        The outer ring's Newell normal.
    """
    empty = np.zeros((0, 3), np.int64), np.zeros(3)
    if not rings:
        counts["short_polygons_dropped"] += 1
        return empty
    outer = _clean_ring(verts, rings[0])
    if len(np.unique(outer)) < 3:
        counts["short_polygons_dropped"] += 1
        return empty
    normal = newell_normal(verts[outer])
    if 0.5 * math.sqrt(normal @ normal) <= DEGENERATE_AREA_M2:
        counts["degenerate_polygons_dropped"] += 1
        return empty
    holes = [_clean_ring(verts, r) for r in rings[1:]]
    counts["holes_dropped"] += sum(len(np.unique(h)) < 3 for h in holes)
    all_rings = [outer] + [h for h in holes if len(np.unique(h)) >= 3]
    if len(all_rings) == 1 and len(outer) == 3:
        return outer.reshape(1, 3), normal  # already a triangle
    index = np.concatenate(all_rings)
    # Relative to the ring's first vertex: small float64 numbers for earcut.
    xy = (verts[index] - verts[outer[0]]) @ _plane_basis(normal).T
    ends = np.cumsum([len(r) for r in all_rings]).astype(np.uint32)
    local = np.asarray(mapbox_earcut.triangulate_float64(np.ascontiguousarray(xy), ends), dtype=np.int64)
    if not len(local):
        counts["earcut_failed_polygons"] += 1
        return empty
    return index[local.reshape(-1, 3)], normal


def _orient_and_filter(verts, tris, normals, counts):
    """Flip triangles whose normal disagrees with their polygon's Newell normal (earcut's
    winding is its own); drop zero-area ones and out-of-plane slivers.

    Slivers: where a ring has nearly collinear vertices (a wall's foot with mm-rounded
    corners), earcut may cut an ear of three of them. In the polygon's plane it has no area,
    in 3D its normal is set by the millimetre noise and can point anywhere (a downward
    "wall"). Dropping triangles more than SLIVER_MAX_ANGLE_DEG off the polygon's plane loses
    at most half their (tiny) area in that plane.

    Parameters
    ----------
    tris : (k, 3) int64
    normals : (k, 3) float64, the owning polygon's normal per triangle.

    Returns
    -------
    tris : (j, 3) int64
    keep : (k,) bool, which input triangles survived.
    """
    a = verts[tris[:, 0]]
    n = np.cross(verts[tris[:, 1]] - a, verts[tris[:, 2]] - a)
    dot = np.einsum("ij,ij->i", n, normals)
    flip = dot < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, [0, 2, 1]]
    area = triangle_areas(verts, tris)
    degenerate = area <= DEGENERATE_AREA_M2
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(dot) / (np.linalg.norm(n, axis=1) * np.linalg.norm(normals, axis=1))
    sliver = ~degenerate & (cos < math.cos(math.radians(SLIVER_MAX_ANGLE_DEG)))
    counts["degenerate_triangles_dropped"] += int(degenerate.sum())
    counts["sliver_triangles_dropped"] += int(sliver.sum())
    keep = ~degenerate & ~sliver
    return tris[keep], keep


def _surface_codes(sem_types: list, normals: np.ndarray) -> np.ndarray:
    """(k,) uint8 surface codes: from each triangle's semantic type, else from its normal.

    Parameters
    ----------
    sem_types : list of k semantic type names or None
    normals : (k, 3) unit normals
    """
    codes = classify_by_normal(normals)
    for i, t in enumerate(sem_types):
        if t in _SEMANTIC_SURFACE:
            codes[i] = _SEMANTIC_SURFACE[t]
    return codes


def face_normals(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(k, 3) unit normals of (k, 3) triangles (right-hand rule)."""
    a = verts[tris[:, 0]]
    n = np.cross(verts[tris[:, 1]] - a, verts[tris[:, 2]] - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def classify_by_normal(normals: np.ndarray) -> np.ndarray:
    """(k, 3) unit normals → (k,) uint8: roof when nz > 0.3, ground when nz < -0.3, else wall."""
    nz = normals[:, 2]
    codes = np.full(len(normals), WALL, np.uint8)
    codes[nz > NORMAL_NZ_THRESHOLD] = ROOF
    codes[nz < -NORMAL_NZ_THRESHOLD] = GROUND
    return codes


# --------------------------------------------------------------------------- storeys


def _estimate_storeys(attributes: dict, verts: np.ndarray, mesh: _BuildingMesh) -> int:
    """Storeys from `storeysAboveGround`, else `measuredHeight`, else roof top − ground / 3 m."""
    attributes = attributes if isinstance(attributes, dict) else {}
    storeys = attributes.get("storeysAboveGround")
    if isinstance(storeys, int) and not isinstance(storeys, bool) and storeys > 0:
        return storeys
    height = attributes.get("measuredHeight")
    if not (isinstance(height, (int, float)) and not isinstance(height, bool)
            and math.isfinite(height) and height > 0):
        roof = mesh.tris[mesh.surface == ROOF]
        base = mesh.tris[mesh.surface == GROUND]
        z_top = verts[(roof if len(roof) else mesh.tris).ravel(), 2].max()
        z_base = verts[(base if len(base) else mesh.tris).ravel(), 2].min()
        height = z_top - z_base
    return max(1, int(round(height / STOREY_HEIGHT_M)))


# --------------------------------------------------------------------------- terrain


def _base_points(verts: np.ndarray, mesh: _BuildingMesh) -> np.ndarray:
    """Where the building meets the ground: its base vertices plus its base edges sampled
    every TERRAIN_EDGE_SPACING_M.

    Base vertices are the GroundSurface vertices within GROUND_BAND_M of the building's lowest
    vertex, or, without GroundSurface semantics, all vertices within BASE_BAND_M of it. Base
    edges are triangle edges with both ends at base vertices (wall bottoms, footprint edges).

    Returns
    -------
    (p, 3) float64, relative to the scene origin.
    """
    used = np.unique(mesh.tris)
    z_min = verts[used, 2].min()
    ground = np.unique(mesh.tris[mesh.ground_semantic])
    ground = ground[verts[ground, 2] <= z_min + GROUND_BAND_M]
    base = ground if len(ground) else used[verts[used, 2] <= z_min + BASE_BAND_M]
    is_base = np.zeros(len(verts), bool)
    is_base[base] = True
    edges = np.concatenate([mesh.tris[:, [0, 1]], mesh.tris[:, [1, 2]], mesh.tris[:, [2, 0]]])
    edges = np.unique(np.sort(edges[is_base[edges].all(axis=1)], axis=1), axis=0)
    return np.concatenate([verts[base], _densify(verts[edges[:, 0]], verts[edges[:, 1]])])


def _densify(a: np.ndarray, b: np.ndarray, spacing: float = TERRAIN_EDGE_SPACING_M) -> np.ndarray:
    """Interior points every <= `spacing` m along segments a→b ((e, 3) each) → (q, 3)."""
    if not len(a):
        return np.zeros((0, 3))
    steps = np.ceil(np.linalg.norm(b - a, axis=1) / spacing).astype(np.int64)  # segments per edge
    n_inner = np.maximum(steps - 1, 0)
    edge = np.repeat(np.arange(len(a)), n_inner)
    # k-th interior point of its edge: 1..steps-1
    k = np.arange(len(edge)) - np.repeat(np.cumsum(n_inner) - n_inner, n_inner) + 1
    t = (k / steps[edge])[:, None]
    return a[edge] + t * (b[edge] - a[edge])


def _merge_xy(points: np.ndarray) -> np.ndarray:
    """One point per TERRAIN_MERGE_M x/y cell, keeping the highest z.

    The highest, because where two buildings share a corner at different base heights the
    terrain then hides the lower wall's foot instead of leaving a gap under the upper one.
    """
    keys = np.floor(points[:, :2] / TERRAIN_MERGE_M).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    z = np.full(len(first), -np.inf)
    np.maximum.at(z, inverse, points[:, 2])
    return np.column_stack([points[first, :2], z])


def _terrain(base: np.ndarray, xy_min: np.ndarray, xy_max: np.ndarray, margin: float):
    """Delaunay TIN through the base points and the margin-extended bounding box corners.

    Parameters
    ----------
    base : (p, 3) float64
        Points where buildings meet the ground.
    xy_min, xy_max : (2,) float64
        Bounding box of the buildings.

    Returns
    -------
    verts : (t, 3) float64
    tris : (m, 3) int64, counter-clockwise seen from above, none degenerate.
    """
    lo, hi = xy_min - margin, xy_max + margin
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    nearest = np.argmin(((corners[:, None, :] - base[None, :, :2]) ** 2).sum(axis=2), axis=1)
    points = _merge_xy(np.concatenate([base, np.column_stack([corners, base[nearest, 2]])]))
    try:
        tris = Delaunay(points[:, :2]).simplices.astype(np.int64)
    except QhullError as e:
        log.warning("terrain TIN failed (%s); the scene has no terrain", str(e).splitlines()[0])
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    a = points[tris[:, 0], :2]
    cross = np.cross(points[tris[:, 1], :2] - a, points[tris[:, 2], :2] - a)
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    tris = tris[triangle_areas(points, tris) > DEGENERATE_AREA_M2]
    return _compact(points, tris)


def building_clusters(boxes: np.ndarray, margin: float) -> np.ndarray:
    """Cluster label (0..k-1) of each building: buildings whose x/y boxes, grown by `margin`,
    overlap belong together, and so do clusters whose grown boxes overlap (so that no two
    terrain patches overlap).

    boxes : (n, 4) float64, x0 y0 x1 y1 per building. A city model's scattered buildings
    then get a terrain patch each instead of one TIN over the whole extent: 49 buildings
    spread over 9 × 10 km need a few hectares, not 90 km².
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    def overlapping_pairs(b):
        grown = b + np.array([-margin, -margin, margin, margin])
        centres = 0.5 * (grown[:, :2] + grown[:, 2:])
        reach = 0.5 * np.hypot(grown[:, 2] - grown[:, 0], grown[:, 3] - grown[:, 1])
        pairs = cKDTree(centres).query_pairs(2 * reach.max() + 1e-9, output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        hit = ((grown[i, 0] <= grown[j, 2]) & (grown[j, 0] <= grown[i, 2]) & (grown[i, 1] <= grown[j, 3])
               & (grown[j, 1] <= grown[i, 3]))
        return i[hit], j[hit]

    labels = np.arange(len(boxes))
    current = boxes
    while True:
        i, j = overlapping_pairs(current)
        if not len(i):
            return labels
        k, merged = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(current),) * 2),
                                         directed=False)
        labels = merged[labels]
        current = np.array([np.concatenate([current[merged == c, :2].min(axis=0), current[merged == c, 2:].max(axis=0)])
                            for c in range(k)])


def _compact(verts: np.ndarray, tris: np.ndarray):
    """Keep only the vertices the triangles use: → ((u, 3) vertices, (m, 3) reindexed tris)."""
    used, inverse = np.unique(tris, return_inverse=True)
    return verts[used], inverse.reshape(tris.shape).astype(np.int64)


# --------------------------------------------------------------------------- assembly


def _assemble(meshes, objects, verts, origin, margin, counts) -> Scene:
    """Buildings (each with its own copy of its vertices, so damage patterns can move one
    building's vertices without dragging a neighbour's) + the terrain, as one Scene."""
    parts_v, parts_f, parts_b, parts_s, buildings, base = [], [], [], [], [], []
    n = 0
    for bid, mesh in enumerate(meshes, start=1):
        v, f = _compact(verts, mesh.tris)
        v, f, surface, closing_m2 = close_open_edges(v, f, mesh.surface)
        if closing_m2:
            counts["buildings_closed"] += 1
            counts["closing_wall_m2"] += int(round(closing_m2))
        parts_v.append(v)
        parts_f.append(f + n)
        parts_b.append(np.full(len(f), bid, np.int32))
        parts_s.append(surface)
        n += len(v)
        base.append(_base_points(verts, mesh))
        storeys = _estimate_storeys(objects[mesh.source_id].get("attributes"), verts, mesh)
        buildings.append(Building(bid, grade=0, material="masonry", storeys=storeys, typology="cityjson",
                                  seed=bid, extra={"source_id": mesh.source_id}))
    boxes = np.array([np.concatenate([v[:, :2].min(axis=0), v[:, :2].max(axis=0)]) for v in parts_v])
    labels = building_clusters(boxes, margin)
    tv_parts, tf_parts, n_tv = [], [], 0
    for k in range(int(labels.max()) + 1):
        members = np.flatnonzero(labels == k)
        tv, tf = _terrain(np.concatenate([base[i] for i in members]), boxes[members, :2].min(axis=0),
                          boxes[members, 2:].max(axis=0), margin)
        tv_parts.append(tv)
        tf_parts.append(tf + n_tv)
        n_tv += len(tv)
    tv, tf = np.concatenate(tv_parts), np.concatenate(tf_parts)
    counts["terrain_triangles"] = len(tf)
    counts["terrain_patches"] = int(labels.max()) + 1
    # Terrain first, like the synthetic scenes.
    vertices = np.concatenate([tv] + parts_v)
    faces = np.concatenate([tf] + [f + len(tv) for f in parts_f])
    face_building = np.concatenate([np.zeros(len(tf), np.int32)] + parts_b)
    face_surface = np.concatenate([np.full(len(tf), GROUND, np.uint8)] + parts_s)
    return Scene(vertices, faces, face_building, face_surface, buildings, origin=np.asarray(origin, np.float64))


def _log_summary(path: Path, scene: Scene, counts: Counter) -> None:
    dropped = {k: v for k, v in sorted(counts.items()) if v and k != "terrain_triangles"}
    log.info("%s: %d buildings, %d building triangles, %d terrain triangles, crs %s%s", path,
             len(scene.buildings), int((scene.face_building > 0).sum()), counts["terrain_triangles"],
             scene.crs, "; " + ", ".join(f"{k} {v}" for k, v in dropped.items()) if dropped else "")
