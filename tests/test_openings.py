"""Openings seen through a roof per return (`quakescan.change.openings`), in closed form.

A 10 x 10 m flat roof 6 m up, sampled by Poisson returns at airborne and drone densities:
an opening's share of the inner returns is its share of the inner area; a rescan shows
nothing; a light well both epochs see is explained by the swapped null; scattered openings
and one collapse to the ground read apart."""
import math

import numpy as np
import pytest

from quakescan.change.openings import (INSET_M, OPENING_DESCRIPTORS, neighbourhood_radius, opening_descriptors,
                                       sampling_floor)

ROOF_Z = 6.0
INNER_AREA = (10.0 - 2 * INSET_M) ** 2


def roof(rng, density, holes=(), floor_z=3.0, wells=()):
    """Returns on the 10 x 10 m roof; inside each of `holes` (x0, y0, x1, y1) they lie on a
    floor at `floor_z` instead; inside each of `wells` on the ground (0 m)."""
    n = rng.poisson(density * 100)
    xyz = np.c_[rng.uniform(0, 10, (n, 2)), np.full(n, ROOF_Z) + rng.normal(0, 0.02, n)]
    for boxes, z in ((holes, floor_z), (wells, 0.0)):
        for x0, y0, x1, y1 in boxes:
            inside = (xyz[:, 0] > x0) & (xyz[:, 0] < x1) & (xyz[:, 1] > y0) & (xyz[:, 1] < y1)
            xyz[inside, 2] = z + rng.normal(0, 0.02, inside.sum())
    return xyz


def describe(pre, post, d_pre, d_post):
    return opening_descriptors(pre, pre, post, 0.0, d_pre, d_post, min_share=0.005)


def test_the_neighbourhood_holds_three_pre_event_returns_at_any_density():
    assert neighbourhood_radius(1.0) == pytest.approx(math.sqrt(3 / math.pi))
    assert neighbourhood_radius(4.0) == pytest.approx(math.sqrt(3 / (4 * math.pi)))  # 0.489 m
    assert neighbourhood_radius(100.0) == 0.25  # sqrt(3 / 100 pi) = 0.098 < the 0.25 m floor
    assert neighbourhood_radius(float("nan")) == 0.25
    assert sampling_floor() == pytest.approx(math.exp(-3))


@pytest.mark.parametrize("density", [4.0, 20.0, 200.0])
def test_an_opening_falls_by_its_share_of_the_inner_area_at_every_density(density):
    rng = np.random.default_rng(int(density))
    pre = roof(rng, density)
    post = roof(rng, density, holes=[(3.5, 3.5, 6.5, 6.5)])
    d = describe(pre, post, density, density)
    share = 9.0 / INNER_AREA
    n = density * INNER_AREA
    tol = 4 * math.sqrt(share * (1 - share) / n) + 0.02  # sampling spread; the rim within a spacing
    assert d["o_fallen"] == pytest.approx(share, abs=tol)
    assert d["o_fallen_null"] == 0.0
    assert d["o_fallen_excess"] > share - tol - 0.03
    assert d["o_fallen_ground"] == 0.0  # the storey below, not the ground
    assert d["o_fallen_largest"] == pytest.approx(d["o_fallen"], abs=0.01)
    assert d["o_fallen_scatter"] < 0.05
    assert set(d) == set(OPENING_DESCRIPTORS)


@pytest.mark.parametrize("density", [2.0, 4.0, 50.0])
def test_an_unchanged_rescan_shows_no_fall(density):
    rng = np.random.default_rng(7)
    d = describe(roof(rng, density), roof(rng, density), density, density)
    assert all(v == 0.0 for v in d.values()), d


def test_a_light_well_both_epochs_see_is_explained_by_the_swapped_null():
    rng = np.random.default_rng(8)
    wells = [(4.0, 4.0, 6.0, 6.0)]
    d = describe(roof(rng, 4.0, wells=wells), roof(rng, 4.0, wells=wells), 4.0, 4.0)
    # returns near the well's rim fall for want of a pre-event return on the well within r: both ways
    assert d["o_fallen_excess"] == 0.0
    assert abs(d["o_fallen"] - d["o_fallen_null"]) < 0.02


def test_scattered_openings_and_one_collapse_to_the_ground_read_apart():
    rng = np.random.default_rng(9)
    pre = roof(rng, 4.0)
    holes = [(1.5, 1.5, 3.0, 3.0), (6.5, 1.5, 8.2, 3.2), (1.5, 6.5, 3.2, 8.2), (6.8, 6.8, 8.5, 8.5),
             (4.2, 4.2, 5.8, 5.8)]
    scattered = describe(pre, roof(rng, 4.0, holes=holes), 4.0, 4.0)
    collapse = describe(pre, roof(rng, 4.0, holes=[(0.0, 0.0, 5.0, 10.0)], floor_z=0.5), 4.0, 4.0)
    assert scattered["o_fallen_scatter"] > 0.5 and collapse["o_fallen_scatter"] < 0.05
    assert scattered["o_fallen_ground"] == 0.0 and collapse["o_fallen_ground"] == 1.0
    assert collapse["o_fallen_largest"] > 2 * scattered["o_fallen_largest"]


