"""Photogrammetry-like point clouds: dense image matching (DIM) from a virtual UAV photo flight.

The model, step by step (every number is a `PhotoSurvey` field; see `quakescan.acquisition.dim_settings.FIELD_DOC`):

1. **Camera network.** Parallel, serpentine flight lines at `altitude_agl_m` above the
   scene's ground level, over the scene's xy extent grown by `margin_m` on every side (so
   that the inward-looking oblique cameras also see the facades at the scene's edges).
   Exposure stations are spaced by the nadir image footprint on flat ground times
   (1 - `forward_overlap_pct`) along a line and (1 - `side_overlap_pct`) across lines. Every
   station carries a nadir camera and, with `oblique_cameras` = 4, four oblique cameras
   tilted by `oblique_tilt_deg` from nadir towards the front, back, left and right
   (Maltese cross), with their own focal length (oblique systems use longer lenses so that
   the oblique images' ground sampling distance, GSD, comes close to the nadir one).
   A camera's image time is the flight time to its station at `speed_m_s`.
2. **Density from the image resolution and viewing angle.** The mesh is cut into pieces of
   at most `dim_pieces.TILE_M` metres (large terrain triangles are split), and every piece ranks the
   cameras that may see it by their sampling interval on its surface
   `h = point_step_px · pixel · d / (f · sqrt(cos θ))` (d distance, θ incidence angle:
   the pixel's footprint is GSD × GSD/cos θ, `h` is the side of the square of the same
   area), keeping the best `max_candidate_views`. A piece is sampled on a jittered grid of
   the best camera's `h` (one candidate point per cell, at a uniform random place in the cell:
   DIM keeps about one point per `point_step_px` × `point_step_px` pixels).
3. **Visibility.** A candidate is reconstructed only if at least `min_views` cameras see
   it: inside the image frame, incidence angle below `max_incidence_deg` (both sides of a
   face count, so flipped normals do not matter) and nothing on the ray from the camera
   to the point closer than `visibility_tolerance_m` before it (Embree through
   `quakescan.acquisition.raycast.RayCaster`: local origin, float32 only at that boundary, hit distance
   refined in float64). Every piece is first probed (its centre and a jittered grid of
   `probe_spacing_m`) against its ranked cameras: a piece that fewer than `min_views`
   cameras see at any probe (under buildings, inside closed solids) gets no candidates,
   and a candidate tries only the cameras that see a probe of its piece, in ranking order,
   until `min_views` see it. Both steps can only drop points, never add one seen by fewer
   than `min_views` cameras; they may miss surfaces seen only through openings narrower
   than the probe spacing, or only by cameras outside the piece's ranking.
4. **Best view.** The first camera in ranking order that sees the point is its best view;
   where the best visible view samples it more coarsely than the piece's grid (the better
   cameras are occluded), the point is kept with probability (h_grid / h_best)², so the
   density follows the views that really see the surface.
5. **Edges and corners** are smoothed as in window-based matching (on the noise-free
   positions, before the noise): a point within
   `smoothing_radius_m` of a crease (mesh edge whose faces meet at more than
   `crease_angle_deg`, or an open edge of a building) moves towards the mean of its
   neighbours within that radius, by a weight falling linearly from 1 on the crease to 0
   at the radius. Convex edges are rounded off, concave corners filled.
6. **Noise** along the best view's ray (a depth error): Gaussian with
   `sigma = noise_px · GSD / cos(θ)^noise_angle_exponent`, GSD = d · pixel / f of the
   best view at the point. It grows with distance and with obliqueness (exponent 2: the
   error across the surface grows as 1/cos θ, foreshortened matching windows).

Output: the epoch point cloud contract (LAS 1.4 format 6, scale 1 mm, offset = scene
origin) written like the ULS scan, with classification 2 ground / 6 building / 1 other
and `building_id`, `grade`, `surface` of the face the point was sampled on. DIM has no
returns or scan angles: return_number = number_of_returns = 1, scan_angle = 0,
gps_time = image time of the best view, point_source_id = flight line (1-based) of the
best view's station. The points are ordered by mesh piece, then grid cell: the same
scene, survey and seed give the same bytes whatever the number of threads.
"""
from __future__ import annotations

