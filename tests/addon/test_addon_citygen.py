"""citygen: procedural layouts (pure Python)."""
import numpy as np
import pytest

from addon import city_plan, citygen
from addon.geometry import poly2d


@pytest.mark.parametrize("set_name", citygen.SETS)
def test_plan_is_seeded_and_has_no_overlaps(set_name):
    a = citygen.city_plan(set_name, 60, 5)
    b = citygen.city_plan(set_name, 60, 5)
    c = citygen.city_plan(set_name, 60, 6)
    assert [x.id for x in a.buildings] == list(range(1, 61))
    assert [(x.shell, x.location, x.rotation, x.seed) for x in a.buildings] == \
           [(x.shell, x.location, x.rotation, x.seed) for x in b.buildings]
    assert [x.location for x in a.buildings] != [x.location for x in c.buildings]
    assert citygen.overlaps(a) == []
    x0, y0, x1, y1 = a.bounds
    for bp in a.buildings:
        bx0, by0, bx1, by1 = bp.extent
        assert x0 < bx0 and bx1 < x1 and y0 < by0 and by1 < y1


def test_generic_variety():
    p = citygen.city_plan("generic", 112, 1)
    typ = {b.typology for b in p.buildings}
    assert {"detached_house", "terraced_house", "small_apartment", "apartment_block"} <= typ
    mats = {b.shell["material"] for b in p.buildings}
    assert mats == {"masonry", "reinforced_concrete"}
    roofs = {b.shell["roof"] for b in p.buildings}
    assert {"flat", "gable"} <= roofs
    storeys = [b.shell["storeys"] for b in p.buildings]
    assert min(storeys) <= 2 and max(storeys) >= 5


def test_region_is_laquila_like():
    p = citygen.city_plan("region", 112, 1)
    mas = [b for b in p.buildings if b.shell["material"] == "masonry"]
    assert len(mas) / len(p.buildings) > 0.7
    assert all(2 <= b.shell["storeys"] <= 4 for b in mas)
    assert all(b.shell["party_walls"] for b in p.buildings)  # attached in courtyard blocks


def test_mixed_grades_cover_targets():
    g = citygen.mixed_grades(list(range(1, 201)), 3)
    assert set(g.values()) >= {0, 3, 4, 5}
    assert g == citygen.mixed_grades(list(range(1, 201)), 3)


def test_bad_arguments():
    with pytest.raises(ValueError, match="set must be"):
        citygen.city_plan("suburb", 3, 0)
    with pytest.raises(ValueError, match=">= 1"):
        citygen.city_plan("generic", 0, 0)


def _plan(*buildings):
    """A hand-made plan of rectangles: (id, x0, y0, x1, y1, party walls)."""
    out = []
    for bid, x0, y0, x1, y1, party in buildings:
        L, W = x1 - x0, y1 - y0
        shell = {"footprint": [[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]]}
        if party:
            shell["party_walls"] = list(party)
        out.append(city_plan.BuildingPlan(bid, shell, ((x0 + x1) / 2, (y0 + y1) / 2), 0.0, "B", bid, "t",
                                        (x0, y0, x1, y1)))
    return city_plan.CityPlan(out, citygen._bounds(out), "test", 0)


def test_a_wall_facing_the_end_of_the_next_building_is_a_party_wall():
    # a courtyard block's corner: building 1 (8 x 8 m) along the street, building 2 on the
    # block's next side, its end wall 5 cm behind building 1's inner facade (edge 2, +y);
    # building 3 stands 4 m away across a yard: its facing wall stays a facade
    plan = citygen.mark_covered_walls(_plan((1, 0, 0, 8, 8, [1]), (2, 0, 8.05, 8, 20, None),
                                            (3, 12, 0, 20, 8, None)))
    walls = {b.id: b.shell.get("party_walls") for b in plan.buildings}
    assert walls == {1: [1, 2], 2: [0], 3: None}


def test_a_wall_covered_over_less_than_half_its_length_stays_a_facade():
    # building 2 (4 m wide) covers 4 of the 10 m of building 1's +y wall, which covers 4 of its 4 m
    plan = citygen.mark_covered_walls(_plan((1, 0, 0, 10, 8, None), (2, 0, 8.05, 4, 14, None)))
    walls = {b.id: b.shell.get("party_walls") for b in plan.buildings}
    assert walls == {1: None, 2: [0]}


@pytest.mark.parametrize("set_name", citygen.SETS)
def test_no_exposed_wall_of_a_plan_faces_another_building(set_name):
    plan = citygen.city_plan(set_name, 120, 7)
    worlds = [city_plan.world_polygon(b, ccw=True) for b in plan.buildings]
    t = (np.arange(20) + 0.5) / 20
    for k, b in enumerate(plan.buildings):
        party = set(b.shell.get("party_walls", []))
        w = worlds[k]
        for i in range(len(w)):
            if i in party:
                continue
            a, d = w[i], w[(i + 1) % len(w)] - w[i]
            pts = a + t[:, None] * d + np.array([d[1], -d[0]]) / np.hypot(*d) * citygen.COVERED_WALL_GAP_M
            covered = np.any([poly2d.contains(o, pts) for j, o in enumerate(worlds) if j != k], axis=0)
            assert covered.mean() < citygen.COVERED_WALL_SHARE, (b.id, i)