def test_a_stray_return_below_the_roof_is_no_opening():
    rng = np.random.default_rng(10)
    pre = roof(rng, 4.0)
    post = roof(rng, 4.0)
    post = np.r_[post, [[5.0, 5.0, 2.0]]]  # a multipath echo 4 m under the roof
    assert describe(pre, post, 4.0, 4.0)["o_fallen"] == 0.0


def _slot(rng, density, wall_density=0.0, width=0.4, depth=4.0):
    """The roof with a narrow slot (x 5..5+width, y 2..8) `depth` deep: a gap between two roof
    parts or a light well. A laser's oblique pulses put nothing into it; a photo flight
    reconstructs its two walls (`wall_density` pts/m²), not its floor."""
    xyz = roof(rng, density)
    xyz = xyz[~((xyz[:, 0] > 5.0) & (xyz[:, 0] < 5.0 + width) & (xyz[:, 1] > 2.0) & (xyz[:, 1] < 8.0))]
    walls = [xyz]
    for x in (5.0, 5.0 + width):
        n = rng.poisson(wall_density * 6.0 * depth)
        walls.append(np.c_[np.full(n, x), rng.uniform(2.0, 8.0, n), rng.uniform(ROOF_Z - depth, ROOF_Z - 0.05, n)])
    return np.concatenate(walls)


@pytest.mark.parametrize("d_pre", [4.0, 50.0])
@pytest.mark.parametrize("width", [0.3, 0.6])
def test_the_walls_of_a_slot_a_photo_flight_saw_and_a_laser_did_not_have_not_fallen(d_pre, width):
    """A drone photo flight after a laser reconstructs the walls of a narrow slot in the roof
    (60 pts/m², the laser none): their returns lie more than a metre below the roof's pre-event
    returns within r, with roof on both sides of them (without the wall rule 4-26 % of the
    inner returns read as fallen); each has its wall's returns just above it, so none counts.
    An opening in the roof beside the same slot is still seen."""
    rng = np.random.default_rng(12)
    pre = _slot(rng, d_pre, width=width)
    d = describe(pre, _slot(rng, 60.0, wall_density=60.0, width=width), d_pre, 60.0)
    assert d["o_fallen"] == 0.0 and d["o_fallen_excess"] == 0.0, d
    post = _slot(rng, 60.0, wall_density=60.0, width=width)
    x0, y0, x1, y1 = 6.5, 3.5, 8.5, 6.5
    inside = (post[:, 0] > x0) & (post[:, 0] < x1) & (post[:, 1] > y0) & (post[:, 1] < y1)
    post[inside, 2] = 3.0
    share = (x1 - x0) * (y1 - y0) / INNER_AREA
    assert describe(pre, post, d_pre, 60.0)["o_fallen_excess"] == pytest.approx(share, abs=0.04)


def test_a_building_without_returns_inside_its_inset_has_zeros():
    rng = np.random.default_rng(11)
    tiny = np.c_[rng.uniform(0, 1.2, (20, 2)), np.full(20, ROOF_Z)]
    assert describe(tiny, tiny, 4.0, 4.0) == {k: 0.0 for k in OPENING_DESCRIPTORS}
    assert describe(tiny, np.zeros((0, 3)), 4.0, 0.0) == {k: 0.0 for k in OPENING_DESCRIPTORS}


@pytest.mark.slow
def test_random_halves_of_a_real_tile_show_no_fall_beyond_the_swapped_null(shared_data, tmp_path):
    """AHN3 tile 2 in two random halves (~4 pts/m² each), nothing changed: each half puts a few
    returns on low surfaces the other missed (o_fallen up to 9 % on a building), and the swapped
    count explains every one of them (no excess on any building)."""
    import laspy

    from quakescan.change.pipeline import describe_pair
    from quakescan.change.settings import settings_for_descriptors
    from quakescan.change.surface import SURFACE_DESCRIPTORS
    from quakescan.formats.pair import load_pair

    las = laspy.read(shared_data / "ahn3_cropped_2.laz")
    settings = settings_for_descriptors(SURFACE_DESCRIPTORS, 1.5)
    for seed in (5, 7):
        half = np.random.default_rng(seed).random(len(las.points)) < 0.5
        paths = []
        for name, mask in (("pre", half), ("post", ~half)):
            sub = laspy.LasData(las.header)
            sub.points = las.points[mask]
            sub.write(tmp_path / f"{seed}_{name}.las")
            paths.append(tmp_path / f"{seed}_{name}.las")
        pair = load_pair(*paths, shared_data / "ahn3_footprints_rd.geojson")
        rows = [r for r in describe_pair(pair.pre, pair.post, settings, workers=2) if r.assessable]
        assert len(rows) >= 20
        assert all(r.descriptors["o_fallen_excess"] == 0.0 for r in rows), seed


