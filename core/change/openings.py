"""Openings seen through a roof at any density, and how what came down is laid out.

An airborne archive at 4 pts/m² puts a handful of returns into each roof opening of a
square metre or two. The raster descriptors of `quakescan.change.surface` need cells, insets
and patch sizes that such a handful never fills; this module asks the question per return:

**A post-event return has fallen** when it lies more than `SEE_THROUGH_M` below every
pre-event return within `r` of it, and at least one pre-event return lies within `r` (the
place was seen before). `r` is set by the pre-event density so that the disc holds
`EXPECTED_NEIGHBOURS` pre-event returns on average: `pi r² d = K`, `r = sqrt(K / (pi d))`
(at least `MIN_RADIUS_M`). Then the chance that the pre-event epoch had a surface there but
put no return on it, which alone makes an unchanged surface look fallen, is the same at every
density: `exp(-K · a)` for a lower surface covering a share `a` of the disc (Poisson sampling).

**The same question with the epochs swapped** (a pre-event return below every post-event
return within the post-event `r`) measures that chance on the building itself: on an
unchanged building both epochs sample the same surfaces and the two shares agree (exactly
in distribution for random halves of one acquisition); a light well, a terrace, a lower roof
part inside the outline give both. Damage that opens a roof gives only the first.

**Surrounded by what it fell through**: the pre-event returns above a fallen return (within
`SURROUND_REACH` radii) must lie all around it, the mean of their unit directions at most
`SURROUND_MAX` long: a roof surrounds what is seen through an opening in it, while the rim of a
light well or a recess, which one sensor sees lower down than another, lies on one side of it
(a half disc gives 2/pi = 0.64).

**Not on a wall**: a return with another return of its own epoch within one point spacing
(at least `STACK_RADIUS_M`) in x/y, `STACK_LOW_M`..`STACK_HIGH_M` above it and at least
`STACK_STEEPNESS` times as far up as across (a surface steeper than 63°) lies on a wall (the
step between two roof parts, a courtyard wall, a wall a collapse laid open), which a photo
flight reconstructs densely and a laser barely samples: it is not seen through anything. What
is seen through an opening has a storey's height of empty space above it, and debris rarely
lies steeper than its angle of repose (35-40°).

Only returns at least `INSET_M` inside the building's outline count (a wall seen by an
oblique pulse lies on the outline), and only **coherent** ones: a fallen return with another
fallen return within two post-event point spacings. A stray return (a bird, a multipath
echo) is alone; what is seen through an opening is areal.

Descriptors (shares are of the building's inner returns; lengths never enter):

- `o_fallen`: share of inner post-event returns fallen (coherent);
- `o_fallen_null`: the same with the epochs swapped;
- `o_fallen_excess`: the fallen share beyond what the null explains at 99 % (one-sided
  binomial bound: `k/n - p0 - z sqrt(p0 (1 - p0) / n)`, `p0` the null share and at least one
  return in `n`), 0 when not beyond;
- `o_fallen_ground`: share of the fallen returns within `GROUND_BAND_M` of the ground: a
  collapse brings the roof down to the ground, an opening shows the storey below;
- `o_fallen_largest`: the largest patch of fallen returns (cells of 1.5 post-event spacings,
  8-connected) as a share of the inner returns: one contiguous collapse against many openings;
- `o_fallen_scatter`: the share of the fallen returns outside the largest patch: 0 for one
  contiguous region, towards 1 for scattered openings with the roof standing between them.
"""
from __future__ import annotations

import math

import numpy as np

from .descriptors import names_of as family_names

# the names and the version (OPENINGS_VERSION) of these descriptors: quakescan.change.descriptors
OPENING_DESCRIPTORS = family_names("openings")
SEE_THROUGH_M = 1.0
EXPECTED_NEIGHBOURS = 3.0
MIN_RADIUS_M = 0.25
MAX_NEIGHBOURS = 32
# the surface a return fell through is looked for within this many radii (12 returns expected),
# and must surround it: at least this many returns above it whose mean direction is this short
SURROUND_REACH = 2.0
SURROUND_MIN_RETURNS = 3
SURROUND_MAX = 0.5
INSET_M = 0.75
STACK_RADIUS_M = 0.25
STACK_LOW_M = 0.3
STACK_HIGH_M = 2.0
STACK_STEEPNESS = 2.0
# the returns of both epochs read around a building: its neighbourhood radius at the sparsest densities
OPENING_REACH_M = 3.0
OUTLINE_CELL_M = 0.5
GROUND_BAND_M = 1.5
# one-sided 99 % normal quantile of the binomial bound
Z_99 = 2.326


