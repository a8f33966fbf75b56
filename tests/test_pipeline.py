"""Pair → per-building descriptors: tiling, exact nearest neighbours, the split on real scans."""
import numpy as np
import pytest

from quakescan.change.paper_descriptors import exact_nearest
from quakescan.change.pipeline import describe_pair
from quakescan.change.settings import PAPER_FEATURES, PipelineError, PipelineSettings, settings_for_descriptors
from quakescan.change.split import SplitSettings, nearest_neighbours
from quakescan.change.tiling import GridIndex
from quakescan.formats.pointcloud import Epoch, read_epoch
from tests.scenes import UTM, scan_box_pair


def _scan_pair(folder, origin, post_heights, seed_post=2):
    scan_box_pair(folder, post_heights, origin, seed_post)
    pre = read_epoch(folder / "pre.las")
    return pre, read_epoch(folder / "post.las", origin=pre.origin)


@pytest.fixture(scope="module")
def collapse_pair(tmp_path_factory):
    """Building 4 loses 9 of its 12 m; the others are scanned again with new range noise."""
    return _scan_pair(tmp_path_factory.mktemp("collapse"), UTM, (9.0, 12.0, 9.0, 3.0, 9.0, 12.0))


def test_grid_index_box_query_matches_brute_force():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-50, 250, (20000, 2))
    index = GridIndex(xy, 17.0)
    for box in ([[0, 0], [30, 40]], [[-100, -100], [-60, -60]], [[100.5, -3], [101, 300]], [[-60, -60], [300, 300]]):
        box = np.array(box, float)
        want = np.flatnonzero(np.all((xy >= box[0]) & (xy <= box[1]), axis=1))
        np.testing.assert_array_equal(index.query(xy, box), want)


def test_nearest_neighbour_is_exact_although_searched_in_a_box():
    """A pre point whose post neighbour lies far outside the tile (a collapsed wall fell
    40 m away, say) still gets the true nearest neighbour."""
    rng = np.random.default_rng(1)
    post_xyz = np.vstack([rng.uniform(0, 10, (500, 3)) + [60, 0, 0], rng.uniform(0, 200, (3000, 3))])
    post_xyz = post_xyz[(post_xyz[:, 0] > 40) | (post_xyz[:, 1] > 150)]  # nothing near the queries
    pre_q = rng.uniform(0, 10, (300, 3))
    post = Epoch(post_xyz, np.zeros(3), np.zeros(len(post_xyz), np.uint8))
    idx, dist = exact_nearest(pre_q, post, GridIndex(post_xyz[:, :2], 5.0), np.array([[0, 0], [10, 10.0]]), 1)
    want_i, want_d = nearest_neighbours(pre_q, post_xyz)
    np.testing.assert_array_equal(idx, want_i)
    np.testing.assert_allclose(dist, want_d)


def test_rescanned_buildings_have_no_change_and_collapse_is_found(collapse_pair):
    pre, post = collapse_pair
    rows = {r.building_id: r for r in describe_pair(pre, post, PipelineSettings())}
    assert sorted(rows) == [1, 2, 3, 4, 5, 6] and all(r.assessable for r in rows.values())
    for bid in (1, 2, 3, 5, 6):  # new range noise only: nothing beyond the level of detection
        assert rows[bid].descriptors["share_changed"] == 0.0
        assert rows[bid].descriptors["height_median"] == 0.0
    d = rows[4].descriptors
    assert d["share_changed"] > 0.5  # roof and upper walls
    assert d["height_median"] == pytest.approx(-9.0, abs=0.2)
    assert set(d) == set(PipelineSettings().descriptor_names())


def test_identical_epochs_give_zero_change(collapse_pair):
    pre, _ = collapse_pair
    rows = describe_pair(pre, pre, PipelineSettings())
    for r in rows:
        assert all(v == 0.0 for v in r.descriptors.values()), r.building_id


def test_tiling_does_not_change_the_answer(collapse_pair):
    pre, post = collapse_pair
    small = describe_pair(pre, post, PipelineSettings(tile_m=20.0))  # one building per tile
    big = describe_pair(pre, post, PipelineSettings(tile_m=500.0))   # all in one tile
    for a, b in zip(small, big):
        assert a.building_id == b.building_id
        for k in a.descriptors:
            assert a.descriptors[k] == pytest.approx(b.descriptors[k], rel=1e-9, abs=1e-12), k


def test_world_coordinates_give_the_same_descriptors(collapse_pair):
    """The same points as float64 world coordinates (x≈500 000, y≈5 000 000, origin 0) and in
    the local frame: features centre their own neighbourhoods, so the answers agree."""
    pre, post = collapse_pair
    world = [Epoch(e.xyz + e.origin, np.zeros(3), e.classification, e.building_id) for e in (pre, post)]
    local = describe_pair(pre, post, PipelineSettings())
    utm = describe_pair(*world, PipelineSettings())
    for a, b in zip(local, utm):
        for k in a.descriptors:
            assert a.descriptors[k] == pytest.approx(b.descriptors[k], rel=1e-6, abs=1e-7), (a.building_id, k)