def test_on_a_wall_is_the_brute_force_answer():
    """`on_a_wall` (pairs within reach found at once) against every pair of returns checked one
    by one, on a random cloud of walls, roofs and floors: the same answer for every return."""
    from quakescan.change.openings import STACK_HIGH_M, STACK_LOW_M, STACK_RADIUS_M, STACK_STEEPNESS
    from quakescan.change.openings import _on_a_wall as on_a_wall

    rng = np.random.default_rng(7)
    floor = np.column_stack([rng.uniform(0, 6, 400), rng.uniform(0, 6, 400), rng.normal(0.0, 0.02, 400)])
    roof = np.column_stack([rng.uniform(0, 6, 400), rng.uniform(0, 6, 400), rng.normal(3.0, 0.02, 400)])
    wall = np.column_stack([np.full(300, 3.0) + rng.normal(0, 0.02, 300), rng.uniform(0, 6, 300),
                            rng.uniform(0, 3, 300)])
    pts = np.vstack([floor, roof, wall])
    flag = rng.random(len(pts)) < 0.5
    spacing = 0.3
    got = on_a_wall(pts, pts, flag, spacing)
    radius = max(STACK_RADIUS_M, spacing)
    want = np.zeros(len(pts), bool)
    for i in np.flatnonzero(flag):
        rel = pts - pts[i]
        across = np.hypot(rel[:, 0], rel[:, 1])
        dz = rel[:, 2]
        want[i] = bool(np.any((across <= radius) & (dz > STACK_LOW_M) & (dz <= STACK_HIGH_M)
                              & (dz >= STACK_STEEPNESS * across)))
    np.testing.assert_array_equal(got, want)
    assert want[flag & (np.arange(len(pts)) >= 800)].mean() > 0.5  # the wall's lower returns are on it
    assert not got[~flag].any()


def _fallen_by_definition(query, reference, radius):
    """`_fallen` spelt out by sorting every distance: the MAX_NEIGHBOURS nearest reference
    returns within SURROUND_REACH radii, fallen when those within `radius` (one at least) all
    lie more than SEE_THROUGH_M above, then surrounded by the ones above it."""
    from quakescan.change.openings import (MAX_NEIGHBOURS, SEE_THROUGH_M, SURROUND_MAX, SURROUND_MIN_RETURNS,
                                           SURROUND_REACH)

    out = np.zeros(len(query), bool)
    for i, q in enumerate(query):
        d = np.hypot(*(reference[:, :2] - q[:2]).T)
        order = np.argsort(d, kind="stable")[:MAX_NEIGHBOURS]
        order = order[d[order] <= SURROUND_REACH * radius]
        near = order[d[order] <= radius]
        if not len(near) or not q[2] < reference[near, 2].min() - SEE_THROUGH_M:
            continue
        above = order[reference[order, 2] > q[2] + SEE_THROUGH_M]
        v = reference[above, :2] - q[:2]
        norm = np.hypot(*v.T)
        v, norm = v[norm > 0], norm[norm > 0]
        mean = np.hypot(*(v / norm[:, None]).sum(axis=0)) / max(len(above), 1)
        out[i] = len(above) >= SURROUND_MIN_RETURNS and mean <= SURROUND_MAX
    return out


@pytest.mark.parametrize("density", [4.0, 40.0, 150.0])
def test_the_one_neighbour_shortcut_finds_exactly_the_returns_the_definition_finds(density):
    """`_fallen` asks one neighbour first and MAX_NEIGHBOURS only of the returns it leaves:
    the same returns as the definition, on a roof with an opening, a light well at the rim
    and stray low returns (so every branch is taken)."""
    from quakescan.change.openings import _fallen, neighbourhood_radius

    rng = np.random.default_rng(int(density))
    pre = roof(rng, density, wells=[(0.0, 4.0, 1.0, 5.0)])
    post = roof(rng, density, holes=[(3.0, 3.0, 5.0, 6.0)], wells=[(0.0, 4.0, 1.0, 5.0)])
    post = np.vstack([post, np.c_[rng.uniform(-1, 11, (40, 2)), rng.uniform(0, 6, 40)]])
    post = post[rng.permutation(len(post))[:2000]]
    r = neighbourhood_radius(density)
    got, want = _fallen(post, pre, r), _fallen_by_definition(post, pre, r)
    assert want.sum() > 10 and (~want).sum() > 10
    assert np.array_equal(got, want)


