"""Optional rigid alignment of the post-event epoch to the pre-event epoch on stable areas.

An earthquake changes buildings; ground, roads and whatever stands outside the building
footprints are assumed unchanged, so a rigid transform fitted on those points removes the
georeferencing offset between two flights without absorbing the damage (`stable_mask`).

`align_epochs` runs point-to-plane ICP (open3d) from the identity:

1. both stable sets are randomly subsampled to at most `max_points` (deterministic by `seed`);
2. both are centred on one common centre, the float64 mean of the pre-event stable points:
   open3d then works on coordinates of at most a few hundred metres whatever the frame
   (a cloud at UTM coordinates gives the same answer as one at the origin), and the
   transform is composed back: T = Tr(c) · T_c · Tr(−c);
3. both are voxel-downsampled (`voxel_m`, open3d's voxel centroids) for speed only; the
   grid is a knob that trades run time against the density ICP sees, nothing more;
4. normals are estimated on the downsampled pre-event points (radius 4 × voxel, at most 30
   neighbours) and oriented upwards; ICP minimises post-to-pre point-to-plane distances
   between correspondences closer than `max_distance_m`.

The quality figures are measured on the subsampled full-resolution stable points, not on
the voxel centroids (voxel averaging would hide the per-point noise): every post point is
paired with its nearest pre point within `max_distance_m`, and its residual is the signed
distance along the normal borrowed from the nearest downsampled pre point (upwards
positive). `rmse_before_m` / `rmse_after_m` are the RMS of these point-to-plane residuals
before / after the transform; `std_after_m` is their standard deviation after it: the
alignment's noise, which a level of detection can use as registration error. Each is over
the post points that found a partner (the inlier set of that moment).
"""
from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError
from ..formats.pointcloud import BUILDING_CLASS, GROUND_CLASS, NOISE_CLASSES, VEGETATION_CLASSES

log = logging.getLogger(__name__)

MIN_STABLE_POINTS = 100
LARGE_TRANSLATION_M = 5.0
LARGE_ROTATION_DEG = 5.0


class AlignmentError(QuakeScanError):
    """The epochs cannot be aligned as given (too few stable points, no overlap)."""


@dataclass
class Alignment:
    """A rigid transform from the post-event local frame to the pre-event one (same origin).

    Residuals are point-to-plane distances (see the module's docstring)."""

    transform: np.ndarray  # (4, 4) float64: post local coords -> pre local coords
    rmse_before_m: float  # RMS point-to-plane residual of stable post points before ICP (inliers)
    rmse_after_m: float  # the same after applying `transform`
    std_after_m: float  # standard deviation of the signed residuals after: the alignment's noise
    fitness: float  # open3d's share of the downsampled post points with a correspondence
    n_stable_pre: int
    n_stable_post: int
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # local coords ICP was centred on

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation part, in degrees."""
        return rotation_angle_deg(self.transform)

    @property
    def translation_m(self) -> np.ndarray:
        """Displacement of the stable points' centre (the translation at the data, which the
        transform's last column is only when the centre is the local origin)."""
        return self.apply(self.centre[None, :])[0] - self.centre

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """Transform (n, 3) post-event local coordinates into the pre-event frame (float64)."""
        return apply_transform(self.transform, xyz)

    def to_json(self) -> dict:
        return {"transform": self.transform.tolist(),
                "centre": self.centre.tolist(),
                "translation_m": self.translation_m.tolist(),
                "rotation_deg": self.rotation_deg,
                "rmse_before_m": self.rmse_before_m, "rmse_after_m": self.rmse_after_m,
                "std_after_m": self.std_after_m, "fitness": self.fitness,
                "residuals": "point-to-plane",
                "n_stable_pre": self.n_stable_pre, "n_stable_post": self.n_stable_post}


