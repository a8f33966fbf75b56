"""Footprints → building IDs: closed-form polygons and the real AHN3 tile with BGT footprints."""
import json

import laspy
import numpy as np
import pytest

from quakescan.formats.footprints import FootprintError, assign_buildings, assign_buildings_reference, read_footprints


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
    text = _write(tmp_path, [_square(0, 0, 1, props={"pand": "b3e-1"}), _square(2, 0, 1, props={"pand": 9})])
    fp = read_footprints(text, id_field="pand")  # text IDs: numbered in file order, their own kept
    assert list(fp.ids) == [1, 2] and fp.own_ids() == {1: "b3e-1", 2: 9}
    bad = _write(tmp_path, [_square(0, 0, 1, props={"pand": None})])
    with pytest.raises(FootprintError, match="property 'pand' must be an ID"):
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


def test_footprints_of_a_box_scene_are_its_rectangles_in_world_coordinates(tmp_path):
    from quakescan.formats.footprints import footprints_from_scene, write_footprints
    from quakescan.formats.synthetic import box_city

    scene = box_city(rows=1, cols=2, height=(9.0, 12.0), origin=(500000.0, 5000000.0, 0.0))
    fp = footprints_from_scene(scene)
    assert sorted(fp.ids.tolist()) == sorted(scene.building_ids.tolist())
    for bid, poly in zip(fp.ids, fp.polygons):
        faces = scene.faces[scene.face_building == bid]
        xy = scene.vertices[np.unique(faces)][:, :2] + scene.origin[:2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        assert poly.area == pytest.approx((hi - lo).prod(), rel=1e-6)  # a box's outline is its rectangle
        assert np.allclose(poly.bounds, [*lo, *hi], atol=1e-6)
    back = read_footprints(write_footprints(fp, tmp_path / "fp.geojson"))
    assert back.ids.tolist() == fp.ids.tolist()
    assert [p.area for p in back.polygons] == pytest.approx([p.area for p in fp.polygons])


def test_parts_that_simplifying_makes_overlap_give_one_valid_outline():
    """Two roof parts of one building that meet along an edge only to within float noise (as
    the generator's small-set row house and its roof overhang did, coordinates copied from
    that scene): simplifying the two-part outline made the parts overlap, and classify refused
    the invalid polygon. The outline must stay valid and keep the parts' area."""
    import shapely

    from quakescan.formats.footprints import _clean_outline

    a = [(11.311999365340567, 37.841000776148036), (17.20599941874633, 37.84100129141788),
         (17.825999304305412, 37.84100134561999), (17.82599952054565, 35.36750133226855),
         (17.82599973678589, 32.89400131891711), (17.825999953026127, 30.420501305565672),
         (17.826000169266365, 27.94700129221423), (17.826000223468476, 27.32700140665515),
         (14.259000311206515, 27.327001094818115), (11.312000284503634, 27.327000837183192),
         (11.312000230301523, 27.947000722742274), (11.311999797821045, 32.894000749445155)]
    b = [(11.311999311138456, 38.46100066170712), (14.258999337841336, 38.46100091934204),
         (17.8259992501033, 38.461001231179075), (17.825999304305412, 37.84100134561999),
         (14.258999392043448, 37.84100103378296), (11.311999365340567, 37.841000776148036)]
    raw = shapely.union_all([shapely.Polygon(a), shapely.Polygon(b)])
    assert raw.is_valid and not raw.simplify(0.02).is_valid  # the case, as it was
    outline = _clean_outline(raw, 0.02, 1.0)
    assert outline.is_valid and outline.area == pytest.approx(raw.area, rel=1e-6)


@pytest.fixture(scope="module")
def scanned_region_city(tmp_path_factory):
    """A generated L'Aquila-like block city (attached buildings, courtyards, pitched roofs)
    scanned with the airborne preset."""
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.formats.scene import read_scene
    from quakescan.generator import GenerationSpec, generate

    folder = tmp_path_factory.mktemp("region_city")
    generate(GenerationSpec("region", "mixed", 12, 4, folder / "city"))
    scene = read_scene(folder / "city" / "pre")
    scan(scene, preset("als"), folder / "pre.las", seed=1)
    return scene, folder / "pre.las"


def test_footprint_labels_of_a_simulated_cloud_agree_with_the_simulator_on_roofs(scanned_region_city):
    from quakescan.formats.footprints import footprints_from_scene

    scene, las_path = scanned_region_city
    fp = footprints_from_scene(scene)
    las = laspy.read(las_path)
    bid = assign_buildings(np.asarray(las.x), np.asarray(las.y), fp)
    roof = np.asarray(las.surface) == 1
    assert roof.sum() > 5000
    assert (bid[roof] == np.asarray(las.building_id)[roof]).mean() >= 0.99
    ground = np.asarray(las.surface) == 0
    assert (bid[ground] > 0).mean() < 0.01  # the terrain between blocks stays outside
