"""Footprints from a cloud's building class (`formats.class_footprints`).

Closed forms: two rectangles of class-6 returns on cell edges, in UTM coordinates, give
their areas exactly and their own IDs in x order; a cell of one without a return is closed;
a 4 m² patch of class 6 (a misclassified crown) is left out; ground returns are not
building. Real file: `sample_c.las` (no outline file, one large building)."""
import numpy as np
import pytest
import shapely

from quakescan.formats.class_footprints import footprints_from_class
from quakescan.formats.footprints import FootprintError, assign_buildings

E0, N0 = 674_000.0, 1_206_000.0


def _samples(x0, y0, x1, y1, step=0.5):
    x, y = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step), indexing="ij")
    return np.c_[x.ravel(), y.ravel()]


def test_rectangles_of_building_returns_give_their_outlines_and_small_patches_none():
    a = _samples(E0 + 10, N0 + 10, E0 + 30, N0 + 22)  # 20 x 12 m
    a = a[~((np.abs(a[:, 0] - (E0 + 20.5)) < 0.5) & (np.abs(a[:, 1] - (N0 + 15.5)) < 0.5))]  # a cell with no return
    b = _samples(E0 + 33, N0 + 5, E0 + 41, N0 + 25)  # 8 x 20 m, 3 m east of the first
    crown = _samples(E0 + 50, N0 + 50, E0 + 52, N0 + 52)  # 4 m²
    ground = _samples(E0, N0, E0 + 60, N0 + 60, 1.0)
    xy = np.r_[a, b, crown, ground]
    cls = np.r_[np.full(len(a) + len(b) + len(crown), 6), np.full(len(ground), 2)]
    fp = footprints_from_class(np.c_[xy, np.zeros(len(xy))], cls, crs="EPSG:32631")
    assert fp.ids.tolist() == [1, 2] and fp.crs == "EPSG:32631"
    assert [p.area for p in fp.polygons] == [240.0, 160.0]  # exact: the rectangles lie on cell edges
    assert fp.polygons[0].equals(shapely.box(E0 + 10, N0 + 10, E0 + 30, N0 + 22))
    assert fp.polygons[1].equals(shapely.box(E0 + 33, N0 + 5, E0 + 41, N0 + 25))
    ids = assign_buildings(xy[:, 0], xy[:, 1], fp)
    assert (ids[: len(a)] == 1).all() and (ids[len(a): len(a) + len(b)] == 2).all()


def test_no_building_class_or_only_small_patches_is_an_error_that_says_so():
    xy = _samples(E0, N0, E0 + 10, N0 + 10)
    with pytest.raises(FootprintError, match="pts.las: no return of class 6 .building.: no footprints can be derived"):
        footprints_from_class(np.c_[xy, xy[:, :1]], np.full(len(xy), 2), source="pts.las")
    with pytest.raises(FootprintError, match="form no region of 20 m² or more"):
        footprints_from_class(np.c_[xy[:8], xy[:8, :1]], np.full(8, 6))
    with pytest.raises(FootprintError, match="cell size must be a positive number"):
        footprints_from_class(np.c_[xy, xy[:, :1]], np.full(len(xy), 6), cell_m=0.0)
    with pytest.raises(FootprintError, match="one class each"):
        footprints_from_class(np.c_[xy, xy[:, :1]], np.full(3, 6))


def test_sample_c_is_one_large_building_holding_its_building_returns(shared_data):
    import laspy

    las = laspy.read(shared_data / "sample_c.las")
    cls = np.asarray(las.classification)
    fp = footprints_from_class(np.c_[las.x, las.y, las.z], cls)
    largest = max(fp.polygons, key=lambda p: p.area)
    assert 2_000 < largest.area < 2_800
    ids = assign_buildings(np.asarray(las.x), np.asarray(las.y), fp)
    assert (ids[cls == 6] > 0).mean() > 0.99  # every building return is in a footprint
    assert (ids[cls == 2] > 0).mean() < 0.15  # the ground mostly is not
