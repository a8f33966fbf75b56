"""Building descriptors that mean the same at any point density and from any sensor.

The paper's descriptors are statistics over points, and several of its point features
(densities, neighbour counts) scale with the density of the cloud: a sparse airborne
archive before and a dense drone cloud after differ everywhere. What a structural
engineer reads from two surveys is geometric: how much of the footprint came down and by
how much, which surfaces disappeared, what lies around the building. This module measures
that on grids and core points whose spacing is set by the *sparser* epoch, so that every
descriptor is a share of area or a length, never a count of points:

**2.5-D upper surfaces** (`cell_m` = sqrt(points_per_cell / density of the sparser epoch),
clipped to [cell_min_m, cell_max_m]). The building's cells are those holding its pre-event
points; before the event the top of a cell is the building's own surface (its points:
vegetation over a roof included, as on real data where points belong to buildings through
footprints), after it whatever is there (every point: rubble, a neighbour's debris). Lowering = pre top − post top. At the building's outline and at steps of the roof
(where one sampling may catch an eave that the other misses) a cell is compared with the
highest post-event cell of its 3 × 3 neighbourhood instead; interior roof cells are
compared directly, so a hole of one or two cells is not smoothed away.

- `s_lowered_1m`, `s_lowered_storey`, `s_lowered_half`: share of the footprint lowered by
  more than 1 m, more than one storey (`storey_m`), more than half its height above ground;
- `s_raised`: share raised by more than `raised_m` (tilted or displaced parts, debris);
- `s_volume_loss`, `s_volume_gain`: lost / gained volume relative to the pre-event volume
  above ground; `s_height_ratio_mean`, `s_height_ratio_p10`: post/pre height above ground over the
  footprint (mean and 10th percentile);
- `s_post_gap`: share of the footprint with no post-event point (not covered or occluded);
- `s_debris_ring`, `s_debris_volume`: cells in a ring of `debris_ring_m` around the building
  (not other buildings' cells) that rose by more than `debris_rise_m`, as a share of the ring
  and as a volume relative to the building's;
- `s_see_through`: share of the footprint whose lowest post-event point lies more than
  `SEE_THROUGH_M` (or the cell's level of detection) below every pre-event point of its
  3 x 3 neighbourhood: the floor through a roof hole, rubble inside. A hole smaller than a
  cell's top layer leaves the top on the roof (no lowering); what was seen through it is
  not. Inner cells only, `SEE_THROUGH_INSET_M` in from the outline (after closing the
  single empty cells a sparse epoch leaves), so that a drone that sees walls or the space
  under the eaves lower down than an airborne archive did reads as nothing.
- `s_interior_seen`: share of the footprint where the post-event epoch saw *inside* the
  building: points at least `INTERIOR_DEPTH_M` in from the outline and `SEE_THROUGH_M`
  below every pre-event point within `INTERIOR_NEIGHBOURHOOD_M`, on a fine grid (0.5 m or
  the sparser epoch's point spacing), in patches of at least `min_patch_cells` and large
  enough that the pre-event epoch, at the building's roof density, would have hit the patch
  had it been in view (`MISSED_CHANCE`). A wall hole,
  a blown-out infill panel or a toppled facade under an intact roof opens the floors behind
  it to an oblique view only a metre or two deep: `s_see_through`'s inset on the coarse
  raster misses that, and an airborne archive never saw the wall, so its core points
  cannot be lost either. The outline is the pre-event footprint's (its points' cells,
  closed), and a wall seen lower down lies on it, not inside.

**Surface change on core points** (`quakescan.change.m3c2`): core points one per `cell_m` voxel of the
building's pre-event points (so shares are shares of surface area), normals from the
pre-event points, walls oriented outwards. A core point is *changed* when its M3C2 distance
exceeds both its own level of detection and `lod_floor_m` and its old surface is no longer
there (`M3C2Result.displaced`), or when its surface is lost: no post-event point within
`max_depth_m` along the normal where an unchanged surface would have had some (`_lost`).

- `m_changed`, `m_lost`: share of core points changed / lost; `m_roof_changed`,
  `m_wall_changed`: the same over roof (|n_z| >= 0.5) and wall core points;
- `m_holes`, `m_wall_holes`: share of (wall) core points lost *and seen through*: the
  post-event epoch has points behind where the surface was (the interior through a hole in
  a wall, a blown-out infill panel, the attic through a roof hole): an intact surface hides
  what is behind it, so this is the most specific sign of an opening;
- `m_upper_changed`, `m_lower_changed`: share changed above and below one storey
  (`storey_m`) over the ground: a neighbour's debris piles against the ground storey,
  damage to roofs, gables and parapets is higher up;
- `m_inward`, `m_outward`: share significantly moved against / along the normal (walls
  point outwards, roofs up): a roof that sagged, a wall that bulged or was buried;
- `m_largest_patch`: the largest patch of changed core points (joined up to two voxels
  apart), as a share;
- `m_coherent`: share of core points that are changed *and* have at least half of their
  (at least three) adjacent core points changed: a 95 % test flags ~5 % of an unchanged
  surface at random, real damage is spatially coherent;
- `m_distance_p10`, `m_distance_median`, `m_distance_p90`: signed distance over the changed
  comparable core points (0 when none); `m_lod_median`: the typical level of detection
  (how noisy the pair is, so the classifier can discount noise it has seen in training).

**Openings per return** (`quakescan.change.openings`, `o_fallen*`): post-event returns more than
`SEE_THROUGH_M` below every pre-event return within a radius that holds three pre-event returns
at the building's density, against the same count with the epochs swapped, and how what fell
is laid out (one region or scattered openings; down to the ground or to the storey below).
They see the handful of returns an airborne archive puts into a roof opening, which the
raster cells and patch sizes above never fill.

The building's ground is the 10th percentile of the pre-event ground points (ASPRS 2)
within `ground_search_m` of it, or the 2nd percentile of all pre-event points there when
the cloud has no ground class.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import QuakeScanError
from ..grid.cells import column_bounds, row_bounds, stable_order
from ..grid.density import planimetric_density
from . import descriptors as registry
from .core_points import core_change, count_by_facing, facing_bins, lost_surface
from .descriptors import names_of, transferring
from .detectability import min_lowering_m
from .m3c2 import ColumnGrid, M3C2Settings, cylinder_radius, m3c2, orient_normals, voxel_core_points
from .openings import OPENING_DESCRIPTORS

GROUND_CLASS = 2
# cells are numbered apart by this many metres of height when their points are ordered by cell
# and height in one array (no building is 10 km tall)
_BAND_STRIDE_M = 1.0e4
# share of a cell's pre-event points at the post-event height that makes it a surface seen before
LOWER_SURFACE_SHARE = 0.2
RASTER_DESCRIPTORS = names_of("raster") + names_of("interior")
# a post-event point this far (or its level of detection, if larger) below every pre-event point of
# its cell's 3 x 3 neighbourhood was seen through the roof: a floor under a hole, rubble inside
SEE_THROUGH_M = 1.0
SEE_THROUGH_INSET_M = 1.5
# the interior seen through an opening in a wall or roof: post-event points at least this far
# inside the outline (on a grid of INTERIOR_CELL_M or the sparser epoch's point spacing) and
# SEE_THROUGH_M below every pre-event point within INTERIOR_NEIGHBOURHOOD_M
INTERIOR_DEPTH_M = 1.0
INTERIOR_CELL_M = 0.5
INTERIOR_NEIGHBOURHOOD_M = 1.0
# An interior patch counts only when the pre-event epoch, at the building's roof density
# (`planimetric_density`), had a chance below this of putting no point on a surface of the patch's area
# (`chance_missed`): the two epochs of a sparse airborne pair each miss small low surfaces (a
# light well, a gap between roofs) the other hit a few times. At 4 pts/m² a patch needs
# 1.7 m² (7 cells of 0.5 m); above ln(1000) / 0.75 m² = 9.2 pts/m², 3 cells, as every patch does.
MISSED_CHANCE = 1e-3
CORE_DESCRIPTORS = names_of("core")
SURFACE_DESCRIPTORS = RASTER_DESCRIPTORS + CORE_DESCRIPTORS + OPENING_DESCRIPTORS
# the built-in descriptors whose meaning does not depend on the sensor's noise (the signed distances
# and the level of detection describe the sensor on an unchanged roof): what the shipped model reads
NOISE_FREE_DESCRIPTORS = transferring(SURFACE_DESCRIPTORS)


class SurfaceError(QuakeScanError):
    """Surface descriptors cannot be computed as asked."""


@dataclass(frozen=True)
class SurfaceSettings:
    points_per_cell: float = 4.0  # expected points of the sparser epoch per raster cell
    cell_min_m: float = 0.5
    cell_max_m: float = 2.0
    storey_m: float = 3.0
    raised_m: float = 0.5
    debris_ring_m: float = 5.0
    debris_rise_m: float = 0.3
    ground_search_m: float = 10.0
    lod_floor_m: float = 0.2  # a surface change smaller than this is not damage, however precise
    # top layer of a cell: within top_layer_cells * cell + top_layer_m of its highest point
    # (1.5 cells spans a 45 degree roof across the cell's diagonal)
    top_layer_cells: float = 1.5
    top_layer_m: float = 0.3
    # changes count only in patches of at least this many core points / raster cells
    min_patch_cores: int = 3
    min_patch_cells: int = 3
    # a share of the footprint (or relative volume) below this is no structural damage at any
    # EMS-98 grade >= 3 (the catalogue's smallest heavy patterns: roof holes over 5-30 % of the
    # roof): it counts as 0, as it does for every simulated undamaged building
    min_share: float = 0.005
    m3c2: M3C2Settings = field(default_factory=M3C2Settings)

    def __post_init__(self):
        for name in ("points_per_cell", "cell_min_m", "cell_max_m", "storey_m", "raised_m", "debris_ring_m",
                     "debris_rise_m", "ground_search_m", "top_layer_cells", "top_layer_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SurfaceError(f"surface setting {name} must be a positive number, got {v!r}")
        if self.cell_max_m < self.cell_min_m:
            raise SurfaceError(f"cell_max_m {self.cell_max_m} < cell_min_m {self.cell_min_m}")
        if isinstance(self.m3c2, dict):
            object.__setattr__(self, "m3c2", M3C2Settings.from_json(self.m3c2))

    def cell_for(self, sparser_density_pts_m2: float) -> float:
        """Raster cell side (m) for a pair whose sparser epoch has this planimetric density."""
        if not (math.isfinite(sparser_density_pts_m2) and sparser_density_pts_m2 > 0):
            return self.cell_max_m
        return float(np.clip(math.sqrt(self.points_per_cell / sparser_density_pts_m2), self.cell_min_m,
                             self.cell_max_m))

    def to_json(self) -> dict:
        d = asdict(self)
        d["m3c2"] = self.m3c2.to_json()
        return d

    @classmethod
    def from_json(cls, d: dict) -> SurfaceSettings:
        d = dict(d)
        d["m3c2"] = M3C2Settings.from_json(d.get("m3c2", {}))
        return cls(**d)


@dataclass
class SurfaceGeometry:
    """Grid and cylinder sizes of one pair (set by its sparser epoch)."""

    cell_m: float
    cylinder_radius_m: float
    density_pre: float
    density_post: float

    @classmethod
    def for_pair(cls, settings: SurfaceSettings, density_pre: float, density_post: float) -> SurfaceGeometry:
        sparser = min(density_pre, density_post)
        return cls(settings.cell_for(sparser), cylinder_radius(settings.m3c2, sparser), density_pre, density_post)



def region_margin(settings: SurfaceSettings, geom: SurfaceGeometry) -> float:
    """How far beyond a building's points its descriptors read the clouds (m)."""
    return max(settings.debris_ring_m + 2 * geom.cell_m, settings.ground_search_m,
               settings.m3c2.max_depth_m + geom.cylinder_radius_m, settings.m3c2.normal_radius_m) + 1.0


