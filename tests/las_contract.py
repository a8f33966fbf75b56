"""The epoch LAS contract (docs/formats.md "Epoch point cloud") that both simulators' outputs must keep."""
import laspy
import numpy as np

CONTRACT_ORIGIN = (2600000.0, 1200000.0, 400.0)  # Swiss LV95 coordinates: EPSG 2056


def read_checked(path, scene) -> laspy.LasData:
    """Read `path` and check the header against the contract for `scene` (origin, CRS 2056)."""
    las = laspy.read(path)
    h = las.header
    assert str(h.version) == "1.4" and h.point_format.id == 6
    np.testing.assert_array_equal(h.scales, [0.001] * 3)
    np.testing.assert_array_equal(h.offsets, scene.origin)
    dims = {d.name: d for d in h.point_format.extra_dimensions}
    assert dims["building_id"].dtype == np.uint32
    assert dims["grade"].dtype == np.uint8 and dims["surface"].dtype == np.uint8
    assert h.parse_crs().to_epsg() == 2056
    # header bookkeeping written from the workers' bounds
    np.testing.assert_allclose(h.mins, [las.x.min(), las.y.min(), las.z.min()])
    np.testing.assert_allclose(h.maxs, [las.x.max(), las.y.max(), las.z.max()])
    assert h.point_count == len(las.x)
    return las