def test_resume_skips_finished_tiles(collapse_pair):
    pre, post = collapse_pair
    s = PipelineSettings(tile_m=20.0)
    first, seen = [], []
    full = describe_pair(pre, post, s, on_tile=first.extend)
    done = {r.building_id: r for r in first[:3]}
    again = describe_pair(pre, post, s, done=done, on_tile=seen.extend)
    assert sorted(r.building_id for r in seen) == [r.building_id for r in full if r.building_id not in done]
    assert [r.descriptors for r in again] == [r.descriptors for r in full]


def test_too_few_points_is_not_assessable(collapse_pair):
    pre, post = collapse_pair
    rows = describe_pair(pre, post, PipelineSettings(min_points_pre=7000))
    small = [r for r in rows if r.n_pre < 7000]
    assert small and all(not r.assessable and "pre-event points < 7000" in r.reason and not r.descriptors
                         for r in small)


def test_missing_building_ids_and_frames_are_refused(collapse_pair):
    pre, post = collapse_pair
    bare = Epoch(post.xyz, post.origin, post.classification, None, source="bare.las")
    with pytest.raises(PipelineError, match="bare.las.*no building IDs"):
        describe_pair(pre, bare, PipelineSettings())
    moved = Epoch(post.xyz, post.origin + 1, post.classification, post.building_id, source="moved.las")
    with pytest.raises(PipelineError, match="different local frames"):
        describe_pair(pre, moved, PipelineSettings())
    nobody = Epoch(pre.xyz, pre.origin, pre.classification, np.zeros(len(pre), np.int64), source="nobody.las")
    with pytest.raises(PipelineError, match="no point belongs to a building"):
        describe_pair(nobody, nobody, PipelineSettings())


def test_settings_round_trip_and_descriptor_columns():
    s = PipelineSettings(radius_m=2.0, split=SplitSettings(lod_height_m=0.5))
    again = PipelineSettings.from_json(s.to_json())
    assert again == s
    assert again.computed_features == (*PAPER_FEATURES, "curvature")
    back = settings_for_descriptors(s.descriptor_names(), 2.0, s.split.to_json())
    assert back.point_features == PAPER_FEATURES and back.descriptor_names() == s.descriptor_names()


def test_a_model_for_unknown_features_is_refused():
    with pytest.raises(PipelineError, match="wetness_mean"):
        settings_for_descriptors(["share_changed", "planarity_mean", "wetness_mean"], 1.5)
    with pytest.raises(PipelineError, match="radius"):
        PipelineSettings(radius_m=float("nan"))
    with pytest.raises(PipelineError, match="unknown point features"):
        PipelineSettings(point_features=("planarity", "colour"))


def _stable_groups(ids, uniq):
    order = np.argsort(ids, kind="stable")
    return order, np.searchsorted(ids[order], uniq)


@pytest.mark.parametrize("ids", [np.random.default_rng(0).choice([0, 3, 5, 7, -2], 100_003),
                                 np.random.default_rng(1).choice([0, 5, 10 ** 12], 1_000),  # wide: np.unique path
                                 np.array([4]), np.zeros(0, np.int64),
                                 np.random.default_rng(2).integers(0, 300, 50_000).astype(np.int32)])
def test_id_counts_and_grouping_are_numpys_unique_and_stable_argsort(ids):
    from quakescan.change.tiling import grouped_by_id, id_counts

    uniq, counts = id_counts(ids)
    want_u, want_c = np.unique(ids, return_counts=True)
    np.testing.assert_array_equal(uniq, want_u)
    np.testing.assert_array_equal(counts, want_c)
    assert uniq.dtype == want_u.dtype
    order, starts = grouped_by_id(ids, uniq)
    want_o, want_s = _stable_groups(ids, uniq)
    np.testing.assert_array_equal(order, want_o)
    np.testing.assert_array_equal(starts, want_s)


@pytest.mark.parametrize("key", [np.random.default_rng(4).integers(-50, 9_000, 20_000),  # counting sort
                                 np.random.default_rng(5).choice([3, 2 ** 40], 500),  # wide: numpy's sort
                                 np.random.default_rng(6).integers(0, 9, 1_000).astype(np.int32),
                                 np.array([7]), np.zeros(0, np.int64)])
def test_stable_order_is_a_stable_argsort(key):
    from quakescan.grid.cells import stable_order

    np.testing.assert_array_equal(stable_order(key), np.argsort(key, kind="stable"))


_UTM = np.random.default_rng(8).uniform(0, 400, (3_000, 3)) + (500_000.0, 5_000_000.0, 300.0)