class _CellTops:
    """Upper surface per cell of one epoch (keys on one integer grid): height, how many points
    define it and how much they scatter.

    The top of a cell is the mean height of its *top layer*: the points within `layer_m`
    of its highest point. The highest point alone is biased by the density (on a sloped
    roof the highest of 20 samples lies nearer the cell's upper edge than the highest of 2);
    the mean of the top layer of a plane is its height at the centroid whatever the
    density, and walls or ground below the layer do not pull it down. Its standard
    deviation and count give the cell's level of detection as M3C2 does for a cylinder: a
    roof is a thin layer, a tree crown a thick one whose top moves by metres between two
    samplings of the same leaves."""

    def __init__(self, xyz: np.ndarray, lo: np.ndarray, cell: float, width: int, layer_m: float):
        from ..grid.cells import cell_keys, top_layers

        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        key = cell_keys(xyz, float(lo[0]), float(lo[1]), float(cell), int(width))
        # the spread of a single point is unknown: take a uniform spread over the layer
        self.unknown_std = layer_m / math.sqrt(12.0)
        if len(key):
            # compiled: numpy's reductions, bincounts and sort of a tile's points were a tenth of its time
            keys, starts, mean, bottom, n, sq, band, z0 = top_layers(key, stable_order(key), xyz[:, 2],
                                                                     float(layer_m), _BAND_STRIDE_M)
            # every point's height, ordered by cell then height, for counts within a height band
            self._z0 = z0
            self._band_key = band
            self._start = starts[:-1]
            self.bottom = bottom
            self.keys = keys
            self.top = mean
            self.n = n
            self.std = np.where(n >= 2, np.sqrt(sq / np.maximum(n - 1, 1)), self.unknown_std)
            self.count = np.diff(starts)
        else:
            self.keys = np.zeros(0, np.int64)
            self.top = self.std = self.bottom = np.zeros(0)
            self._band_key = np.zeros(0)
            self._z0 = 0.0
            self._start = np.zeros(0, np.int64)
            self.n = self.count = np.zeros(0, np.int64)

    def index(self, keys: np.ndarray) -> np.ndarray:
        """Position of each key's cell, -1 where the cell holds no point."""
        if len(self.keys) == 0:
            return np.full(keys.shape, -1, np.int64)
        pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return np.where(self.keys[pos] == keys, pos, -1)

    def _at(self, values: np.ndarray, keys: np.ndarray) -> np.ndarray:
        i = self.index(keys)
        return np.where(i >= 0, values[np.maximum(i, 0)] if len(values) else np.nan, np.nan)

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Top height per key, NaN where the cell holds no point."""
        return self._at(self.top, keys)

    def lowest(self, keys: np.ndarray) -> np.ndarray:
        """Lowest point's height per key, NaN where the cell holds no point."""
        return self._at(self.bottom, keys)

    def share_within(self, i: np.ndarray, height: np.ndarray, tol: np.ndarray) -> np.ndarray:
        """Share of the points of the cells at positions `i` within `tol` of `height` (0 where
        there is no cell or no height)."""
        out = np.zeros(i.shape)
        ok = (i >= 0) & np.isfinite(height) & np.isfinite(tol)
        if not ok.any() or len(self._band_key) == 0:
            return out
        j = i[ok]
        base = j * _BAND_STRIDE_M + self._z0
        lo = np.searchsorted(self._band_key, base + height[ok] - tol[ok], side="left")
        hi = np.searchsorted(self._band_key, base + height[ok] + tol[ok], side="right")
        # the band never reaches a neighbouring cell: heights are clipped to the cell's own range
        first, last = self._start[j], np.r_[self._start[1:], len(self._band_key)][j]
        lo, hi = np.clip(lo, first, last), np.clip(hi, first, last)
        out[ok] = (hi - lo) / np.maximum(self.count[j], 1)
        return out

    def variance_of_mean(self, i: np.ndarray) -> np.ndarray:
        """Squared standard error of the top at cell positions `i` (-1: no cell, NaN)."""
        if len(self.top) == 0:
            return np.full(i.shape, np.nan)
        j = np.maximum(i, 0)
        return np.where(i >= 0, self.std[j] ** 2 / self.n[j], np.nan)