@pytest.mark.parametrize("density", [4.0, 150.0])
def test_the_compiled_fall_and_surround_test_gives_numpys_answers_to_the_bit(density):
    """`_opening_kernels.fallen_and_surrounded` against `_fallen_reference` on the same kd-tree
    answer: the same returns, and the mean direction's length to the last bit."""
    from scipy.spatial import cKDTree

    from quakescan.change._opening_kernels import fallen_and_surrounded
    from quakescan.change.openings import (MAX_NEIGHBOURS, SEE_THROUGH_M, SURROUND_MAX, SURROUND_MIN_RETURNS,
                                           SURROUND_REACH, _fallen_reference, _surround_mean)

    rng = np.random.default_rng(7)
    pre = roof(rng, density, wells=[(0.0, 4.0, 1.0, 5.0)])
    post = roof(rng, density, holes=[(3.0, 3.0, 5.0, 6.0)], wells=[(0.0, 4.0, 1.0, 5.0)])
    post = np.vstack([post, np.c_[rng.uniform(-1, 11, (40, 2)), rng.uniform(0, 6, 40)]])
    r = neighbourhood_radius(density)
    dist, idx = cKDTree(pre[:, :2]).query(post[:, :2], k=MAX_NEIGHBOURS, distance_upper_bound=SURROUND_REACH * r)
    got, mean = fallen_and_surrounded(post, pre, dist, idx, r, SEE_THROUGH_M, SURROUND_MIN_RETURNS, SURROUND_MAX)
    want = _fallen_reference(post, pre, dist, idx, r)
    assert want.sum() > 10 and np.array_equal(got, want)
    fell = np.isfinite(mean)
    assert fell.sum() > want.sum()  # some fell but are not surrounded: the light well's rim
    want_mean, _ = _surround_mean(post[fell], pre, dist[fell], idx[fell])
    assert np.array_equal(mean[fell], want_mean)


@pytest.mark.parametrize("density", [4.0, 150.0])
def test_the_compiled_wall_search_finds_the_walls_the_kd_tree_pairs_find(density):
    """`_on_a_wall` (a compiled search of the cells around each flagged return) against
    `_on_a_wall_reference` (every pair within the radius from two kd-trees), on returns
    under a 6 m wall, under a gentle slope, beside the wall at the radius, and in the open."""
    from quakescan.change.openings import _on_a_wall, _on_a_wall_reference, spacing

    rng = np.random.default_rng(11)
    n = int(density * 40)
    wall = np.c_[np.full(n, 5.0) + rng.normal(0, 0.03, n), rng.uniform(0, 10, n), rng.uniform(0, 6, n)]
    slope_xy = rng.uniform(0, 10, (n, 2))
    slope = np.c_[slope_xy + [10, 0], 0.4 * slope_xy[:, 0]]  # 22°: not a wall
    own = np.vstack([wall, slope, roof(rng, density)])
    query = np.c_[rng.uniform(-1, 21, (3000, 2)), rng.uniform(-0.5, 5, 3000)]
    flag = rng.random(3000) < 0.7
    d = spacing(density)
    got, want = _on_a_wall(query, own, flag, d), _on_a_wall_reference(query, own, flag, d)
    assert want.sum() > 20 and (flag & ~want).sum() > 20 and not (got & ~flag).any()
    assert np.array_equal(got, want)


def test_the_wall_search_of_a_footprint_kilometres_long_needs_no_grid_of_its_size():
    """Cells grow with the returns' extent (about as many cells as returns): returns 100 km apart
    in UTM-sized coordinates, which 0.25 m cells would need 1.6e11 of, are searched as the
    kd-tree pairs search them."""
    from quakescan.change.openings import _on_a_wall, _on_a_wall_reference

    rng = np.random.default_rng(3)
    base = np.array([500_000.0, 5_800_000.0, 0.0])
    wall = np.c_[np.full(200, 0.0), rng.uniform(0, 5, 200), rng.uniform(0, 6, 200)]
    own = np.vstack([wall, wall + [100_000.0, 0, 0]]) + base
    query = np.vstack([np.c_[rng.uniform(-0.3, 0.3, (50, 1)), rng.uniform(0, 5, (50, 1)), np.zeros((50, 1))],
                       np.c_[rng.uniform(2, 3, (50, 1)), rng.uniform(0, 5, (50, 1)), np.zeros((50, 1))]])
    query = np.vstack([query, query + [100_000.0, 0, 0]]) + base
    flag = np.ones(len(query), bool)
    got = _on_a_wall(query, own, flag, 0.5)
    assert np.array_equal(got, _on_a_wall_reference(query, own, flag, 0.5))
    assert got[:50].all() and not got[50:100].any() and got[100:150].all() and not got[150:].any()
