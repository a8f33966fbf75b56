"""Reading epochs of real and simulated LAS/LAZ, and refusing pairs that cannot be compared."""
import numpy as np
import pytest

from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import preset
from quakescan.errors import PointCloudError
from quakescan.formats.pointcloud import check_pair, read_epoch
from quakescan.formats.synthetic import box_city


@pytest.mark.realdata
@pytest.mark.parametrize("name, n, fmt", [("ahn3_cropped_1.laz", 640_510, 1), ("ahn3_cropped_2.laz", 208_432, 1),
                                          ("sample_c.las", 14_408, 3)])
def test_real_files_of_any_point_format(shared_data, name, n, fmt):
    import laspy

    e = read_epoch(shared_data / name)
    las = laspy.read(shared_data / name)
    assert len(e) == n and las.header.point_format.id == fmt
    world = e.xyz + e.origin
    np.testing.assert_allclose(world[:, 0], las.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(world[:, 1], las.y, rtol=0, atol=1e-9)
    assert np.abs(e.xyz).max() < 1e4  # local frame: small numbers
    assert e.building_id is None  # real data: IDs come from footprints


def test_simulated_epoch_keeps_labels(tmp_path):
    scene = box_city(rows=1, cols=2, origin=(500000.0, 5000000.0, 0.0), grades=[3, 5])
    scene.crs = "EPSG:32633"
    scan(scene, preset("paper").replace(pulse_rate_hz=50_000.0), tmp_path / "e.las")
    e = read_epoch(tmp_path / "e.las")
    np.testing.assert_array_equal(e.origin, scene.origin)
    assert e.crs == "EPSG:32633"
    assert set(np.unique(e.building_id)) == {0, 1, 2}
    assert set(np.unique(e.grade[e.building_id == 2])) == {5}


def test_pairs_with_other_crs_or_no_overlap_are_refused(tmp_path):
    a = box_city(rows=1, cols=1, origin=(500000.0, 5000000.0, 0.0))
    a.crs = "EPSG:32633"
    b = box_city(rows=1, cols=1, origin=(500000.0, 5000000.0, 0.0))
    b.crs = "EPSG:32632"
    c = box_city(rows=1, cols=1, origin=(510000.0, 5000000.0, 0.0))
    c.crs = "EPSG:32633"
    s = preset("paper").replace(pulse_rate_hz=20_000.0)
    for name, sc in (("a", a), ("b", b), ("c", c)):
        scan(sc, s, tmp_path / f"{name}.las")
    pre = read_epoch(tmp_path / "a.las")
    check_pair(pre, read_epoch(tmp_path / "a.las", origin=pre.origin))
    with pytest.raises(PointCloudError, match="CRS EPSG:32632 differs"):
        check_pair(pre, read_epoch(tmp_path / "b.las", origin=pre.origin))
    with pytest.raises(PointCloudError, match="no overlap"):
        check_pair(pre, read_epoch(tmp_path / "c.las", origin=pre.origin))


def test_missing_and_garbage_files(tmp_path):
    with pytest.raises(PointCloudError, match="does not exist"):
        read_epoch(tmp_path / "nope.las")
    (tmp_path / "bad.las").write_bytes(b"not a las file")
    with pytest.raises(PointCloudError, match="cannot read as LAS/LAZ"):
        read_epoch(tmp_path / "bad.las")


def _labelled_las(path, ids, seed=0):
    """A LAS file of len(ids) points with QuakeScan's labels, building_id stored as uint32."""
    import laspy

    rng = np.random.default_rng(seed)
    n = len(ids)
    h = laspy.LasHeader(point_format=6, version="1.4")
    h.offsets, h.scales = [500000.0, 5000000.0, 0.0], [0.001, 0.001, 0.001]
    h.add_extra_dims([laspy.ExtraBytesParams("building_id", np.uint32), laspy.ExtraBytesParams("grade", np.uint8),
                      laspy.ExtraBytesParams("surface", np.uint8)])
    las = laspy.LasData(h)
    las.x = 500000.0 + rng.uniform(0, 300, n)
    las.y = 5000000.0 + rng.uniform(0, 200, n)
    las.z = rng.uniform(0, 30, n)
    las.classification = rng.integers(0, 7, n).astype(np.uint8)
    las.building_id = np.asarray(ids, np.uint32)
    las.grade = rng.integers(0, 6, n).astype(np.uint8)
    las.surface = rng.integers(0, 3, n).astype(np.uint8)
    las.write(path)
    return laspy.read(path)


@pytest.mark.parametrize("chunk", [1, 7, 1000, 4_000_000])
def test_reading_by_chunks_gives_every_point_and_label_of_the_file(tmp_path, chunk):
    """The epoch is filled chunk by chunk (no whole-file record array beside it): whatever
    the chunk, the coordinates are the file's to the last bit and every label is kept."""
    ids = np.random.default_rng(1).integers(0, 40, 2_503)
    las = _labelled_las(tmp_path / "e.las", ids)
    e = read_epoch(tmp_path / "e.las", chunk_points=chunk)
    assert len(e) == 2_503
    for k, c in enumerate("xyz"):
        np.testing.assert_array_equal(e.xyz[:, k] + e.origin[k], np.asarray(getattr(las, c)))
    np.testing.assert_array_equal(e.classification, np.asarray(las.classification))
    np.testing.assert_array_equal(e.building_id, ids)
    np.testing.assert_array_equal(e.grade, np.asarray(las.grade))
    np.testing.assert_array_equal(e.surface, np.asarray(las.surface))
    assert e.building_id.dtype == np.int32  # 4 bytes a point, signed: the file's uint32 IDs all < 2^31
    bare = read_epoch(tmp_path / "e.las", chunk_points=chunk, labels=False)  # what classify reads
    assert bare.grade is None and bare.surface is None
    np.testing.assert_array_equal(bare.building_id, ids)
    np.testing.assert_array_equal(bare.xyz, e.xyz)


def test_building_ids_beyond_int32_are_kept_whole(tmp_path):
    ids = np.array([0, 5, 2 ** 31, 2 ** 32 - 1, 7], np.int64)
    _labelled_las(tmp_path / "e.las", ids)
    e = read_epoch(tmp_path / "e.las", chunk_points=2)
    assert e.building_id.dtype == np.int64
    np.testing.assert_array_equal(e.building_id, ids)


def test_a_file_cut_short_is_refused_with_its_name(tmp_path):
    _labelled_las(tmp_path / "e.las", np.arange(5_000) % 9)
    data = (tmp_path / "e.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[:len(data) - 40_000])
    with pytest.raises(PointCloudError, match="cut.las"):
        read_epoch(tmp_path / "cut.las")


def test_the_post_epoch_read_beside_the_pre_epoch_is_in_its_frame(tmp_path):
    """load_pair reads both epochs at once, the post epoch in the frame the pre-event file's
    header gives: the same arrays as reading one after the other."""
    from quakescan.formats.pointcloud import epoch_origin
    from quakescan.formats.pair import load_pair

    _labelled_las(tmp_path / "a.las", np.arange(3_000) % 5, seed=1)
    _labelled_las(tmp_path / "b.las", np.arange(2_000) % 5, seed=2)
    pre = read_epoch(tmp_path / "a.las")
    post = read_epoch(tmp_path / "b.las", origin=pre.origin)
    np.testing.assert_array_equal(epoch_origin(tmp_path / "a.las"), pre.origin)
    pair = load_pair(tmp_path / "a.las", tmp_path / "b.las")
    for got, want in ((pair.pre, pre), (pair.post, post)):
        np.testing.assert_array_equal(got.origin, want.origin)
        np.testing.assert_array_equal(got.xyz, want.xyz)
        np.testing.assert_array_equal(got.building_id, want.building_id)