def _row_argmax(values: np.ndarray):
    """Row-wise max ignoring NaN and its column (NaN, 0 for all-NaN rows)."""
    filled = np.where(np.isnan(values), -np.inf, values)
    j = np.argmax(filled, axis=1)
    m = filled[np.arange(len(values)), j]
    return np.where(np.isinf(m), np.nan, m), j


def _neighbour_offsets(width: int, radius_cells: int, disc_m: float | None = None, cell: float = 1.0):
    """Key offsets of the cells within a square of `radius_cells` (or within `disc_m` of the cell)."""
    d = np.arange(-radius_cells, radius_cells + 1)
    di, dj = np.meshgrid(d, d, indexing="ij")
    keep = np.ones(di.shape, bool) if disc_m is None else (di * di + dj * dj) * cell * cell <= disc_m ** 2 + 1e-9
    return (di * width + dj)[keep].ravel()


def describe_surfaces(pre_xyz: np.ndarray, pre_bid: np.ndarray, pre_ground: np.ndarray, post_xyz: np.ndarray,
                      bids, settings: SurfaceSettings, geom: SurfaceGeometry, *, workers: int = -1,
                      quality: bool = False, facing_counts: np.ndarray | None = None,
                      facing_out: dict | None = None, wanted=None, groups: dict | None = None):
    """Surface descriptors of the buildings `bids` from the points of a region around them.

    pre_xyz/post_xyz: (n, 3) local-frame points of the region (every kind of point);
    pre_bid: building ID per pre-event point (0 = none); pre_ground: ground mask (ASPRS 2)
    or None. Returns ({building ID: {descriptor: value}}, {building ID: CoreChange}) and,
    with `quality`, {building ID: {density_pre, density_post, coverage, cells, area_m2,
    wall_density_pre, wall_density_post, facade_m2, wall_facings, lowering_lod_m}}: planimetric densities
    (pts/m²) of the building's own pre-event points and of the post-event points over its
    cells, the share of its cells with post-event points, its cells and their area (m²), each
    epoch's returns per m² of its facades and their area (`quakescan.change.facade_sampling`),
    and the smallest lowering it resolves
    (`quakescan.change.detectability.min_lowering_m`; absent without a comparable core point).

    Whether a wall is lost is judged against how well the post-event flight saw walls facing
    the same way among the core points of all of `bids` (`_lost`): `facing_out`, when given,
    receives those counts ("facing_counts", `count_by_facing`), and `facing_counts` given
    replaces them, so buildings described in parts (a tile split to fit a worker's memory)
    are judged against the counts of the whole tile.

    Every registered family (`quakescan.change.descriptors.register`) that names one of
    `wanted` (default: every one) is computed per building from its `BuildingView`.
    `groups`: {building ID: ascending indices of its points in `pre_xyz`}, when the caller has
    grouped the points already (the pipeline has); otherwise they are grouped here."""
    from ..runtime.workers import kernel_threads
    from .features import compute_features

    bids = [int(b) for b in bids]
    c = geom.cell_m
    # the x/y bounds of both epochs in one compiled pass each (no stacked copy of them)
    lo_xy, hi_xy = (b[:2] for b in column_bounds(np.asarray(pre_xyz, dtype=np.float64)))
    if len(post_xyz):
        lo_post, hi_post = column_bounds(np.asarray(post_xyz, dtype=np.float64))
        lo_xy, hi_xy = np.minimum(lo_xy, lo_post[:2]), np.maximum(hi_xy, hi_post[:2])
    pad = int(math.ceil(settings.debris_ring_m / c)) + 3
    lo = np.floor(lo_xy / c) * c - pad * c
    width = int(math.ceil((hi_xy[1] - lo[1]) / c)) + 2 * pad + 2
    layer = settings.top_layer_cells * c + settings.top_layer_m
    pre_tops = _CellTops(pre_xyz, lo, c, width, layer)
    post_tops = _CellTops(post_xyz, lo, c, width, layer)
    pre_key = (np.floor((pre_xyz[:, 0] - lo[0]) / c).astype(np.int64) * width
               + np.floor((pre_xyz[:, 1] - lo[1]) / c).astype(np.int64))
    building_keys = np.unique(pre_key[pre_bid > 0])
    post_key = (np.floor((post_xyz[:, 0] - lo[0]) / c).astype(np.int64) * width
                + np.floor((post_xyz[:, 1] - lo[1]) / c).astype(np.int64))
    n3 = _neighbour_offsets(width, 1)
    ring_offsets = _neighbour_offsets(width, int(math.ceil(settings.debris_ring_m / c)), settings.debris_ring_m, c)

    if groups is None:
        order = stable_order(pre_bid)
        sorted_bid = pre_bid[order]
        groups = {bid: order[slice(*np.searchsorted(sorted_bid, [bid, bid + 1]))] for bid in bids}
    pre_sorted = _XSorted(pre_xyz)
    interior = _InteriorView(pre_sorted, _XSorted(post_xyz), max(INTERIOR_CELL_M, 0.5 * c))
    ground_finder = _GroundFinder(pre_sorted, pre_xyz[pre_ground] if pre_ground is not None else None,
                                  settings.ground_search_m)
    descriptors, members, core_of, qual, grounds, outline_core = {}, {}, {}, {}, {}, {}
    added = [f for f in registry.computed_per_building() if wanted is None or set(f.names) & set(wanted)]
    for bid in bids:
        idx = groups[bid]
        if len(idx) == 0:
            raise SurfaceError(f"building {bid} has no pre-event points in its region")
        ground = grounds[bid] = ground_finder.height(pre_xyz[idx])
        own_tops = _CellTops(pre_xyz[idx], lo, c, width, layer)
        descriptors[bid], edge_keys = _raster(pre_key[idx], own_tops, pre_tops, post_tops, building_keys, ground,
                                              n3, ring_offsets, settings, c, width)
        own_density = planimetric_density(pre_xyz[idx])  # read by three descriptors: measured once
        descriptors[bid]["s_interior_seen"] = interior.share(pre_xyz[idx], settings.min_patch_cells, own_density)
        descriptors[bid].update(_openings(pre_xyz[idx], pre_key[idx], own_density, interior, ground, lo, c, width,
                                          settings))
        for family in added:
            view = _building_view(pre_xyz[idx], pre_key[idx], own_density, interior, ground, lo, c, width, settings)
            descriptors[bid].update(registry.checked(family, family.compute(view)))
        if quality:
            cells = np.unique(pre_key[idx])
            inside = np.isin(post_key, cells)
            qual[bid] = {"density_pre": round(own_density, 3),
                         "density_post": round(planimetric_density(post_xyz[inside]), 3),
                         "coverage": round(1.0 - descriptors[bid]["s_post_gap"], 4),
                         "cells": int(len(cells)), "area_m2": round(len(cells) * c * c, 3)}
            qual[bid].update(_facades(pre_xyz[idx], interior, building_keys, ground, lo, c, width))
        members[bid] = idx
        core_of[bid] = idx[voxel_core_points(pre_xyz[idx], c)]
        outline_core[bid] = np.isin(pre_key[core_of[bid]], edge_keys)
    # the region's sorted copies, cell tops and keys served the buildings' rasters: gone before
    # the column grids of the M3C2 pass are built (about 80 bytes a point of the region less at
    # the tile's peak, two tiles at a time in one process)
    del pre_sorted, interior, ground_finder, pre_tops, post_tops, pre_key, post_key
    # one normal and one M3C2 pass over every building's core points
    all_core = np.concatenate([core_of[b] for b in bids]) if bids else np.zeros(0, np.int64)
    f = compute_features(pre_xyz, settings.m3c2.normal_radius_m, ("normal_x", "normal_y", "normal_z"),
                         query_index=np.sort(all_core), workers=workers)
    sorted_core = np.sort(all_core)
    normals_all = np.column_stack([f["normal_x"], f["normal_y"], f["normal_z"]])
    normals = {}
    for bid in bids:
        pos = np.searchsorted(sorted_core, core_of[bid])
        normals[bid] = orient_normals(normals_all[pos], pre_xyz[core_of[bid], :2],
                                      pre_xyz[members[bid], :2].mean(axis=0))
    nrm = np.vstack([normals[b] for b in bids]) if bids else np.zeros((0, 3))
    with kernel_threads(workers):  # the column sorts and the cylinder kernel
        pre_grid = ColumnGrid(pre_xyz, max(geom.cylinder_radius_m, 0.5))
        post_grid = ColumnGrid(post_xyz, max(geom.cylinder_radius_m, 0.5))
        res = m3c2(pre_xyz[all_core], nrm, pre_grid, post_grid, settings.m3c2, geom.cylinder_radius_m)
    facing = facing_bins(nrm)
    own_counts = count_by_facing(res, facing)
    if facing_out is not None:
        facing_out["facing_counts"] = own_counts
    lost_all = lost_surface(res, facing, np.concatenate([outline_core[b] for b in bids]) if bids else np.zeros(0, bool),
                            own_counts if facing_counts is None else np.asarray(facing_counts))
    cores, start = {}, 0
    for bid in bids:
        k = len(core_of[bid])
        sl = slice(start, start + k)
        start += k
        cc, dm = core_change(pre_xyz[core_of[bid]], normals[bid], res, lost_all[sl], res.seen_through[sl], sl,
                             settings, c, grounds[bid])
        descriptors[bid].update(dm)
        _dead_zone(descriptors[bid], settings.min_share)
        cores[bid] = cc
        if quality and cc.comparable.any():  # the smallest lowering the building resolves (detectability)
            qual[bid]["lowering_lod_m"] = round(min_lowering_m(float(np.median(cc.lod[cc.comparable])),
                                                               settings.lod_floor_m), 4)
    if quality:
        return descriptors, cores, qual
    return descriptors, cores


