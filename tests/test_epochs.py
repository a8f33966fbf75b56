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
