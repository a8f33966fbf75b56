"""Footprints → building IDs: closed-form polygons and the real AHN3 tile with BGT footprints."""
import json

import laspy
import numpy as np
import pytest

from core.footprints import FootprintError, assign_buildings, assign_buildings_reference, read_footprints


def _write(tmp_path, features, crs="EPSG:28992"):
    doc = {"type": "FeatureCollection", "features": features}
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": f"urn:ogc:def:crs:{crs.replace(':', '::')}"}}
    path = tmp_path / "f.geojson"
    path.write_text(json.dumps(doc))
    return path


def _square(x0, y0, size, hole=None, props=None):
    ring = [[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size], [x0, y0]]
    coords = [ring] + ([hole] if hole else [])
    return {"type": "Feature", "properties": props or {}, "geometry": {"type": "Polygon", "coordinates": coords}}


def test_squares_holes_and_overlaps(tmp_path):
    x0, y0 = 85000.0, 447000.0  # RD New coordinates
    hole = [[x0 + 4, y0 + 4], [x0 + 6, y0 + 4], [x0 + 6, y0 + 6], [x0 + 4, y0 + 6], [x0 + 4, y0 + 4]]
    path = _write(tmp_path, [_square(x0, y0, 10, hole), _square(x0 + 1, y0 + 1, 2), _square(x0 + 20, y0, 5)])
    fp = read_footprints(path)
    assert fp.crs == "EPSG:28992" and list(fp.ids) == [1, 2, 3]
    x = x0 + np.array([0.5, 1.5, 5.0, 8.0, 22.0, 15.0])
    y = y0 + np.array([0.5, 1.5, 5.0, 8.0, 2.0, 2.0])
    # corner of big, inside the small overlapping one, in the hole, big, third, outside
    np.testing.assert_array_equal(assign_buildings(x, y, fp), [1, 2, 0, 1, 3, 0])
    np.testing.assert_array_equal(assign_buildings_reference(x, y, fp), [1, 2, 0, 1, 3, 0])


def test_id_field(tmp_path):
    path = _write(tmp_path, [_square(0, 0, 1, props={"pand": 7}), _square(2, 0, 1, props={"pand": 9})])
    assert list(read_footprints(path, id_field="pand").ids) == [7, 9]
    bad = _write(tmp_path, [_square(0, 0, 1, props={"pand": "x"})])
    with pytest.raises(FootprintError, match="property 'pand' must be an integer > 0"):
        read_footprints(bad, id_field="pand")


@pytest.mark.parametrize("content, text", [
    (None, "does not exist"),
    ("{", "not valid JSON"),
    ('{"type": "Feature"}', "not a GeoJSON FeatureCollection"),
    ('{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": {"type": "Point", '
     '"coordinates": [0, 0]}}]}', "no polygon footprints"),
])
def test_bad_footprint_files(tmp_path, content, text):
    path = tmp_path / "f.geojson"
    if content is not None:
        path.write_text(content)
    with pytest.raises(FootprintError, match=text):
        read_footprints(path)


@pytest.mark.realdata
def test_ahn3_points_fall_in_bgt_footprints(shared_data):
    fp = read_footprints(shared_data / "ahn3_footprints_rd.geojson")
    assert len(fp) == 160 and fp.crs == "EPSG:28992"
    las = laspy.read(shared_data / "ahn3_cropped_1.laz")
    x, y = np.asarray(las.x), np.asarray(las.y)
    cls = np.asarray(las.classification)
    ids = assign_buildings(x, y, fp)
    # the fast assignment equals the obvious ray-casting reference (on a sample)
    sample = np.random.default_rng(0).choice(len(x), 40_000, replace=False)
    np.testing.assert_array_equal(ids[sample], assign_buildings_reference(x[sample], y[sample], fp))
    # points inside footprints are the airborne scan's building points; ground stays outside
    # (the 160 footprints cover only part of the tile, so not every building point is inside one)
    assert (cls[ids > 0] == 6).mean() > 0.9  # 0.949 measured
    assert (ids[cls == 2] > 0).mean() < 0.02
    hit = np.unique(ids[ids > 0])
    assert len(hit) > 50  # many of the 160 footprints get points on this tile