class _XSorted:
    """Points sorted by x once, so that the points in one building's box are a slice away."""

    def __init__(self, xyz: np.ndarray):
        self.xyz = xyz[np.argsort(xyz[:, 0], kind="stable")]

    def in_box(self, lo, hi) -> np.ndarray:
        a, b = np.searchsorted(self.xyz[:, 0], [lo[0], hi[0]])
        cand = self.xyz[a:b]
        return cand[(cand[:, 1] >= lo[1]) & (cand[:, 1] < hi[1])]


class _InteriorView:
    """`s_interior_seen` of one building at a time (see the module's docstring)."""

    def __init__(self, pre: _XSorted, post: _XSorted, cell: float):
        self.pre, self.post, self.cell = pre, post, cell

    def share(self, own_xyz: np.ndarray, min_patch_cells: int, own_density: float) -> float:
        from scipy import ndimage

        f = self.cell
        near = int(math.ceil(INTERIOR_NEIGHBOURHOOD_M / f))
        pad = near + 3
        own_lo, own_hi = row_bounds(own_xyz[:, :2])
        lo = np.floor(own_lo / f) * f - pad * f
        shape = tuple(np.floor((own_hi - lo) / f).astype(int) + pad + 1)
        hi = lo + np.array(shape) * f

        def cells(xyz):  # clipped: a point a rounding error short of `hi` stays on the grid
            return tuple(np.clip(np.floor((xyz[:, :2] - lo) / f).astype(np.int64), 0, np.array(shape) - 1).T)

        footprint = np.zeros(shape, bool)
        footprint[cells(own_xyz)] = True
        # single empty cells of a sparse sampling are the building's; a courtyard stays outside
        footprint = ndimage.binary_closing(footprint, np.ones((3, 3), bool), iterations=2) | footprint
        inner = ndimage.distance_transform_edt(footprint) * f - 0.5 * f >= INTERIOR_DEPTH_M
        if not inner.any():
            return 0.0
        pre = self.pre.in_box(lo, hi)
        lowest = np.full(shape, np.inf)
        np.minimum.at(lowest, cells(pre), pre[:, 2])
        # every pre-event point around the cell: a step of the roof or a wall seen before is no opening
        lowest = ndimage.minimum_filter(lowest, size=2 * near + 1, mode="constant", cval=np.inf)
        post = self.post.in_box(lo, hi)
        ij = cells(post)
        below = inner[ij] & np.isfinite(lowest[ij]) & (post[:, 2] < lowest[ij] - SEE_THROUGH_M)
        seen = np.zeros(shape, bool)
        seen[ij[0][below], ij[1][below]] = True
        if not seen.any():
            return 0.0
        # a single stray point (a bird, multipath) is no opening; what is seen through one is areal
        labels, n = ndimage.label(seen, np.ones((3, 3), bool))
        sizes = np.bincount(labels.ravel())
        patches = sizes[1:]
        missed = chance_missed(patches * f * f, own_density)
        kept = int(patches[(patches >= min_patch_cells) & (missed < MISSED_CHANCE)].sum())
        return kept / int(footprint.sum())


