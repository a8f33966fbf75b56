"""Inputs checked for what they mean (issue 45): duplicate or oversized IDs, float ID
dimensions, JSON nested without end, non-finite CityJSON transforms, BOMs, special files."""
import json
import os

import laspy
import numpy as np
import pytest

from quakescan.errors import MAX_JSON_DEPTH, SceneError
from quakescan.formats.cityjson import import_cityjson
from quakescan.formats.footprints import FootprintError, read_footprints
from quakescan.formats.pointcloud import PointCloudError, checked_building_ids, read_epoch
from quakescan.results.evaluation import EvaluationError, read_grade_csv

RING = [[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]


def _feature(props, dx=0.0):
    return {"type": "Feature", "properties": props,
            "geometry": {"type": "Polygon", "coordinates": [[[x + dx, y] for x, y in RING]]}}


def _footprints(tmp_path, features, name="fp.geojson"):
    path = tmp_path / name
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return path


def test_two_footprints_with_one_id_are_refused_naming_both(tmp_path):
    path = _footprints(tmp_path, [_feature({"building_id": 5}), _feature({"building_id": 6}, 20),
                                  _feature({"building_id": 5}, 40)])
    with pytest.raises(FootprintError, match=r"features 0 and 2 have the same 'building_id' 5"):
        read_footprints(path)
    text = _footprints(tmp_path, [_feature({"ref": "A"}), _feature({"ref": "B"}, 20), _feature({"ref": "B"}, 40)],
                       "text.geojson")
    with pytest.raises(FootprintError, match=r"features 1 and 2 have the same 'ref' 'B'"):
        read_footprints(text, id_field="ref")
    # the number 7 and the text "7" are different IDs
    mixed = _footprints(tmp_path, [_feature({"ref": 7}), _feature({"ref": "7"}, 20)], "mixed.geojson")
    assert read_footprints(mixed, id_field="ref").own_ids() == {1: 7, 2: "7"}


@pytest.mark.parametrize("big", [2 ** 63, 2 ** 64, 10 ** 30])
def test_an_id_beyond_int64_is_a_clear_error(tmp_path, big):
    path = _footprints(tmp_path, [_feature({"building_id": big})])
    with pytest.raises(FootprintError, match=r"feature 0: 'building_id' \d+ is too large for a building ID"):
        read_footprints(path)
    ok = _footprints(tmp_path, [_feature({"building_id": 2 ** 63 - 1})], "ok.geojson")
    assert read_footprints(ok).ids.tolist() == [2 ** 63 - 1]


def test_json_nested_without_end_is_a_clear_error_not_a_recursion_error(tmp_path):
    deep = tmp_path / "deep.geojson"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(FootprintError, match="nests arrays or objects more than"):
        read_footprints(deep)
    # deep enough for the parser, too deep for everything that walks the document after it
    nested = {"type": "FeatureCollection", "features": [_feature({"building_id": 1})]}
    value = 1
    for _ in range(MAX_JSON_DEPTH + 300):
        value = [value]
    nested["features"][0]["properties"]["deep"] = value
    path = tmp_path / "nested.geojson"
    path.write_text(json.dumps(nested))
    with pytest.raises(FootprintError, match="nests arrays or objects more than"):
        read_footprints(path)
    city = tmp_path / "deep.city.json"
    city.write_text('{"type": "CityJSON", "version": "2.0", "CityObjects": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(SceneError, match="nests arrays or objects more than"):
        import_cityjson(city, crs="EPSG:7415")


@pytest.mark.parametrize("field,value", [("scale", float("nan")), ("scale", float("inf")),
                                         ("translate", float("-inf")), ("scale", 0.0)])
def test_a_cityjson_transform_that_is_not_finite_is_refused(shared_data, tmp_path, field, value):
    doc = json.loads((shared_data / "rotterdam_subset.json").read_bytes())
    doc["transform"][field][0] = value
    path = tmp_path / "city.json"
    path.write_text(json.dumps(doc))  # Python writes NaN and Infinity, and reads them back
    with pytest.raises(SceneError, match=rf"transform\.{field} .* (not a finite number|holds a zero)"):
        import_cityjson(path)


def _las_with_ids(path, ids, dtype):
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name="building_id", type=dtype)])
    header.scales = np.array([0.001] * 3)
    las = laspy.LasData(header)
    n = len(ids)
    las.x, las.y, las.z = np.arange(n, dtype=float), np.zeros(n), np.zeros(n)
    las.building_id = np.asarray(ids, dtype=dtype)
    las.write(path)
    return path


def test_a_float_building_id_dimension_is_refused_unless_every_value_is_integral(tmp_path):
    bad = _las_with_ids(tmp_path / "bad.las", [1.0, 1.5, 2.7, 3.0], np.float64)
    with pytest.raises(PointCloudError, match=r"float type \(float64\) and 2 of 4 values read are not whole"):
        read_epoch(bad)
    good = _las_with_ids(tmp_path / "good.las", [1.0, 2.0, 0.0, 503100000018603.0], np.float64)
    assert read_epoch(good).building_id.tolist() == [1, 2, 0, 503100000018603]
    with pytest.raises(PointCloudError, match="not whole numbers"):
        checked_building_ids(np.array([np.nan, 1.0], np.float32), "x.las")
    with pytest.raises(PointCloudError, match="2\\^63 or more"):
        checked_building_ids(np.array([2 ** 63], np.uint64), "x.las")


def test_a_truth_csv_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "truth.csv"
    path.write_bytes("\ufeffbuilding_id,grade\r\n1,3\r\n2,0\r\n".encode("utf-8"))  # Excel's "CSV UTF-8"
    assert read_grade_csv(path) == {1: 3, 2: 0}


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "input.fifo"
    os.mkfifo(path)
    return path


def test_a_device_or_fifo_given_as_an_input_is_refused_as_not_a_regular_file(tmp_path, fifo):
    from quakescan.assessment.run import classify
    from quakescan.errors import ClassifyError

    for special in ("/dev/zero", fifo):
        with pytest.raises(FootprintError, match="footprint file is not a regular file"):
            read_footprints(special)
        with pytest.raises(PointCloudError, match="point cloud file is not a regular file"):
            read_epoch(special)
        with pytest.raises(EvaluationError, match="truth file is not a regular file"):
            read_grade_csv(special)
        with pytest.raises(SceneError, match="CityJSON file is not a regular file"):
            import_cityjson(special)
        with pytest.raises(ClassifyError, match="pre-event point cloud is not a regular file"):
            classify(special, special, tmp_path / "out")
    with pytest.raises(PointCloudError, match="does not exist"):
        read_epoch(tmp_path / "missing.las")


def test_the_dask_streaming_path_refuses_a_fractional_building_id_as_well(tmp_path):
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch

    bad = _las_with_ids(tmp_path / "bad.las", [1.0, 1.5, 2.0], np.float64)
    f = open_epoch_file(bad)
    with pytest.raises(PointCloudError, match="not whole numbers"):
        stream_epoch(f, default_origin(f), tmp_path / "blocks", block_cells=50)
