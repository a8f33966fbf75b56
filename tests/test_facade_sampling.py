"""Each epoch's returns per m² of a building's facades (`quakescan.change.facade_sampling`), in
closed form: a 10 x 10 x 9 m box whose walls are sampled at a known density."""
import numpy as np
import pytest

from quakescan.change.detectability import facings_resolve, walls_resolved, min_opening_m2
from quakescan.change.facade_sampling import BAND_BOTTOM_M, BAND_TOP_M, NO_FACADE, facade_densities

C = 0.5
LO = np.array([-20.0, -20.0])
WIDTH = 80


def _box(rng, roof_density, wall_density, top=9.0, unseen_side=None):
    """`unseen_side`: the index of a wall (0 south, 1 east, 2 north, 3 west) no return reached."""
    n = rng.poisson(roof_density * 100)
    roof = np.c_[rng.uniform(-5, 5, (n, 2)), np.full(n, top)]
    walls = []
    for side, (ax, ay, bx, by) in enumerate(((-5, -5, 5, -5), (5, -5, 5, 5), (5, 5, -5, 5), (-5, 5, -5, -5))):
        m = 0 if side == unseen_side else rng.poisson(wall_density * 10 * top)
        t = rng.uniform(0, 1, m)
        # just inside the outline, where a footprint assigns a wall's returns
        inward = -0.05 * np.sign(np.array([ax + bx, ay + by]))
        walls.append(np.c_[ax + t * (bx - ax) + inward[0], ay + t * (by - ay) + inward[1], rng.uniform(0, top, m)])
    return np.vstack([roof] + walls)


def _keys(xyz):
    return np.unique(np.floor((xyz[:, 0] - LO[0]) / C).astype(np.int64) * WIDTH
                     + np.floor((xyz[:, 1] - LO[1]) / C).astype(np.int64))


@pytest.mark.parametrize("wall_pre,wall_post", [(0.3, 40.0), (5.0, 5.0)])
def test_the_wall_densities_and_the_facade_area_are_what_was_sampled(wall_pre, wall_post):
    rng = np.random.default_rng(int(wall_pre * 10))
    pre, post = _box(rng, 10.0, wall_pre), _box(rng, 60.0, wall_post)
    d_pre, d_post, area, _ = facade_densities(pre, pre, post, _keys(pre), 0.0, LO, C, WIDTH)
    band = 9.0 - BAND_TOP_M - BAND_BOTTOM_M  # the eave at the roof's 9 m: every outline cell's top
    assert area == pytest.approx(40.0 * band, rel=0.01)
    for got, want in ((d_pre, wall_pre), (d_post, wall_post)):
        n = want * 40 * band
        assert got == pytest.approx(want, abs=4 * np.sqrt(n) / (40 * band) + 1e-9)


def test_a_neighbours_roof_beside_the_outline_is_no_wall_and_a_shed_has_no_facade():
    rng = np.random.default_rng(3)
    pre = _box(rng, 10.0, 0.0)
    # a lower neighbour against the east wall: its roof at 4 m, inside the band's heights
    n = 2000
    neighbour = np.c_[rng.uniform(5.0, 10.0, n), rng.uniform(-5, 5, n), np.full(n, 4.0)]
    every = np.vstack([pre, neighbour])
    d_pre, _, _, _ = facade_densities(pre, every, every, _keys(every), 0.0, LO, C, WIDTH)
    assert d_pre == 0.0
    shed = _box(rng, 10.0, 5.0, top=2.2)
    assert facade_densities(shed, shed, shed, _keys(shed), 0.0, LO, C, WIDTH) == NO_FACADE
    assert facade_densities(np.zeros((0, 3)), pre, pre, _keys(pre), 0.0, LO, C, WIDTH) == NO_FACADE


def test_each_open_facing_is_sampled_apart_and_one_unseen_facade_leaves_the_walls_unresolved():
    """Three walls sampled at 40 returns per m² and the fourth at none: the facades together
    resolve 2 % of their 160 m² band, the unseen one resolves nothing of its 40 m², so heavy
    damage confined to it could not have shown (the one-facade infill blow-out an airborne
    flight line never faced)."""
    rng = np.random.default_rng(11)
    pre = _box(rng, 10.0, 40.0, unseen_side=1)
    walls = facade_densities(pre, pre, pre, _keys(pre), 0.0, LO, C, WIDTH)
    band = 9.0 - BAND_TOP_M - BAND_BOTTOM_M
    assert len(walls.facings) == 4
    assert sorted(a for a, _, _ in walls.facings) == pytest.approx([10.0 * band] * 4, rel=0.06)
    densities = sorted(p for _, p, _ in walls.facings)
    assert densities[0] == 0.0 and densities[1] == pytest.approx(40.0, rel=0.2)
    assert walls_resolved(walls.area_m2, min_opening_m2(walls.pre, walls.post))  # pooled: resolved
    assert facings_resolve(walls.facings) is False
    seen = facade_densities(*(3 * (_box(rng, 10.0, 40.0),)), _keys(pre), 0.0, LO, C, WIDTH)
    assert facings_resolve(seen.facings) is True


def test_a_party_wall_is_no_facing():
    """A neighbour's cells against the east wall: that side shows nothing and hides nothing of
    its own, so only three facings are counted."""
    rng = np.random.default_rng(4)
    pre = _box(rng, 10.0, 40.0, unseen_side=1)
    n = 2000
    neighbour = np.c_[rng.uniform(5.0, 10.0, n), rng.uniform(-5, 5, n), np.full(n, 12.0)]
    walls = facade_densities(pre, pre, pre, np.union1d(_keys(pre), _keys(neighbour)), 0.0, LO, C, WIDTH)
    assert len(walls.facings) == 3 and min(p for _, p, _ in walls.facings) > 20.0
    assert facings_resolve(walls.facings) is True