@pytest.mark.parametrize("a", [_UTM, _UTM[:, :2], _UTM.astype(np.float32)[:, :2], np.floor(_UTM).astype(np.int64),
                               _UTM[:1], np.array([[-0.0, 3.0], [0.0, -np.inf], [np.inf, 2.0]])])
def test_row_bounds_are_numpys_min_and_max_down_the_rows(a):
    """Strided views, float32, integers, one row, infinities: numpy's values and dtype."""
    from quakescan.grid.cells import row_bounds

    lo, hi = row_bounds(a)
    assert lo.dtype == a.dtype and hi.dtype == a.dtype
    np.testing.assert_array_equal(lo, a.min(axis=0))
    np.testing.assert_array_equal(hi, a.max(axis=0))


def test_column_bounds_share_the_row_bounds_pass_as_float64():
    from quakescan.grid.cells import column_bounds

    lo, hi = column_bounds(_UTM.astype(np.float32)[:, :2])
    assert lo.dtype == np.float64
    np.testing.assert_array_equal(lo, _UTM.astype(np.float32)[:, :2].min(axis=0))
    np.testing.assert_array_equal(hi, _UTM.astype(np.float32)[:, :2].max(axis=0))
    np.testing.assert_array_equal(column_bounds(np.zeros((0, 3)))[0], [np.inf] * 3)


@pytest.mark.parametrize("row", [0, 1, 2999])
def test_row_bounds_propagate_nan_and_refuse_no_rows(row):
    from quakescan.grid.cells import row_bounds

    a = _UTM.copy()
    a[row, 1] = np.nan
    lo, hi = row_bounds(a)
    assert np.isnan(lo[1]) and np.isnan(hi[1])
    np.testing.assert_array_equal(lo[[0, 2]], _UTM[:, [0, 2]].min(axis=0))
    with pytest.raises(ValueError, match="zero-size"):
        row_bounds(np.zeros((0, 3)))


@pytest.mark.parametrize("offset", [(0.0, 0.0), (500_000.0, 5_000_000.0)])
def test_grid_index_buckets_are_a_stable_argsort_of_the_cells(offset):
    """The counting sort behind GridIndex gives the order, cells and starts the numpy
    expression it replaced gives, at UTM coordinates too (the same float64 operations)."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 333, (40_000, 2)) + offset
    xy[:50] = xy[50]  # points on one spot
    xy[60] = xy.min(axis=0)  # a point on the lower corner
    index = GridIndex(xy, 12.5)
    lo = xy.min(axis=0)
    ij = np.floor((xy - lo) / 12.5).astype(np.int64)
    dims = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
    key = ij[:, 0] * dims[1] + ij[:, 1]
    order = np.argsort(key, kind="stable")
    assert index.dims == dims
    np.testing.assert_array_equal(index.order, order)
    np.testing.assert_array_equal(index.starts, np.searchsorted(key[order], np.arange(dims[0] * dims[1] + 1)))


def test_tiles_described_side_by_side_give_the_rows_of_one_at_a_time(collapse_pair, monkeypatch):
    """Tiles run in threads when numba's threading layer allows it; the rows, their order
    and every descriptor are those of the tiles described one after the other."""
    import threading

    import numba

    from quakescan.change import pipeline

    pre, post = collapse_pair
    s = PipelineSettings(tile_m=20.0)  # one building per tile: six tiles
    threads, describe_tile = set(), pipeline._describe_tile

    def spy(*a, **k):
        threads.add(threading.get_ident())
        return describe_tile(*a, **k)

    monkeypatch.setattr(pipeline, "_describe_tile", spy)
    side_by_side = describe_pair(pre, post, s, workers=2)
    if numba.threading_layer() in ("tbb", "omp"):
        assert len(threads) > 1  # the tiles did run in threads
    monkeypatch.setattr(pipeline, "tile_threads", lambda workers, n: 1)
    one_at_a_time = describe_pair(pre, post, s, workers=2)
    assert [r.building_id for r in side_by_side] == [r.building_id for r in one_at_a_time]
    for a, b in zip(side_by_side, one_at_a_time):
        assert repr(a.descriptors) == repr(b.descriptors) and a.quality == b.quality


def test_tile_threads_follow_workers_and_the_threading_layer(monkeypatch):
    import numba

    from quakescan.change.tiling import tile_threads

    monkeypatch.setattr(numba, "threading_layer", lambda: "tbb")
    assert tile_threads(2, 10) == 2 and tile_threads(1, 10) == 1 and tile_threads(8, 3) == 3
    assert tile_threads(2, 1) == 1  # one tile: its kernels get the threads
    monkeypatch.setattr(numba, "threading_layer", lambda: "workqueue")  # not safe from several threads
    assert tile_threads(2, 10) == 1