import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError, SurveyError
from ..formats.pointcloud import LasChunkWriter, PointChunk
from ..formats.scene import Scene
from ..runtime.progress import ProgressCallback
from ..runtime.workers import EVERY_CORE, check_workers
from .dim_cameras import plan_cameras
from .dim_edges import crease_segments, smooth
from .dim_pieces import interval, make_pieces, work_chunks
from .dim_settings import PhotoSurvey
from .las_output import label_counts, las_offset
from .raycast import RayCaster, check_scannable, ground_level

log = logging.getLogger(__name__)

# Points written per LAS chunk.
_WRITE_CHUNK = 1 << 20


@dataclass
class DimSummary:
    output: str
    points: int = 0
    candidates: int = 0
    rejected_by_angle: int = 0  # fewer than min_views cameras with the point in frame and below the cut-off
    rejected_by_visibility: int = 0  # enough such cameras, but fewer than min_views unoccluded
    rejected_by_thinning: int = 0  # dropped where the best visible view samples more coarsely
    rays_cast: int = 0  # visibility rays, probes included
    probes: int = 0
    hidden_pieces: int = 0  # mesh pieces whose probes fewer than min_views cameras see: no candidates
    cameras: int = 0
    stations: int = 0
    lines: int = 0
    pieces: int = 0
    smoothed_points: int = 0
    gsd_nadir_m: float = 0.0
    points_by_surface: dict = field(default_factory=dict)
    points_by_building: dict = field(default_factory=dict)
    wall_time_s: float = 0.0
    seed: int = 0

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["points_by_building"] = {str(k): v for k, v in sorted(self.points_by_building.items())}
        return d