def _openings(own: np.ndarray, own_keys: np.ndarray, own_density: float, interior: _InteriorView, ground: float,
              lo, c: float, width: int, settings: SurfaceSettings) -> dict:
    """`quakescan.change.openings` of one building from the returns around it: the pre-event
    density of its own returns, the post-event density of the returns over its cells."""
    from .openings import OPENING_REACH_M, opening_descriptors

    own_lo, own_hi = row_bounds(own[:, :2])
    pre = interior.pre.in_box(own_lo - OPENING_REACH_M, own_hi + OPENING_REACH_M)
    post = interior.post.in_box(own_lo - OPENING_REACH_M, own_hi + OPENING_REACH_M)
    keys = (np.floor((post[:, 0] - lo[0]) / c).astype(np.int64) * width
            + np.floor((post[:, 1] - lo[1]) / c).astype(np.int64))
    over = np.isin(keys, np.unique(own_keys))
    d_post = planimetric_density(post[over]) if over.any() else 0.0
    return opening_descriptors(own, pre, post, ground, own_density, d_post, settings.min_share)


def _building_view(own: np.ndarray, own_keys: np.ndarray, own_density: float, interior: _InteriorView,
                   ground: float, lo, c: float, width: int, settings: SurfaceSettings) -> registry.BuildingView:
    own_lo, own_hi = row_bounds(own[:, :2])

    def post_over() -> np.ndarray:
        post = interior.post.in_box(own_lo - c, own_hi + c)  # every point of the building's cells
        keys = (np.floor((post[:, 0] - lo[0]) / c).astype(np.int64) * width
                + np.floor((post[:, 1] - lo[1]) / c).astype(np.int64))
        return post[np.isin(keys, np.unique(own_keys))]

    return registry.BuildingView(own=own, ground=ground, density=own_density, cell_m=c, settings=settings,
                                 pre_near=lambda reach: interior.pre.in_box(own_lo - reach, own_hi + reach),
                                 post_near=lambda reach: interior.post.in_box(own_lo - reach, own_hi + reach),
                                 post_over=post_over)


