"""Training rows from real points with injected damage (`quakescan.learning.realset`)."""
import dataclasses
import json

import numpy as np
import pytest

from quakescan.learning import realset
from quakescan.learning.default_model import TABLE_SETTINGS


def test_the_plan_never_trains_on_the_tile_reserved_for_evaluation():
    realset.check_plan()
    assert all("ahn3_cropped_1" not in s.cloud for s in realset.SOURCES)
    tile1 = realset.RealSource("ahn3_tile1", "ahn3_cropped_1.laz", "ahn3_footprints_rd.geojson")
    with pytest.raises(realset.RealSetError, match="reserved for evaluation"):
        realset.check_plan([realset.RealPair("ahn3_tile1", "halves", 1, 1, ((3, 1),))], realset.SOURCES + (tile1,))
    with pytest.raises(realset.RealSetError, match="kind must be"):
        realset.check_plan([realset.RealPair("ahn3_tile2", "mirror", 1, 1)])
    names = [p.name for p in realset.REAL_PLAN]
    assert len(set(names)) == len(names)  # every pair its own folder
    with pytest.raises(realset.RealSetError, match="a drone kind needs a sensor of uls, dim"):
        realset.check_plan([realset.RealPair("ahn3_tile2", "drone", 1, 1, ((3, 1),))])
    with pytest.raises(realset.RealSetError, match="only a drone kind has one"):
        realset.check_plan([realset.RealPair("ahn3_tile2", "halves", 1, 1, ((3, 1),), sensor="uls")])


def test_a_pair_without_a_drone_keeps_the_name_and_fields_its_cached_rows_were_made_with():
    pair = realset.RealPair("ahn3_tile2", "halves", 11, 1, ((3, 6),))
    assert pair.name == "ahn3_tile2_halves_s11_i1" and pair.sensor_pair == "real-halves"
    assert "sensor" not in pair.spec() and pair.spec()["split"] == 11
    drone = realset.RealPair("ahn3_tile2", "drone", 21, 21, ((3, 6),), sensor="dim")
    assert drone.name == "ahn3_tile2_drone_dim_s21_i21" and drone.sensor_pair == "real-drone-dim"
    assert drone.spec()["sensor"] == "dim"


@pytest.mark.slow
def test_a_drone_pair_is_a_real_half_before_and_a_simulated_flight_over_the_other_half_after(shared_data, tmp_path):
    import laspy

    pair = realset.RealPair("ahn3_tile2", "drone_rescan", 25, 25, sensor="uls")
    a = realset.pair_rows(tmp_path, shared_data, pair, TABLE_SETTINGS, workers=1)
    folder = tmp_path / pair.name
    pre, post = laspy.read(folder / "pre.las"), laspy.open(folder / "post_real.las")
    whole = laspy.open(shared_data / "ahn3_cropped_2.laz").header.point_count
    half = np.random.default_rng(25).random(whole) < 0.5
    assert len(pre.points) == half.sum()  # the archive's own returns before
    sidecar = json.loads((folder / "post_real.las.acquisition.json").read_text())
    assert sidecar["acquisition"]["kind"] == "uls" and post.header.point_count > 100_000  # a drone's after
    assert (a["y"] == 0).all() and len(a["y"]) >= 20  # no damage: every building undamaged
    again = realset.pair_rows(tmp_path, shared_data, pair, TABLE_SETTINGS, workers=1)
    assert all(np.array_equal(a[k], again[k], equal_nan=a[k].dtype.kind == "f") for k in a)


def test_a_real_pair_gives_rows_labelled_by_the_injected_truth_and_is_cached(shared_data, tmp_path):
    pair = realset.RealPair("ahn3_tile2", "halves", 11, 1, ((3, 3), (5, 3)))
    a = realset.pair_rows(tmp_path, shared_data, pair, TABLE_SETTINGS, workers=1)
    assert a["x"].shape == (len(a["y"]), len(TABLE_SETTINGS.descriptor_names()))
    assert set(np.unique(a["y"]).tolist()) <= {0, 3, 5} and (a["y"] == 5).sum() >= 2
    names = TABLE_SETTINGS.descriptor_names()
    destroyed = a["x"][a["y"] == 5]
    assert (destroyed[:, names.index("s_lowered_1m")] > 0.2).all()  # a heap where the building stood
    again = realset.pair_rows(tmp_path, shared_data, pair, TABLE_SETTINGS, workers=1)
    assert all(np.array_equal(a[k], again[k], equal_nan=a[k].dtype.kind == "f") for k in a)
    table = realset.real_table(tmp_path, shared_data, TABLE_SETTINGS, plan=(pair,), repeat=2, workers=1)
    assert len(table.y) == 2 * len(a["y"]) and table.cities == ["ahn3_tile2", "sample_c"] and table.pairs == [pair.name]


def test_tables_append_with_their_cities_and_pairs_numbered_after():
    from quakescan.learning.trainset import TransferTable

    def t(n, cities, pairs):
        return TransferTable(x=np.ones((n, 2)), y=np.zeros(n, np.int64), names=["a", "b"],
                             city=np.zeros(n, np.int64), pair=np.zeros(n, np.int64), building_id=np.arange(n),
                             density=np.ones((n, 2)), cities=cities, pairs=pairs, sensors=["s"] * len(pairs),
                             cells=np.ones(n, np.int64))

    c = realset.append_tables(t(3, ["x", "y"], ["p"]), t(2, ["r"], ["q"]))
    assert c.city.tolist() == [0, 0, 0, 2, 2] and c.pair.tolist() == [0, 0, 0, 1, 1]
    assert c.cities == ["x", "y", "r"] and c.pairs == ["p", "q"]
    with pytest.raises(realset.RealSetError, match="different descriptor columns"):
        realset.append_tables(t(1, ["x"], ["p"]), dataclasses.replace(t(1, ["r"], ["q"]), names=["a", "c"]))


def test_real_rows_carry_the_unseen_shares_classify_counts():
    from quakescan.change import detectability as D
    from quakescan.change.pipeline import BuildingRow
    from quakescan.learning.realset import sampling_rows, unseen_of_sampling

    def row(walls):  # 4 pts/m² on the roof; walls at an airborne laser's 0.3 or a drone's 20 per m²
        return BuildingRow(1, 800, 800, True, quality={
            "density_pre": 4.0, "density_post": 4.0, "area_m2": 200.0, "lowering_lod_m": 0.3,
            "wall_density_pre": walls, "wall_density_post": walls, "facade_m2": 300.0})

    q = unseen_of_sampling(sampling_rows([row(0.3), row(20.0), BuildingRow(3, 10, 10, True)]))  # the last: no detectability
    np.testing.assert_allclose(q, [[D.WALLS_ONLY_SHARE[3], D.WALLS_ONLY_SHARE[4], 0.0], [0, 0, 0], [0, 0, 0]])


@pytest.mark.slow
def test_a_source_without_an_outline_file_gets_footprints_from_its_building_class(shared_data, tmp_path):
    pair = realset.RealPair("sample_c", "halves", 32, 32, ((5, 1),))
    a = realset.pair_rows(tmp_path, shared_data, pair, TABLE_SETTINGS, workers=1)
    assert (tmp_path / "sample_c" / "footprints.geojson").is_file()
    assert sorted(a["y"].tolist()) == [0, 5]  # the large building destroyed, the small one as it was
    names = TABLE_SETTINGS.descriptor_names()
    assert a["x"][a["y"] == 5, names.index("s_lowered_1m")][0] > 0.2