def neighbourhood_radius(density: float) -> float:
    """`r` with EXPECTED_NEIGHBOURS returns expected within it at `density` pts/m²."""
    if not (math.isfinite(density) and density > 0):
        return MIN_RADIUS_M
    return max(MIN_RADIUS_M, math.sqrt(EXPECTED_NEIGHBOURS / (math.pi * density)))


def sampling_floor() -> float:
    """The closed-form chance that a return on a surface the other epoch saw falls for want of
    the other epoch's returns on it: exp(-K)."""
    return math.exp(-EXPECTED_NEIGHBOURS)


def spacing(density: float) -> float:
    return 1.0 / math.sqrt(density) if math.isfinite(density) and density > 0 else 1.0


def zeros() -> dict:
    return {n: 0.0 for n in OPENING_DESCRIPTORS}


def opening_descriptors(own_pre: np.ndarray, pre: np.ndarray, post: np.ndarray, ground_z: float,
                        density_pre: float, density_post: float, min_share: float = 0.0) -> dict:
    """The descriptors above for one building: `own_pre` its pre-event returns (footprint),
    `pre` / `post` every return of each epoch around it (local frame, float64)."""
    from scipy import ndimage

    out = zeros()
    if len(own_pre) == 0 or len(post) == 0:
        return out
    inner, lo, f = _inner_mask(own_pre, density_pre)
    if not inner.any():
        return out
    post_in = _inside(post, inner, lo, f, ground_z)
    pre_in = _inside(pre, inner, lo, f, ground_z)
    if len(post_in) == 0:
        return out
    fallen = _fallen(post_in, pre, neighbourhood_radius(density_pre))
    fallen &= ~_on_a_wall(post_in, post, fallen, spacing(density_post))
    fallen &= _coherent(post_in[:, :2], fallen, 2.0 * spacing(density_post))
    swapped = _fallen(pre_in, post, neighbourhood_radius(density_post)) if len(pre_in) else np.zeros(0, bool)
    if len(pre_in):
        swapped &= ~_on_a_wall(pre_in, pre, swapped, spacing(density_pre))
        swapped &= _coherent(pre_in[:, :2], swapped, 2.0 * spacing(density_pre))
    n, k = len(post_in), int(fallen.sum())
    share = k / n
    null = float(swapped.mean()) if len(swapped) else 0.0
    p0 = max(null, 1.0 / n)  # no building is judged against a null of exactly zero
    excess = share - p0 - Z_99 * math.sqrt(p0 * (1.0 - p0) / n)
    out["o_fallen"] = share
    out["o_fallen_null"] = null
    out["o_fallen_excess"] = max(0.0, excess)
    if k:
        out["o_fallen_ground"] = float(np.mean(post_in[fallen, 2] - ground_z < GROUND_BAND_M))
        # cells of 1.5 spacings: neighbouring fallen returns of one opening share or touch a cell
        g = max(OUTLINE_CELL_M, 1.5 * spacing(density_post))
        cells = np.floor((post_in[fallen, :2] - lo) / g).astype(np.int64)
        cells -= cells.min(axis=0)
        grid = np.zeros(tuple(cells.max(axis=0) + 1), np.int32)
        np.add.at(grid, tuple(cells.T), 1)
        labels, _ = ndimage.label(grid > 0, np.ones((3, 3), bool))
        returns = np.bincount(labels.ravel(), weights=grid.ravel())[1:]
        # measured in returns, not cells: a sparse sampling leaves a share of an opening's cells empty
        out["o_fallen_largest"] = float(returns.max()) / n
        out["o_fallen_scatter"] = 1.0 - float(returns.max()) / k
    if min_share:
        for name in ("o_fallen_null", "o_fallen_excess", "o_fallen_largest"):
            if out[name] < min_share:
                out[name] = 0.0
        if out["o_fallen"] < min_share:  # no fall at all: nothing to describe the layout of
            out.update(o_fallen=0.0, o_fallen_excess=0.0, o_fallen_ground=0.0, o_fallen_largest=0.0,
                       o_fallen_scatter=0.0)
    return out