def apply_transform(transform, xyz: np.ndarray) -> np.ndarray:
    """(n, 3) float64 coordinates moved by a 4 × 4 rigid transform, element by element: a
    matrix product (BLAS) may round a row differently by its place in the array, and a chunk
    of a streamed cloud must move exactly as it does within the whole cloud."""
    transform = np.asarray(transform, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    r, t = transform[:3, :3], transform[:3, 3]
    out = np.empty_like(xyz)
    for k in range(3):
        out[:, k] = xyz[:, 0] * r[k, 0] + xyz[:, 1] * r[k, 1] + xyz[:, 2] * r[k, 2] + t[k]
    return out


def rotation_angle_deg(transform: np.ndarray) -> float:
    r = np.asarray(transform, dtype=np.float64)[:3, :3]
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def format_alignment(a: Alignment) -> str:
    """One line for a human: translation at the data, rotation, noise, fitness."""
    tx, ty, tz = a.translation_m
    return (f"translation ({tx:+.3f}, {ty:+.3f}, {tz:+.3f}) m, rotation {a.rotation_deg:.4f}°, "
            f"std {a.std_after_m:.3f} m (rmse {a.rmse_before_m:.3f} -> {a.rmse_after_m:.3f} m), "
            f"fitness {a.fitness:.2f}, stable points {a.n_stable_pre} pre / {a.n_stable_post} post")


def sample_mask(index: np.ndarray | range, n_total: int, max_points: int) -> np.ndarray:
    """About `max_points` of `n_total` points, chosen by their index in the file alone (a
    splitmix64 hash of it below a threshold): the same points whether the cloud is read
    whole or streamed in chunks, which a random draw over the stable points is not.
    `index`: the points' indices, or a range of them (no index array made)."""
    if isinstance(index, range) and index.step == 1:
        start, n, index = index.start, len(index), np.zeros(0, np.int64)
    else:
        index = np.ascontiguousarray(index, dtype=np.int64)
        start, n = 0, len(index)
    share = min(1.0, max_points / max(int(n_total), 1))
    if share >= 1.0:
        return np.ones(n, bool)
    from ..grid.cells import splitmix_below

    # compiled: the numpy expression made five 8-byte temporaries of a whole epoch (3 s and
    # 3 GB for 75 M points); the same bits. 2 % under: a sample rarely tops max_points
    return splitmix_below(start, index, n, np.uint64(int(share * 0.98 * 2.0 ** 64)))


def stable_mask(classification, building_id=None) -> np.ndarray:
    """Points assumed unchanged between epochs: buildings are what changes after an earthquake.

    Stable are ground points (ASPRS class 2) and, when building ids are known, every point
    outside a building (building_id == 0) that is not itself classified as building (class 6:
    a building missing from the footprints is still a building) nor as vegetation (classes
    3-5: crowns are porous and move in the wind) nor noise (7, 18). Without building ids only
    ground is trusted: unclassified points may well be buildings."""
    c = np.asarray(classification)
    mask = c == GROUND_CLASS
    if building_id is not None:
        b = np.asarray(building_id)
        if b.shape != c.shape:
            raise AlignmentError(f"building_id has {b.shape} entries but classification {c.shape}")
        mask |= (b == 0) & (c != BUILDING_CLASS) & ~np.isin(c, VEGETATION_CLASSES) & ~np.isin(c, NOISE_CLASSES)
    return mask


def _stable_points(xyz, mask, name, max_points, rng):
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise AlignmentError(f"{name}: coordinates must be an (n, 3) array, got shape {xyz.shape}")
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (len(xyz),):
        raise AlignmentError(f"{name}: stable mask has shape {mask.shape} for {len(xyz)} points")
    pts = xyz[mask]
    pts = pts[np.isfinite(pts).all(axis=1)]
    n = len(pts)
    if n < MIN_STABLE_POINTS:
        raise AlignmentError(f"too few stable points (ground / non-building) to align: {n} in {name} "
                             f"(at least {MIN_STABLE_POINTS} needed)")
    if n > max_points:
        pts = pts[np.sort(rng.choice(n, size=max_points, replace=False))]
    return pts, n


def _residuals(post_c, pre_tree, pre_c, down_tree, down_normals, max_distance_m):
    """Signed point-to-plane residuals of post points with a pre partner within the distance."""
    d, j = pre_tree.query(post_c, k=1, distance_upper_bound=max_distance_m, workers=-1)
    ok = np.isfinite(d)
    if not ok.any():
        return np.empty(0)
    q = pre_c[j[ok]]
    _, k = down_tree.query(q, k=1, workers=-1)
    return np.einsum("ij,ij->i", post_c[ok] - q, down_normals[k])


@contextlib.contextmanager
def open3d_threads(workers: int = -1):
    """open3d runs on at most `workers` threads inside (-1 or None: its own default); its limit
    before is restored after. open3d parallelises with TBB, which neither OMP_NUM_THREADS nor
    threadpoolctl reaches: a one-thread Dask worker's ICP ran on every core and slowed the
    other worker's tiles (the 2 x 75 M pair's tile compute on two workers: 123.2 s beside it,
    114.7 s once it kept to one thread)."""
    import open3d as o3d

    if workers is None or workers < 1:
        yield
        return
    old = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(min(int(workers), old))
    try:
        yield
    finally:
        o3d.utility.set_max_threads(old)


def align_epochs(pre_xyz, post_xyz, pre_stable, post_stable, max_distance_m: float = 1.0,
                 voxel_m: float = 0.25, max_iterations: int = 50, max_points: int = 2_000_000,
                 seed: int = 0, pre_name: str = "the pre-event epoch",
                 post_name: str = "the post-event epoch", workers: int = -1) -> Alignment:
    """Point-to-plane ICP of the post epoch's stable points onto the pre epoch's (see the module).

    Both xyz arrays are float64 (n, 3) in the same local frame; the masks select stable points
    (`stable_mask`). Raises AlignmentError when either side has fewer than 100 stable points
    or when no correspondence lies within `max_distance_m`. `workers`: open3d's threads (-1:
    every core); the transform does not depend on it beyond its 1e-12 rounding."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    if not max_distance_m > 0:
        raise AlignmentError(f"max_distance_m must be positive, got {max_distance_m}")
    if max_points < MIN_STABLE_POINTS:
        raise AlignmentError(f"max_points must be at least {MIN_STABLE_POINTS}, got {max_points}")
    rng = np.random.default_rng(seed)
    pre, n_pre = _stable_points(pre_xyz, pre_stable, pre_name, max_points, rng)
    post, n_post = _stable_points(post_xyz, post_stable, post_name, max_points, rng)

    centre = pre.mean(axis=0)
    pre_c, post_c = pre - centre, post - centre

    def cloud(p):
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(p)
        return pc

    target, source = cloud(pre_c), cloud(post_c)
    if voxel_m and voxel_m > 0:
        target, source = target.voxel_down_sample(voxel_m), source.voxel_down_sample(voxel_m)
        normal_radius = 4.0 * voxel_m
    else:
        normal_radius = 1.0
    with open3d_threads(workers):
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
        target.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
        result = o3d.pipelines.registration.registration_icp(
            source, target, max_distance_m, np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                                              max_iteration=int(max_iterations)))
    if result.fitness <= 0 or len(result.correspondence_set) == 0:
        raise AlignmentError(f"{post_name}: epochs do not overlap within max_distance {max_distance_m} m: "
                             f"no stable point of it lies that close to {pre_name}'s "
                             f"({n_post} and {n_pre} stable points)")
    # open3d sums over threads: two runs on the same points differ in the last bits (7.6e-19
    # measured). Rounded to 1e-12 (a nanometre at a kilometre) every run moves the points alike,
    # so a rerun, or a distributed run, writes the same results.
    t_c = np.round(np.asarray(result.transformation, dtype=np.float64), 12)

    # quality on the full-resolution (subsampled) points, before and after
    down_pts = np.asarray(target.points)
    down_normals = np.asarray(target.normals)
    pre_tree, down_tree = cKDTree(pre_c), cKDTree(down_pts)
    before = _residuals(post_c, pre_tree, pre_c, down_tree, down_normals, max_distance_m)
    after = _residuals(post_c @ t_c[:3, :3].T + t_c[:3, 3], pre_tree, pre_c, down_tree, down_normals,
                       max_distance_m)

    def rms(r):
        return float(np.sqrt(np.mean(r * r))) if len(r) else float("nan")

    to_c, from_c = np.eye(4), np.eye(4)
    to_c[:3, 3], from_c[:3, 3] = -centre, centre
    a = Alignment(transform=from_c @ t_c @ to_c, rmse_before_m=rms(before), rmse_after_m=rms(after),
                  std_after_m=float(np.std(after)) if len(after) else float("nan"),
                  fitness=float(result.fitness), n_stable_pre=int(n_pre), n_stable_post=int(n_post),
                  centre=centre)
    shift, angle = float(np.linalg.norm(a.translation_m)), a.rotation_deg
    if shift > LARGE_TRANSLATION_M or angle > LARGE_ROTATION_DEG:
        log.warning("%s: the alignment moves it by %.2f m and rotates it by %.2f° (more than %g m or %g°): "
                    "likely a wrong match; check the result or skip alignment", post_name, shift, angle,
                    LARGE_TRANSLATION_M, LARGE_ROTATION_DEG)
    log.info("alignment of %s to %s: %s", post_name, pre_name, format_alignment(a))
    return a
