"""The scene as every simulated sensor sees it: the Embree ray caster with its face labels,
the ground level a flight is planned from, and the check that there is something to acquire.

Numerics: the mesh is shifted to a local origin (the centre of its bounding box) in
float64 and only then converted to float32 for Embree. Embree answers *which* triangle a
ray hits; the hit point is recomputed in float64 as the intersection of the float64 ray
with that triangle's float64 plane. A scene at UTM coordinates therefore gives the same
points as the same scene at the origin.
"""
from __future__ import annotations

import numpy as np

from ..errors import SceneError
from ..formats.pointcloud import BUILDING_CLASS, GRADE_UNKNOWN, GROUND_CLASS, UNCLASSIFIED
from ..formats.scene import GROUND, VEGETATION, Scene
from ._scan_reference import loops as choose_loops


class RayCaster:
    """Embree scene of a QuakeScan scene, with float64 hit refinement and face labels."""

    def __init__(self, scene: Scene):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        if len(scene.faces) == 0:
            raise SceneError("scene has no faces: nothing to scan")
        bounds = scene.bounds()
        # Local origin: keeps float32 coordinates small (|x| < scene size) at the Embree boundary.
        self.local_origin = 0.5 * (bounds[0] + bounds[1])
        v = scene.vertices - self.local_origin
        f = scene.faces
        self.bounds_local = bounds - self.local_origin
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = n
        self.plane_d = np.einsum("ij,ij->i", n, a)
        self.face_building = scene.face_building.astype(np.uint32)
        self.face_surface = scene.face_surface.astype(np.uint8)
        grades = scene.grade_lookup()
        lut = np.full(int(self.face_building.max()) + 1, GRADE_UNKNOWN, np.uint8)
        for bid, g in grades.items():
            lut[bid] = g
        self.face_grade = lut[self.face_building]
        from .reflectance import face_reflectance

        self.face_reflectance = face_reflectance(scene)
        self.face_class = np.where(self.face_building > 0, BUILDING_CLASS,
                                   np.where(self.face_surface == GROUND, GROUND_CLASS, UNCLASSIFIED)
                                   ).astype(np.uint8)
        # Porous faces (tree crowns) let rays pass (quakescan.acquisition.vegetation); None: every face is opaque
        # and a ray ends at its first hit, with no transmission drawn.
        self.face_porous = scene.face_porous.astype(bool) if scene.has_porous else None
        self.transmission = float(scene.transmission)
        is_veg = (self.face_building == 0) & (self.face_surface == VEGETATION)
        if is_veg.any():
            from .vegetation import vegetation_face_classes

            veg_class = vegetation_face_classes(v, f, is_veg, self.face_porous)
            self.face_class[is_veg] = veg_class[is_veg]
        self._embree = rtcore_scene.EmbreeScene()
        self._mesh = TriangleMesh(self._embree, v.astype(np.float32), f.astype(np.int32))
        # Committing is lazy in embreex and not thread-safe: do it now with one ray.
        self._embree.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))

    def cast(self, origins: np.ndarray, directions: np.ndarray, max_range: float,
             origins32=None, directions32=None, loops=None, ray_ids=None):
        """Cast rays (local frame, float64 (n, 3), unit directions).

        Returns (face, t): face index per ray (-1 = no hit) and the float64 distance to
        the hit on that face's plane (inf where there is no hit). Embree releases the GIL,
        so calls from several threads run in parallel. `origins32`/`directions32` skip the
        float32 conversion when the caller has them; `loops` is the module whose
        `refine_hits` refines them (`_scan_reference.loops`; default the compiled one).
        `ray_ids` (`quakescan.acquisition.vegetation.RayIds`) lets
        rays pass porous faces (tree crowns); without it every face is opaque (DIM).
        """
        o32 = origins.astype(np.float32) if origins32 is None else origins32
        d32 = directions.astype(np.float32) if directions32 is None else directions32
        face = self.embree_faces(o32, d32, max_range).astype(np.int64)
        if ray_ids is not None and self.face_porous is not None:
            from .vegetation import pass_porous

            face = pass_porous(self, origins, directions, face, max_range, ray_ids)
        refine = (choose_loops(True) if loops is None else loops).refine_hits
        return face, refine(origins, directions, face, self.normals, self.plane_d, float(max_range))

    def embree_faces(self, origins32: np.ndarray, directions32: np.ndarray, max_range: float) -> np.ndarray:
        """Face hit by each float32 ray (int32, -1 = none); Embree alone, GIL released.
        `max_range`: one distance, or one per ray (float32 array)."""
        dists = max_range if isinstance(max_range, np.ndarray) else float(max_range)
        return self._embree.run(origins32, directions32, dists=dists, output=0)


def ground_level(scene: Scene) -> float:
    """Median height of terrain faces (building_id 0, surface ground), else the lowest vertex."""
    terrain = (scene.face_building == 0) & (scene.face_surface == GROUND)
    if terrain.any():
        return float(np.median(scene.vertices[scene.faces[terrain]][..., 2]))
    return float(scene.vertices[:, 2].min())


def check_scannable(scene: Scene, source="scene") -> None:
    if len(scene.faces) == 0:
        raise SceneError(f"{source}: the scene is empty (no faces); nothing to scan")
    if not scene.buildings or not (scene.face_building > 0).any():
        raise SceneError(f"{source}: the scene has no buildings (no faces with building_id > 0); "
                         "a damage scan needs at least one building")