def _inner_mask(own_pre: np.ndarray, density: float):
    """Cells (OUTLINE_CELL_M) at least INSET_M inside the outline of the building's pre-event
    returns (gaps of the sampling closed), and the grid's corner and cell size."""
    from scipy import ndimage

    f = OUTLINE_CELL_M
    pad = 4
    lo = np.floor(own_pre[:, :2].min(axis=0) / f) * f - pad * f
    shape = tuple(np.floor((own_pre[:, :2].max(axis=0) - lo) / f).astype(int) + pad + 1)
    grid = np.zeros(shape, bool)
    ij = np.floor((own_pre[:, :2] - lo) / f).astype(np.int64)
    grid[tuple(ij.T)] = True
    reach = max(1, int(math.ceil(spacing(density) / f)))
    # single empty cells of a sparse sampling are the building's; a courtyard stays outside
    grid = ndimage.binary_closing(grid, np.ones((3, 3), bool), iterations=reach) | grid
    inner = ndimage.distance_transform_edt(grid) * f - 0.5 * f >= INSET_M
    return inner, lo, f


def _inside(xyz: np.ndarray, inner: np.ndarray, lo: np.ndarray, f: float, ground_z: float) -> np.ndarray:
    ij = np.floor((xyz[:, :2] - lo) / f).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < np.array(inner.shape)), axis=1)
    ok[ok] = inner[ij[ok, 0], ij[ok, 1]]
    ok &= xyz[:, 2] > ground_z - GROUND_BAND_M  # below the ground is noise, not a floor
    return xyz[ok]


def _fallen(query: np.ndarray, reference: np.ndarray, radius: float) -> np.ndarray:
    """Query returns more than SEE_THROUGH_M below every reference return within `radius`,
    with at least one there, and surrounded by the surface they fell through (`_surrounded`)."""
    from scipy.spatial import cKDTree

    if len(reference) == 0 or len(query) == 0:
        return np.zeros(len(query), bool)
    tree = cKDTree(reference[:, :2])
    # The nearest reference return is among those within `radius` whenever any is, so a return
    # not SEE_THROUGH_M below its nearest one cannot have fallen: one neighbour decides for
    # nearly every return of a standing surface, and only the rest pay for MAX_NEIGHBOURS (the
    # openings took 56 % of a dense tile's time, 332 of 691 samples in this query).
    first, nearest = tree.query(query[:, :2], k=1, distance_upper_bound=radius)
    found = np.isfinite(first)
    fell = np.zeros(len(query), bool)
    fell[found] = query[found, 2] < reference[nearest[found], 2] - SEE_THROUGH_M
    if not fell.any():
        return fell
    candidates = np.flatnonzero(fell)
    k = min(MAX_NEIGHBOURS, len(reference))
    dist, idx = tree.query(query[candidates, :2], k=k, distance_upper_bound=SURROUND_REACH * radius)
    dist, idx = dist.reshape(len(candidates), -1), idx.reshape(len(candidates), -1)
    from ._opening_kernels import fallen_and_surrounded

    fell[candidates], _ = fallen_and_surrounded(np.ascontiguousarray(query[candidates], dtype=np.float64),
                                             np.ascontiguousarray(reference, dtype=np.float64), dist,
                                             idx.astype(np.int64, copy=False), float(radius), SEE_THROUGH_M,
                                             SURROUND_MIN_RETURNS, SURROUND_MAX)
    return fell


def _fallen_reference(query: np.ndarray, reference: np.ndarray, dist: np.ndarray, idx: np.ndarray,
                      radius: float) -> np.ndarray:
    """numpy's `_opening_kernels.fallen_and_surrounded`: of the query returns whose k nearest
    reference returns within SURROUND_REACH radii are `dist`/`idx`, those fallen and surrounded."""
    near = dist <= radius
    z = np.where(near, reference[np.minimum(idx, len(reference) - 1), 2], np.inf)
    fell = near.any(axis=1) & (query[:, 2] < z.min(axis=1) - SEE_THROUGH_M)
    if fell.any():
        fell[fell] = _surrounded(query[fell], reference, dist[fell], idx[fell])
    return fell