class _Sim:
    def __init__(self, survey, cams, pieces, caster, seed, geometry):
        self.s, self.cams, self.p, self.caster, self.seed = survey, cams, pieces, caster, seed
        self.e1, self.e2, self.cx, self.cy, self.ab = geometry
        self.cos_max = math.cos(math.radians(survey.max_incidence_deg))

    def sample(self, idx, h, rng):
        """Jittered grid of spacing h[i] on pieces idx[i]: (points, piece index)."""
        p = self.p
        cx, cy, ab = self.cx[idx], self.cy[idx], self.ab[idx]
        x0 = np.minimum(0, cx) - rng.random(len(idx)) * h
        y0 = np.minimum(0, cy) - rng.random(len(idx)) * h
        nx = np.ceil((np.maximum(ab, cx) - x0) / h).astype(np.int64)
        ny = np.ceil((np.maximum(0, cy) - y0) / h).astype(np.int64)
        counts = nx * ny
        total = int(counts.sum())
        piece = np.repeat(np.arange(len(idx)), counts)
        k = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        nxp = nx[piece]
        jit = rng.random((total, 2))
        x = x0[piece] + (k % nxp + jit[:, 0]) * h[piece]
        y = y0[piece] + (k // nxp + jit[:, 1]) * h[piece]
        # inside the triangle (0,0), (ab,0), (cx,cy): edge functions
        cxp, cyp, abp = cx[piece], cy[piece], ab[piece]
        sgn = np.sign(cyp)  # orientation of (a, b, c) in the plane's 2-D frame
        e0 = sgn * abp * y  # edge a → b
        e1 = sgn * ((cxp - abp) * y - cyp * (x - abp))  # edge b → c
        e2 = sgn * (cyp * x - cxp * y)  # edge c → a
        inside = (e0 >= 0) & (e1 >= 0) & (e2 >= 0)
        piece, x, y = piece[inside], x[inside], y[inside]
        g = idx[piece]
        pts = p.a[g] + x[:, None] * self.e1[g] + y[:, None] * self.e2[g]
        return pts, g

    def see(self, pts, normal, cam, stats):
        """Per (point, camera) pair: in the frame and below the incidence cut-off (`ok`), and
        also unoccluded (`vis`); distance and |cos incidence|."""
        s, cams = self.s, self.cams
        rel = pts - cams.position[cam]  # camera → point
        d = np.sqrt(np.einsum("ij,ij->i", rel, rel))
        q = np.einsum("nij,nj->ni", cams.rotation[cam], rel)
        cos_t = np.abs(np.einsum("ij,ij->i", normal, rel)) / d
        ok = ((q[:, 2] > 0) & (np.abs(q[:, 0]) <= q[:, 2] * cams.tan_half_w[cam])
              & (np.abs(q[:, 1]) <= q[:, 2] * cams.tan_half_h[cam]) & (cos_t >= self.cos_max))
        vis = np.zeros(len(pts), bool)
        i = np.flatnonzero(ok)
        if len(i):
            face, t = self.caster.cast(cams.position[cam[i]], rel[i] / d[i, None], float(d[i].max()) + 1.0)
            stats["rays_cast"] += len(i)
            vis[i] = (face < 0) | (t >= d[i] - s.visibility_tolerance_m)
        return ok, vis, d, cos_t

    def probe(self, idx, rng, stats):
        """Cameras (rank columns) that see at least one probe of each piece: the centre and
        a jittered grid of spacing max(probe_spacing_m, h)."""
        s, p = self.s, self.p
        pts, g = self.sample(idx, np.maximum(p.h[idx], s.probe_spacing_m), rng)
        pts = np.concatenate([(p.a[idx] + p.b[idx] + p.c[idx]) / 3, pts])
        g = np.concatenate([idx, g])
        local = np.searchsorted(idx, g)
        useful = np.zeros((len(idx), p.rank.shape[1]), bool)
        for r in range(p.rank.shape[1]):
            cam = p.rank[g, r]
            has = np.flatnonzero(cam >= 0)
            if not len(has):
                break
            _, vis, _, _ = self.see(pts[has], p.normal[g[has]], cam[has], stats)
            useful[local[has[vis]], r] = True
        stats["probes"] += len(pts)
        return useful

    def run(self, chunk_no, i0, i1):
        s, cams, p = self.s, self.cams, self.p
        stats = {"candidates": 0, "rays_cast": 0, "probes": 0, "hidden_pieces": 0}
        idx = np.arange(i0, i1)
        idx = idx[np.isfinite(p.h[idx])]
        useful = self.probe(idx, np.random.default_rng([self.seed, chunk_no, 1]), stats)
        visible = useful.sum(axis=1) >= s.min_views
        stats["hidden_pieces"] = int(np.count_nonzero(~visible))
        idx, useful = idx[visible], useful[visible]
        # per piece the cameras that see one of its probes, in rank order
        order = np.argsort(~useful, axis=1, kind="stable")
        table = np.where(np.take_along_axis(useful, order, 1), np.take_along_axis(p.rank[idx], order, 1), -1)
        rng = np.random.default_rng([self.seed, chunk_no])
        pts, g = self.sample(idx, p.h[idx], rng)
        local = np.searchsorted(idx, g)
        n = len(pts)
        stats["candidates"] = n
        found = np.zeros(n, np.int64)
        geometric = np.zeros(n, np.int64)
        best = np.full(n, -1, np.int64)
        best_d = np.zeros(n)
        best_cos = np.zeros(n)
        cos_max = self.cos_max
        for r in range(table.shape[1]):
            act = np.flatnonzero((found < s.min_views) & (table[local, r] >= 0))
            if not len(act):
                break
            cam = table[local[act], r]
            ok, vis, d, cos_t = self.see(pts[act], p.normal[g[act]], cam, stats)
            geometric[act[ok]] += 1
            act, cam, d, cos_t = act[vis], cam[vis], d[vis], cos_t[vis]
            first = best[act] < 0
            best[act[first]], best_d[act[first]], best_cos[act[first]] = cam[first], d[first], cos_t[first]
            found[act] += 1
        seen = found >= s.min_views
        stats["rejected_by_angle"] = int(np.count_nonzero(~seen & (geometric < s.min_views)))
        stats["rejected_by_visibility"] = int(np.count_nonzero(~seen & (geometric >= s.min_views)))
        # density of the best view that really sees the point
        h_best = interval(s, cams, best, best_d, np.maximum(best_cos, 1e-6))
        u = rng.random(n)
        thin_keep = u < (p.h[g] / np.where(seen, h_best, np.inf)) ** 2
        stats["rejected_by_thinning"] = int(np.count_nonzero(seen & ~thin_keep))
        keep = seen & thin_keep
        pts, g, cam, d, cos_t = pts[keep], g[keep], best[keep], best_d[keep], best_cos[keep]
        pitch = s.pixel_pitch_um * 1e-6
        gsd = d * pitch / cams.focal_m[cam]
        sigma = s.noise_px * gsd / np.maximum(cos_t, cos_max) ** s.noise_angle_exponent
        ray = (pts - cams.position[cam]) / d[:, None]
        disp = ray * (sigma * rng.standard_normal(len(pts)))[:, None]
        return pts, disp, g, cam, stats


def simulate_dim(scene: Scene, photo_survey: PhotoSurvey, out_path: str | os.PathLike, seed: int = 0,
                 progress: ProgressCallback | None = None, workers: int = -1, source: str = "scene") -> DimSummary:
    """Simulate a DIM point cloud of `scene` from `photo_survey` and write it to `out_path`.

    `progress` is called with (chunks_done, chunks_total). Same scene, survey and seed give
    the same bytes whatever `workers` (threads; -1: every core, at most 4 here)."""
    started = time.perf_counter()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise QuakeScanError(f"seed must be an integer >= 0, got {seed!r}")
    workers = check_workers(workers)
    s = photo_survey
    check_scannable(scene, source)
    caster = RayCaster(scene)
    verts = scene.vertices - caster.local_origin
    cams = plan_cameras(s, caster.bounds_local, ground_level(scene) - caster.local_origin[2])
    pieces = make_pieces(s, cams, verts, scene.faces)
    chunks, *geometry = work_chunks(pieces)
    summary = DimSummary(output=str(out_path), cameras=len(cams), stations=cams.stations, lines=cams.lines,
                         pieces=len(pieces.h), gsd_nadir_m=s.gsd_m, seed=seed)
    if not np.isfinite(pieces.h).any():
        raise SurveyError(f"{source}: no surface of the scene lies in the images of at least {s.min_views} "
                          f"cameras of the photo survey '{s.name}' (is altitude_agl_m={s.altitude_agl_m} above "
                          f"the buildings?)")
    sim = _Sim(s, cams, pieces, caster, seed, geometry)
    threads = workers if workers != EVERY_CORE else min(4, os.cpu_count() or 1)
    results = []
    with ThreadPoolExecutor(max_workers=threads) as pool:
        futures = [pool.submit(sim.run, k, i0, i1) for k, (i0, i1) in enumerate(chunks)]
        for k, fut in enumerate(futures):
            results.append(fut.result())
            if progress:
                progress(k + 1, len(futures))
    for *_, stats in results:
        for key, v in stats.items():
            setattr(summary, key, getattr(summary, key) + v)
    pts = np.concatenate([r[0] for r in results]) if results else np.zeros((0, 3))
    if len(pts) == 0:
        raise SurveyError(f"{source}: the photo survey '{s.name}' reconstructed no points: no surface is seen "
                          f"by {s.min_views} cameras")
    disp = np.concatenate([r[1] for r in results])
    g = np.concatenate([r[2] for r in results])
    cam = np.concatenate([r[3] for r in results])
    del results
    if s.smoothing_radius_m > 0:
        p0, p1 = crease_segments(verts, scene.faces, scene.face_building, s.crease_angle_deg)
        pc = (pieces.a + pieces.b + pieces.c) / 3
        pr = np.max(np.stack([np.linalg.norm(x - pc, axis=1) for x in (pieces.a, pieces.b, pieces.c)]), axis=0)
        summary.smoothed_points = smooth(pts, p0, p1, s.smoothing_radius_m, pc, pr, g)
    pts += disp
    face = pieces.face[g]
    summary.points = len(pts)
    offset, shift = las_offset(scene, caster)
    writer = LasChunkWriter(out_path, offset, scene.crs, s.acquisition_date)
    writer.header.system_identifier = "QuakeScan virtual DIM"
    with writer:
        for i in range(0, len(pts), _WRITE_CHUNK):
            sl = slice(i, i + _WRITE_CHUNK)
            f = face[sl]
            m = len(f)
            writer.write(PointChunk(
                xyz=pts[sl] + shift, gps_time=cams.time_s[cam[sl]], scan_angle_deg=np.zeros(m),
                return_number=np.ones(m, np.uint8), number_of_returns=np.ones(m, np.uint8),
                classification=caster.face_class[f], building_id=caster.face_building[f],
                grade=caster.face_grade[f], surface=caster.face_surface[f],
                point_source_id=(cams.line[cam[sl]] + 1).astype(np.uint16)))
    by_face = np.bincount(face, minlength=len(scene.faces))
    summary.points_by_surface, summary.points_by_building = label_counts(scene, caster, by_face, source,
                                                                          "DIM points")
    summary.wall_time_s = time.perf_counter() - started
    return summary
