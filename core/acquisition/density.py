"""The density of an epoch (what a survey's nominal density is checked against) and a
seeded, sparser copy of an epoch at a target density.

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

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PointCloudError
from ..formats.pointcloud import BUILDING_CLASS, Epoch, read_epoch, read_las
from ..grid.density import DENSITY_CELL_M, roof_cell_density
from ..runtime.atomic import replacing

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
    density, cells = roof_cell_density(_cells(epoch.xyz[m], epoch.origin), epoch.xyz[m, 2])
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
    before, n_cells = roof_cell_density(cells, z)
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
        d = roof_cell_density(cells[kept], z[kept])[0]
        if math.isfinite(d) and (math.isnan(best[1]) or abs(d - target) < abs(best[1] - target)):
            best = (p, d)
        if not math.isfinite(d) or d <= 0:
            p = min(1.0, 2 * p)
            continue
        if abs(d - target) <= 0.01 * target:
            break
        p = min(1.0, p * target / d)
    return best


__all__ = ["Thinning", "measured_density", "thin_to_density"]