def _facades(own: np.ndarray, interior: _InteriorView, building_keys, ground: float, lo, c: float,
             width: int) -> dict:
    """`quakescan.change.facade_sampling` of one building: its facades' area and how densely
    each epoch sampled them (returns per m² of facade)."""
    from .facade_sampling import facade_densities

    own_lo, own_hi = row_bounds(own[:, :2])
    reach = 2.0 * c
    walls = facade_densities(own, interior.pre.in_box(own_lo - reach, own_hi + reach),
                             interior.post.in_box(own_lo - reach, own_hi + reach), building_keys, ground, lo, c, width)
    return {"wall_density_pre": round(walls.pre, 3), "wall_density_post": round(walls.post, 3),
            "facade_m2": round(walls.area_m2, 1), "wall_facings": [list(f) for f in walls.facings]}


def chance_missed(area_m2, pre_density: float):
    """Chance that the pre-event epoch, sampling at `pre_density` (pts/m²), put no point on a
    surface of `area_m2` that was there and in view: its hits there are Poisson with mean
    area x density, exp(-mean) of them zero."""
    return np.exp(-np.asarray(area_m2, dtype=np.float64) * pre_density)


class _GroundFinder:
    """Ground height near a building: the 10th percentile of the ground points (ASPRS 2) within
    `search_m` of its points, or the 2nd percentile of every point there when the cloud has no
    ground class (or too few ground points nearby)."""

    def __init__(self, every: _XSorted, ground_xyz: np.ndarray | None, search_m: float):
        self.search = search_m
        self.sets = ([(_XSorted(ground_xyz), False)] if ground_xyz is not None and len(ground_xyz) else []) \
            + [(every, True)]

    def height(self, pts: np.ndarray) -> float:
        lo, hi = row_bounds(pts[:, :2])
        lo, hi = lo - self.search, hi + self.search
        for sorted_pts, is_all in self.sets:
            cand = sorted_pts.in_box(lo, hi)
            if is_all:
                return float(np.percentile(cand[:, 2], 2))
            if len(cand) >= 3:
                return float(np.percentile(cand[:, 2], 10))
        raise AssertionError("unreachable: the last set holds every point")


