"""citygen: procedural layouts (pure Python)."""
import pytest

from addon import citygen


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
