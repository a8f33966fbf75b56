"""Every JSON and GeoJSON output is strict JSON: NaN and infinities as null (issue 45)."""
import json

import numpy as np

from quakescan.results.geojson import write_geojson
from quakescan.runtime.atomic import write_json
from test_safe_text_html import CLASSES, _rows_and_outlines


def _strict(text):
    """json.loads that refuses NaN and Infinity, as every reader but Python's does."""
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def test_write_json_writes_nan_and_infinities_as_null(tmp_path):
    path = tmp_path / "x.json"
    write_json(path, {"a": float("nan"), "b": [float("inf"), -float("inf"), 1.5], "c": np.float64("nan"),
                      "d": np.float32(2.0)}, default=float)
    assert _strict(path.read_text()) == {"a": None, "b": [None, None, 1.5], "c": None, "d": 2.0}


def test_geojson_with_nan_and_infinite_footprint_attributes_is_strict_json(tmp_path):
    rows, outlines = _rows_and_outlines([1, 2])
    attributes = {1: {"height": float("nan"), "area": float("inf"), "nested": {"v": [float("-inf"), 3]}},
                  2: {"name": "ok"}}
    path = tmp_path / "buildings.geojson"
    write_geojson(rows, outlines, path, "EPSG:32633", CLASSES, attributes)
    doc = _strict(path.read_text())
    props = doc["features"][0]["properties"]
    assert props["footprint"] == {"height": None, "area": None, "nested": {"v": [None, 3]}}
    assert props["min_opening_m2"] is None and doc["features"][1]["properties"]["footprint"] == {"name": "ok"}


def test_a_footprint_file_with_nan_attributes_reads_and_writes_back_as_strict_json(tmp_path):
    from quakescan.formats.footprints import read_footprints, write_footprints

    ring = [[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]
    src = tmp_path / "fp.geojson"
    src.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": '
                   '{"building_id": 3, "h": NaN, "w": Infinity}, "geometry": {"type": "Polygon", "coordinates": '
                   + json.dumps([ring]) + "}}]}")
    fp = read_footprints(src)
    out = write_footprints(fp, tmp_path / "out.geojson")
    props = _strict(out.read_text())["features"][0]["properties"]
    assert props == {"building_id": 3, "h": None, "w": None}