def _raster(keys_b, own_tops, pre_tops, post_tops, building_keys, ground, n3, ring_offsets, s: SurfaceSettings, c,
            width):
    """Raster descriptors of one building (its cells: `keys_b`) and the cells around it, and
    the keys of its outline and step cells.

    Lowering is measured from the building's *own* pre-event surface (`own_tops`: its points,
    by footprint on real data) to whatever is there after (`post_tops`, every point): a cell at
    a party wall also holds the neighbour's roof, and the neighbour's collapse is not this
    building's. Rises compare with every pre-event point, so that a taller intact neighbour
    does not read as a rise."""
    z, reg = s.m3c2.z, s.m3c2.registration_error_m
    cells = np.unique(keys_b)
    nb = cells[:, None] + n3[None, :]
    i_pre, i_post = own_tops.index(cells), post_tops.index(cells)
    pre_top, post_top = own_tops.lookup(cells), post_tops.lookup(cells)
    h_pre = np.maximum(pre_top - ground, 0.0)
    pre_nb = own_tops.lookup(nb)
    post_nb_max, j_post = _row_argmax(post_tops.lookup(nb))
    pre_nb_max, _ = _row_argmax(pre_nb)
    all_nb_max, j_all = _row_argmax(pre_tops.lookup(nb))
    # outline cells (a neighbour outside the building) and steps of the roof are compared with
    # the highest cell of the other epoch's 3x3 neighbourhood: one sampling may catch an eave
    # or a dormer wall that the other misses by a few centimetres
    in_building = np.isin(nb, cells)
    with np.errstate(invalid="ignore"):
        step = (pre_nb_max + _row_max(-pre_nb)) > 3 * c  # max - min of the 3x3 pre-event tops
    edge = ~in_building.all(axis=1) | step
    rows = np.arange(len(cells))
    i_post_cmp = np.where(edge, post_tops.index(nb[rows, j_post]), i_post)
    i_all_cmp = np.where(edge, pre_tops.index(nb[rows, j_all]), pre_tops.index(cells))
    post_cmp = np.where(edge, post_nb_max, post_top)
    all_cmp = np.where(edge, all_nb_max, pre_tops.lookup(cells))
    covered = ~np.isnan(post_top)
    with np.errstate(invalid="ignore"):
        # levels of detection of the two differences (M3C2's form on the cells' top layers)
        lod_low = z * (np.sqrt(own_tops.variance_of_mean(i_pre) + post_tops.variance_of_mean(i_post_cmp)) + reg)
        lod_raise = z * (np.sqrt(pre_tops.variance_of_mean(i_all_cmp) + post_tops.variance_of_mean(i_post)) + reg)
        lowered = pre_top - post_cmp
        # an inner cell where a good share of its own pre-event points already lay at the
        # post-event top held two surfaces (a roof step, a light well): a sparser post-event
        # sampling that caught only the lower one is no lowering (AHN3 tile vs its 25 % thinning:
        # a 2.7 m roof step read as a 3-cell collapse). A wall through the cell spreads its
        # points over every height and stays below the share; outline cells compare with their
        # 3 x 3 neighbourhood instead.
        lowered = np.where(~edge & (own_tops.share_within(i_pre, post_cmp, s.top_layer_m + np.nan_to_num(lod_low))
                                    >= LOWER_SURFACE_SHARE), 0.0, lowered)
        raised = post_top - all_cmp
        low = np.where(lowered > lod_low, lowered, 0.0)
        rise = np.where(raised > lod_raise, raised, 0.0)
    low, rise = np.nan_to_num(low, nan=0.0), np.nan_to_num(rise, nan=0.0)
    # a roof hole smaller than a cell leaves the cell's top on the roof, but the post-event points
    # seen through it lie below anything the pre-event epoch saw around the cell. Inner cells
    # only, SEE_THROUGH_INSET_M from the outline: there a sensor that saw walls (or under
    # the eaves) lower down after the event than before, a drone after an airborne archive,
    # would read as holes
    inner = ~step & _inset(cells, width, max(2, int(math.ceil(SEE_THROUGH_INSET_M / c))))
    with np.errstate(invalid="ignore"):
        depth = -_row_max(-own_tops.lowest(nb)) - post_tops.lowest(cells)
        through = inner & (depth > np.maximum(SEE_THROUGH_M, np.nan_to_num(lod_low)))
    # a 95 % test flags single cells of an unchanged roof at random; damage is areal
    low = np.where(_in_patches(cells, low > 0, width, s.min_patch_cells), low, 0.0)
    rise = np.where(_in_patches(cells, rise > 0, width, s.min_patch_cells), rise, 0.0)
    through = _in_patches(cells, through, width, s.min_patch_cells)
    out = {
        "s_lowered_1m": float(np.mean(low > 1.0)),
        "s_lowered_storey": float(np.mean(low > s.storey_m)),
        "s_lowered_half": float(np.mean((low > 0.5 * h_pre) & (h_pre > 1.0))),
        "s_raised": float(np.mean(rise > s.raised_m)),
        # sampling leaves single empty cells in a sparse epoch; an unobserved area is a patch
        "s_post_gap": float(_in_patches(cells, ~covered, width, s.min_patch_cells).mean()),
        "s_see_through": float(np.mean(through)),
    }
    vol = float(np.sum(h_pre)) * c * c
    out["s_volume_loss"] = float(np.sum(np.clip(low, 0.0, h_pre)) * c * c / vol) if vol > 0 else 0.0
    out["s_volume_gain"] = float(np.sum(rise) * c * c / vol) if vol > 0 else 0.0
    tall = covered & (h_pre > 1.0)
    # divided by the cell's own height: `tall` keeps it above 1 m (a building lower than one
    # sparse raster cell kept its height at ratio 1, not h / cell)
    ratio = np.clip((h_pre[tall] - low[tall] + rise[tall]) / h_pre[tall], 0.0, 1.5)
    out["s_height_ratio_mean"] = float(np.mean(ratio)) if len(ratio) else 1.0
    out["s_height_ratio_p10"] = float(np.percentile(ratio, 10)) if len(ratio) else 1.0
    edge_keys = cells[edge]
    # debris: a ring around the outline, other buildings' cells excluded, compared with the
    # highest pre-event cell around (vegetation and cars are sampled differently each time)
    outline = cells[~in_building.all(axis=1)]
    ring = np.unique((outline[:, None] + ring_offsets[None, :]).ravel())
    ring = ring[~np.isin(ring, building_keys)]
    pre_ring, j_ring = _row_argmax(pre_tops.lookup(ring[:, None] + n3[None, :]))
    i_ring_pre = pre_tops.index(ring + n3[j_ring])
    i_ring_post = post_tops.index(ring)
    with np.errstate(invalid="ignore"):
        up = post_tops.lookup(ring) - np.where(np.isnan(pre_ring), ground, pre_ring)
        var = np.nan_to_num(pre_tops.variance_of_mean(i_ring_pre), nan=0.0) + post_tops.variance_of_mean(i_ring_post)
        up = np.where(up > z * (np.sqrt(var) + reg), up, 0.0)
    up = np.where(_in_patches(ring, np.nan_to_num(up) > 0, width, s.min_patch_cells), up, 0.0)
    seen = i_ring_post >= 0
    out["s_debris_ring"] = float(np.mean(up[seen] > s.debris_rise_m)) if seen.any() else 0.0
    out["s_debris_volume"] = (float(np.sum(np.clip(up[seen], 0, None)) * c * c / vol)
                              if vol > 0 and seen.any() else 0.0)
    return out, edge_keys