def _surrounded(query: np.ndarray, reference: np.ndarray, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Whether the reference returns above each query return (by SEE_THROUGH_M, within
    SURROUND_REACH radii) lie all around it: the mean of their unit directions is short
    (`SURROUND_MAX`). A roof around an opening surrounds what is seen through it; the rim of a
    light well or a deep recess, which one sensor sees lower down than another, lies on one side
    (a half disc gives 2/pi = 0.64)."""
    return _surround_mean(query, reference, dist, idx)[1]


def _surround_mean(query, reference, dist, idx):
    """(the mean length of the unit directions to the returns above, whether it surrounds)."""
    found = np.isfinite(dist)
    j = np.minimum(idx, len(reference) - 1)
    above = found & (reference[j, 2] > query[:, 2:3] + SEE_THROUGH_M)
    d = reference[j, :2] - query[:, None, :2]
    norm = np.linalg.norm(d, axis=2)
    unit = np.where((above & (norm > 0))[..., None], d / np.maximum(norm, 1e-12)[..., None], 0.0)
    n = above.sum(axis=1)
    mean = np.linalg.norm(unit.sum(axis=1), axis=1) / np.maximum(n, 1)
    return mean, (n >= SURROUND_MIN_RETURNS) & (mean <= SURROUND_MAX)


def _on_a_wall(query: np.ndarray, own_epoch: np.ndarray, flag: np.ndarray, point_spacing: float) -> np.ndarray:
    """Flagged query returns under a steep surface of their own epoch: a return of it within
    one point spacing (at least STACK_RADIUS_M) in x/y, STACK_LOW_M..STACK_HIGH_M above, and at
    least STACK_STEEPNESS times as far up as across (steeper than 63°: a wall)."""
    from ._opening_kernels import under_a_steep_surface

    out, sel, q, cand, radius = _wall_search(query, own_epoch, flag, point_spacing)
    if len(cand):
        out[sel] = under_a_steep_surface(np.ascontiguousarray(q, dtype=np.float64),
                                         np.ascontiguousarray(own_epoch[cand], dtype=np.float64), float(radius),
                                         STACK_LOW_M, STACK_HIGH_M, STACK_STEEPNESS)
    return out


def _on_a_wall_reference(query: np.ndarray, own_epoch: np.ndarray, flag: np.ndarray, point_spacing: float):
    """numpy's `_on_a_wall` (every pair within the radius at once, from two kd-trees)."""
    from scipy.spatial import cKDTree

    out, sel, q, cand, radius = _wall_search(query, own_epoch, flag, point_spacing)
    if len(cand):
        pairs = cKDTree(q[:, :2]).sparse_distance_matrix(cKDTree(own_epoch[cand, :2]), radius,
                                                         output_type="ndarray")
        i, across = pairs["i"], pairs["v"]
        dz = own_epoch[cand[pairs["j"]], 2] - q[i, 2]
        steep = (dz > STACK_LOW_M) & (dz <= STACK_HIGH_M) & (dz >= STACK_STEEPNESS * across)
        out[sel] = np.bincount(i[steep], minlength=len(sel)) > 0
    return out


def _wall_search(query, own_epoch, flag, point_spacing):
    """(all False, the flagged returns' indices and points, the indices of own-epoch returns
    within reach above the lowest and below the highest of them, the search radius)."""
    out = np.zeros(len(query), bool)
    sel = np.flatnonzero(flag)
    if not len(sel) or not len(own_epoch):
        return out, sel, query[:0], np.zeros(0, np.int64), 0.0
    q = query[sel]
    # only returns within reach above a flagged one can be the wall over it
    z = own_epoch[:, 2]
    cand = np.flatnonzero((z > q[:, 2].min() + STACK_LOW_M) & (z <= q[:, 2].max() + STACK_HIGH_M))
    return out, sel, q, cand, max(STACK_RADIUS_M, point_spacing)


def _coherent(xy: np.ndarray, flag: np.ndarray, radius: float) -> np.ndarray:
    """Flagged returns with another flagged return within `radius`."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(xy), bool)
    sel = np.flatnonzero(flag)
    if len(sel) < 2:
        return out
    tree = cKDTree(xy[sel])
    dist, _ = tree.query(xy[sel], k=2, distance_upper_bound=radius)
    out[sel] = np.isfinite(dist[:, 1])
    return out