def _row_max(a):
    """Row-wise maximum ignoring NaN; NaN for an all-NaN row (without numpy's warning)."""
    m = np.max(np.where(np.isnan(a), -np.inf, a), axis=1)
    return np.where(np.isinf(m), np.nan, m)


# shares of the footprint (or volumes relative to the building's): the dead zone applies. Not to
# the core-point shares: those are over roofs and walls together, where a 2 x 2 m roof hole in
# a 10 x 10 x 6 m box is 0.5 % of the surface but 4 % of its roof
SHARES = ("s_lowered_1m", "s_lowered_storey", "s_lowered_half", "s_raised", "s_volume_loss", "s_volume_gain",
          "s_post_gap", "s_debris_ring", "s_debris_volume", "s_see_through", "s_interior_seen")


def _dead_zone(d: dict, min_share: float) -> None:
    for k in SHARES:
        if k in d and abs(d[k]) < min_share:
            d[k] = 0.0


def _inset(cells: np.ndarray, width: int, radius_cells: int) -> np.ndarray:
    """Per cell (integer keys i * width + j): whether every cell within `radius_cells` (a
    square) belongs to the building too, counting single empty cells that sampling leaves
    inside a sparse epoch's footprint as the building's (a 3 x 3 closing; a courtyard is
    wider and stays outside)."""
    from scipy import ndimage

    i, j = np.divmod(cells, width)
    pad = radius_cells + 2
    i, j = i - i.min() + pad, j - j.min() + pad
    grid = np.zeros((i.max() + pad + 1, j.max() + pad + 1), bool)
    grid[i, j] = True
    closed = ndimage.binary_closing(grid, structure=np.ones((3, 3), bool)) | grid
    inner = ndimage.binary_erosion(closed, structure=np.ones((2 * radius_cells + 1,) * 2, bool))
    return inner[i, j]


def _in_patches(cells: np.ndarray, mask: np.ndarray, width: int, min_cells: int) -> np.ndarray:
    """`mask` where its cell belongs to an 8-connected group of at least `min_cells` masked cells
    (cells: integer keys i * width + j)."""
    if min_cells <= 1 or not mask.any():
        return mask
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keys = cells[mask]
    a, b = [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == dj == 0:
                continue
            nk = keys + di * width + dj
            pos = np.minimum(np.searchsorted(keys, nk), len(keys) - 1)
            hit = keys[pos] == nk
            a.append(np.flatnonzero(hit))
            b.append(pos[hit])
    a, b = np.concatenate(a), np.concatenate(b)
    _, labels = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(len(keys), len(keys))),
                                     directed=False)
    out = mask.copy()
    out[mask] = np.bincount(labels)[labels] >= min_cells
    return out
