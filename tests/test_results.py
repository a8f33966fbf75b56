"""Per-building results: CSV round trip and evaluation, GeoJSON, PNG map, graded LAS."""
import csv
import json

import laspy
import numpy as np
import pytest
import shapely.geometry

from quakescan.formats.footprints import Footprints, read_footprints
from quakescan.learning.model import GRADE_LABELS
from quakescan.errors import ResultsError
from quakescan.results import png_map
from quakescan.results.building_result import BuildingResult
from quakescan.results.colours import BACKGROUND_COLOUR, GRADE_COLOURS, NOT_ASSESSABLE_COLOUR, rgb8
from quakescan.results.csv_table import csv_columns, read_csv, write_csv
from quakescan.results.evaluation import evaluate_files
from quakescan.results.geojson import geojson_crs_member, write_geojson
from quakescan.results.graded_cloud import write_grade_las
from quakescan.results.outlines import (
    OUTLINE_BUFFER,
    OUTLINE_FOOTPRINT,
    OUTLINE_HULL,
    Outline,
    building_outlines,
    hull_candidates,
)
from quakescan.results.png_map import (
    LABEL_ALL_MAX,
    MAP_DPI,
    MAP_SIZE_IN,
    labelled_ids,
    legible_labels,
    nice_length,
    write_map_png,
)

CLASSES = [0, 3, 4, 5]
ORIGIN = np.array([500000.0, 5000000.0, 40.0])


def _rows():
    return [
        BuildingResult(7, 900, 850, True, grade=5, probabilities={0: 0.05, 3: 0.1, 4: 0.15, 5: 0.7},
                         share_changed=0.8123456789, decided_by="model", confidence=0.7),
        BuildingResult(2, 12, 400, False, reason="12 pre-event points < 50"),
        BuildingResult(3, 500, 510, True, grade=0, probabilities={0: 1.0, 3: 0.0, 4: 0.0, 5: 0.0},
                         share_changed=0.0, decided_by="no change", confidence=1.0),
        BuildingResult(5, 700, 300, True, grade=4, probabilities={0: 0.1, 3: 0.2, 4: 0.4, 5: 0.3},
                         share_changed=1 / 3, decided_by="model, with \"quotes\", commas", confidence=0.4),
    ]


def _no_part(tmp_path):
    assert not [p for p in tmp_path.rglob("*") if ".part" in p.name]


def test_csv_round_trip(tmp_path):
    path = tmp_path / "buildings.csv"
    write_csv(_rows(), path, CLASSES)
    back = read_csv(path)
    assert [r.building_id for r in back] == [2, 3, 5, 7]  # sorted
    want = {r.building_id: r for r in _rows()}
    for r in back:
        w = want[r.building_id]
        assert (r.n_pre, r.n_post, r.assessable, r.grade, r.reason, r.decided_by) == \
               (w.n_pre, w.n_post, w.assessable, w.grade, w.reason, w.decided_by)
        assert r.probabilities == pytest.approx(w.probabilities, rel=1e-6)
        assert r.confidence == w.confidence
        assert (r.share_changed is None) == (w.share_changed is None)
        if w.share_changed is not None:
            assert r.share_changed == pytest.approx(w.share_changed, rel=1e-6)
        assert r.label == w.label
    assert back[-1].label == GRADE_LABELS[5]
    _no_part(tmp_path)


def test_csv_not_assessable_is_empty_never_a_guess(tmp_path):
    path = tmp_path / "buildings.csv"
    write_csv(_rows(), path, CLASSES)
    with open(path, newline="") as f:
        rows = {int(r["building_id"]): r for r in csv.DictReader(f)}
    assert list(next(iter(rows.values()))) == csv_columns(CLASSES)
    na = rows[2]
    assert na["assessable"] == "0" and na["predicted_grade"] == "" and na["label"] == "not assessable"
    assert all(na[f"p_{c}"] == "" for c in CLASSES)
    assert na["reason"] == "12 pre-event points < 50" and na["n_pre"] == "12"
    assert rows[7]["assessable"] == "1" and rows[7]["predicted_grade"] == "5" and rows[7]["p_5"] == "0.7"
    assert rows[7]["share_changed"] == "0.812346"
    assert rows[7]["confidence"] == "0.7" and rows[3]["confidence"] == "1" and na["confidence"] == ""
    # a not-assessable row whose caller forgot to clear a grade still writes no grade
    write_csv([BuildingResult(1, 0, 0, False, "no point inside the footprint", grade=3,
                                  probabilities={3: 1.0}, confidence=1.0)], path, CLASSES)
    (r,) = read_csv(path)
    assert r.grade is None and r.probabilities == {} and r.label == "not assessable" and r.confidence is None


def test_confidence_comes_after_the_first_columns_and_old_files_still_read(tmp_path):
    """The column added for confidence goes last; a result file without it (an earlier
    QuakeScan's) reads with confidence empty, in read_csv and evaluate."""
    first = ["building_id", "assessable", "predicted_grade", "label", "p_0", "p_3", "p_4", "p_5",
             "share_changed", "n_pre", "n_post", "decided_by", "reason"]
    added = ["confidence", "grade_name", "detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved",
             "min_wall_opening_m2"]
    assert csv_columns(CLASSES) == first + added
    path = tmp_path / "buildings.csv"
    write_csv(_rows(), path, CLASSES)
    old = tmp_path / "old.csv"
    with open(path, newline="") as f, open(old, "w", newline="") as g:
        w = csv.writer(g, lineterminator="\n")
        for line in csv.reader(f):
            w.writerow(line[:-len(added)])
    back = read_csv(old)
    assert [r.confidence for r in back] == [None] * 4 and [r.grade for r in back] == [None, 0, 4, 5]
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n3,0\n5,4\n7,5\n")
    assert evaluate_files(old, truth).overall_accuracy == evaluate_files(path, truth).overall_accuracy == 1.0


def test_empty_csv_round_trip(tmp_path):
    write_csv([], tmp_path / "b.csv", CLASSES)
    assert read_csv(tmp_path / "b.csv") == []
    with pytest.raises(ResultsError, match="does not exist"):
        read_csv(tmp_path / "nope.csv")


def test_evaluate_reads_the_csv(tmp_path):
    path = tmp_path / "buildings.csv"
    write_csv(_rows(), path, CLASSES)
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n2,5\n3,0\n5,3\n7,5\n99,0\n")
    ev = evaluate_files(path, truth)
    assert ev.n == 3 and ev.not_assessable == 1 and ev.missing == [99]
    assert ev.overall_accuracy == pytest.approx(2 / 3)  # 3 → 0 right, 7 → 5 right, 5 → 4 wrong (truth 3)


def _square(n=11, side=10.0, at=(1000.0, 2000.0)):
    """Grid of points on a side × side square (local coordinates), area side²."""
    g = np.linspace(0.0, side, n)
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel()]) + np.asarray(at)


@pytest.mark.parametrize("kind", ["disc", "grid", "roof at UTM", "line", "thin sliver", "duplicates"])
def test_hull_candidates_give_geos_the_same_polygon_as_every_point(kind):
    """Culling the points inside the octagon of extremes leaves the hull's vertices: GEOS makes
    the same polygon, byte for byte, from a few hundred points as from all of them."""
    rng = np.random.default_rng(3)
    if kind == "disc":
        a, r = rng.uniform(0, 2 * np.pi, 20_000), np.sqrt(rng.uniform(0, 1, 20_000)) * 7.0
        xy = np.column_stack([r * np.cos(a), r * np.sin(a)])
    elif kind == "grid":  # many points on the hull's edges: collinear, not vertices
        xy = _square(n=101, side=12.0, at=(3.0, -4.0))
    elif kind == "roof at UTM":  # an L-shaped building's points at UTM coordinates, mm-quantised
        xy = rng.uniform(0, 20, (30_000, 2))
        xy = xy[(xy[:, 0] < 8) | (xy[:, 1] < 8)]
        xy = np.round(xy + [674_512.0, 5_206_733.0], 3)
    elif kind == "line":
        xy = np.column_stack([np.linspace(0, 9, 500), np.linspace(0, 3, 500)]) + 1e6
    elif kind == "thin sliver":
        xy = np.column_stack([rng.uniform(0, 50, 5_000), rng.uniform(0, 1e-7, 5_000)]) + [5e5, 4e6]
    else:
        xy = np.repeat(rng.uniform(0, 5, (40, 2)), 50, axis=0)
    kept = hull_candidates(xy)
    every = shapely.convex_hull(shapely.multipoints(xy))
    culled = shapely.convex_hull(shapely.multipoints(kept))
    assert shapely.to_wkb(culled) == shapely.to_wkb(every)
    if kind in ("disc", "grid", "roof at UTM"):
        assert len(kept) < len(xy) // 5  # the point of it (a disc keeps the most: ~11 %)


def test_outlines_hull_in_world_coordinates_and_footprints():
    rows = _rows()
    fp_poly = shapely.geometry.box(501000.0, 5002000.0, 501012.0, 5002008.0)
    fp = Footprints(np.array([7]), [fp_poly], "EPSG:32633")
    xy = {3: _square(side=10.0, at=(1000.0, 2000.0)) + 0.0004,  # not on the mm grid on purpose
          5: np.array([[1.0, 1.0], [1.0, 1.0]]),  # one distinct point
          7: _square(at=(0.0, 0.0))}  # ignored: the footprint wins
    out = building_outlines(rows, fp, xy, ORIGIN)
    assert set(out) == {3, 5, 7}  # 2 has neither footprint nor points
    assert out[7].source == OUTLINE_FOOTPRINT and out[7].geometry.equals(fp_poly)
    hull = out[3]
    assert hull.source == OUTLINE_HULL
    assert abs(hull.geometry.area - 100.0) < 1e-6
    minx, miny, maxx, maxy = hull.geometry.bounds
    assert np.allclose([minx, miny, maxx, maxy],
                       [501000.0004, 5002000.0004, 501010.0004, 5002010.0004], atol=1e-6)
    assert out[5].source == OUTLINE_BUFFER
    assert out[5].geometry.contains(shapely.geometry.Point(500001.0, 5000001.0))
    # collinear points: a buffered line, not an empty "hull"
    line = building_outlines([rows[0]], None, {7: np.array([[0.0, 0], [1, 0], [2, 0]])}, ORIGIN)[7]
    assert line.source == OUTLINE_BUFFER and line.geometry.area > 0


def test_geojson(tmp_path):
    rows = _rows()
    fp_poly = shapely.geometry.box(501000.0, 5002000.0, 501012.0, 5002008.0)
    fp = Footprints(np.array([7]), [fp_poly], "EPSG:32633")
    xy = {3: _square(side=10.0, at=(1000.0, 2000.0)) + 0.0004}
    outlines = building_outlines(rows, fp, xy, ORIGIN)
    path = tmp_path / "buildings.geojson"
    write_geojson(rows, outlines, path, "EPSG:32633", CLASSES)
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["crs"] == {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}}
    feats = {f["properties"]["building_id"]: f for f in doc["features"]}
    assert sorted(feats) == [2, 3, 5, 7] and len(doc["features"]) == len(rows)
    assert feats[7]["properties"]["outline"] == "footprint"
    assert shapely.geometry.shape(feats[7]["geometry"]).equals(fp_poly)
    assert feats[7]["properties"]["colour"] == GRADE_COLOURS[5]
    assert feats[7]["properties"]["predicted_grade"] == 5 and feats[7]["properties"]["p_5"] == 0.7
    assert feats[7]["properties"]["confidence"] == 0.7 and feats[2]["properties"]["confidence"] is None
    h = feats[3]
    assert h["properties"]["outline"] == "convex hull of points"
    coords = np.array(h["geometry"]["coordinates"][0])
    assert np.all(np.abs(coords * 1000 - np.rint(coords * 1000)) < 1e-3)  # mm precision
    assert abs(shapely.geometry.shape(h["geometry"]).area - 100.0) < 2 * 10 * 0.001  # edges within 1 mm
    assert np.abs(coords.min(axis=0) - [501000.0, 5002000.0]).max() <= 0.001
    na = feats[2]
    assert na["geometry"] is None and na["properties"]["assessable"] is False
    assert na["properties"]["predicted_grade"] is None and na["properties"]["p_0"] is None
    assert na["properties"]["label"] == "not assessable"
    assert na["properties"]["colour"] == NOT_ASSESSABLE_COLOUR
    # the footprint reader takes it back, CRS included
    back = read_footprints(path)
    assert sorted(back.ids.tolist()) == [3, 7] and back.crs == "EPSG:32633"
    _no_part(tmp_path)


def test_geojson_crs_member():
    assert geojson_crs_member(None) is None
    assert geojson_crs_member("EPSG:28992")["properties"]["name"] == "urn:ogc:def:crs:EPSG::28992"
    import pyproj

    wkt = pyproj.CRS.from_epsg(28992).to_wkt()
    assert geojson_crs_member(wkt)["properties"]["name"] == "urn:ogc:def:crs:EPSG::28992"


def _hex_rgb(h):
    return np.array(rgb8(h)) / 255.0


def test_map_png(tmp_path):
    a = shapely.geometry.box(500000.0, 5000000.0, 500020.0, 5000020.0)
    b = shapely.geometry.box(500040.0, 5000000.0, 500060.0, 5000020.0)
    rows = [BuildingResult(1, 10, 0, False, "no post-event points"),
            BuildingResult(2, 100, 100, True, grade=5, probabilities={5: 1.0}, share_changed=1.0,
                             decided_by="model")]
    outlines = {1: Outline(a, OUTLINE_FOOTPRINT), 2: Outline(b, OUTLINE_HULL)}
    pts = np.random.default_rng(0).uniform([499990, 4999990], [500070, 5000030], (2000, 2))
    path = tmp_path / "damage_map.png"
    write_map_png(rows, outlines, path, "test map", points_xy=pts, crs="EPSG:32633")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    img = matplotlib.image.imread(path)
    w_px, h_px = (int(round(v * MAP_DPI)) for v in MAP_SIZE_IN)
    assert img.shape[:2] == (h_px, w_px)
    # where the map drew each building (same inputs → same layout)
    fig, ax = png_map._draw_map(rows, outlines, "test map", pts, "EPSG:32633")
    fig.canvas.draw()
    for geom, colour in ((a, NOT_ASSESSABLE_COLOUR), (b, GRADE_COLOURS[5])):
        x0, y0, x1, y1 = geom.bounds  # a quarter in from the corner: the ID label sits in the middle
        px, py = ax.transData.transform((x0 + 0.25 * (x1 - x0), y0 + 0.25 * (y1 - y0)))
        pixel = img[int(round(h_px - py)), int(round(px)), :3]
        assert np.abs(pixel - _hex_rgb(colour)).max() < 2 / 255, (colour, pixel)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "5 destruction: 1" in labels and "not assessable: 1" in labels and "0 no damage: 0" in labels
    assert "3 substantial to heavy (heavy): 0" in labels and "4 very heavy (extreme): 0" in labels
    _no_part(tmp_path)


def _texts(ax, gid):
    return [t.get_text() for t in ax.texts if t.get_gid() == gid]


def test_map_png_is_framed_on_the_buildings_with_ids_scale_bar_and_crs():
    """The frame is the outlines' extent plus the margin, not the scan area; every building
    of a small city carries its ID; a scale bar of a round length and the CRS are drawn."""
    boxes = {i: shapely.geometry.box(500000.0 + 30 * i, 5000000.0, 500020.0 + 30 * i, 5000015.0)
             for i in range(1, 5)}
    rows = [BuildingResult(i, 100, 100, True, grade=g, probabilities={g: 1.0}, share_changed=0.5,
                             decided_by="model") for i, g in zip(boxes, (0, 3, 4, 5))]
    outlines = {i: Outline(b, OUTLINE_FOOTPRINT) for i, b in boxes.items()}
    scan_area = np.random.default_rng(0).uniform([499000, 4999000], [501000, 5001000], (5000, 2))
    fig, ax = png_map._draw_map(rows, outlines, "framed", scan_area, "EPSG:32633")
    # buildings span x 500030..500140 (110 m), y 5000000..5000015: margin max(10, 0.08 * 110) = 10 m
    assert ax.get_xlim() == pytest.approx((500020.0, 500150.0))
    assert ax.get_ylim() == pytest.approx((4999990.0, 5000025.0))
    assert sorted(_texts(ax, "building-id")) == ["1", "2", "3", "4"]
    assert _texts(ax, "crs") == ["CRS: EPSG:32633 (WGS 84 / UTM zone 33N)"]
    bars = [a for a in ax.artists if a.get_gid() == "scale-bar"]
    assert len(bars) == 1
    bar_texts = [t.get_text() for t in bars[0].findobj(lambda o: hasattr(o, "get_text"))]
    assert "20 m" in bar_texts  # a fifth of 130 m → 20 m
    scatter = ax.collections[0].get_offsets()
    assert len(scatter) < 50 and (scatter[:, 0] >= 500020.0).all()  # the scan area outside the frame is left out
    _, ax = png_map._draw_map(rows, outlines, "no crs", None, None)
    assert _texts(ax, "crs")[0].startswith("CRS: unknown")


def test_map_labels_only_damaged_buildings_when_many():
    n = LABEL_ALL_MAX + 10
    grades = [0 if i % 3 else 4 for i in range(1, n + 1)]
    rows = [BuildingResult(i, 100, 100, True, grade=g, probabilities={g: 1.0}, decided_by="model")
            for i, g in zip(range(1, n + 1), grades)]
    rows.append(BuildingResult(n + 1, 3, 0, False, "3 pre-event points < 50"))
    outlines = {i: Outline(shapely.geometry.box(10 * i, 0, 10 * i + 8, 8), OUTLINE_HULL) for i in range(1, n + 2)}
    _, ax = png_map._draw_map(rows, outlines, "many", None, None)
    want = [str(i) for i, g in zip(range(1, n + 1), grades) if g > 0] + [str(n + 1)]
    assert sorted(_texts(ax, "building-id"), key=int) == want
    assert nice_length(130) == 20 and nice_length(1000) == 200 and nice_length(7) == 1


def test_map_draws_as_many_ids_as_can_be_read_the_worst_grade_first():
    """A district of 4,900 damaged buildings 4 m apart on one map: the IDs drawn do not cover
    each other (measured on the rendered text boxes, not the estimate), fewer than all are
    drawn, and where a grade 5 and a grade 1 building's labels would collide, the grade 5
    one is named. The HTML map still names them all (`labelled_ids`). Rows are 9 px apart,
    a label 11 px high: the grade 5 buildings (every 7th, in columns) cover each other too."""
    side = 70
    rows, outlines = [], {}
    for k in range(side * side):
        bid = 1000 + k
        grade = 5 if k % 7 == 0 else 1
        rows.append(BuildingResult(bid, 100, 100, True, grade=grade, probabilities={grade: 1.0},
                                     decided_by="model"))
        x, y = 4.0 * (k % side), 4.0 * (k // side)
        outlines[bid] = Outline(shapely.geometry.box(x, y, x + 3, y + 3), OUTLINE_HULL)
    fig, ax = png_map._draw_map(rows, outlines, "district", None, None)
    drawn = [t for t in ax.texts if t.get_gid() == "building-id"]
    assert len(labelled_ids(rows, outlines)) == side * side
    assert 20 < len(drawn) < side * side / 2
    fig.canvas.draw()  # lays the label boxes out
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_bbox_patch().get_window_extent(renderer) for t in drawn]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not a.overlaps(b), (a, b)
    # a grade 5 building left unnamed is one whose label would cover a named grade 5 one's:
    # no grade 1 label took its place
    named = {int(t.get_text()): b for t, b in zip(drawn, boxes)}
    fives = [r.building_id for r in rows if r.grade == 5]
    assert 0 < len(set(named) & set(fives)) < len(fives) and len(set(named) - set(fives)) > 0
    for f in set(fives) - set(named):
        p = outlines[f].geometry.representative_point()
        x, y = ax.transData.transform((p.x, p.y))
        # (the estimate is at most a pixel wider than the rendered box)
        assert any(abs(x - (b.x0 + b.x1) / 2) < b.width + 1 and abs(y - (b.y0 + b.y1) / 2) < b.height + 1
                   for n, b in named.items() if n in fives), f
    # two buildings 0.5 m apart: one label, the worse grade's, whatever their IDs' order
    pair = [BuildingResult(1, 100, 100, True, grade=1, probabilities={1: 1.0}, decided_by="model"),
            BuildingResult(2, 100, 100, True, grade=5, probabilities={5: 1.0}, decided_by="model")]
    far = [BuildingResult(i, 100, 100, True, grade=0, probabilities={0: 1.0}, decided_by="model")
           for i in range(3, 3 + LABEL_ALL_MAX)]
    lines = {1: shapely.geometry.box(0, 0, 3, 3), 2: shapely.geometry.box(0.5, 0, 3.5, 3)}
    lines.update({i: shapely.geometry.box(100.0 + 10 * i, 0, 103.0 + 10 * i, 3) for i in range(3, 3 + LABEL_ALL_MAX)})
    _, ax = png_map._draw_map(pair + far, {b: Outline(g, OUTLINE_HULL) for b, g in lines.items()}, "pair", None, None)
    assert _texts(ax, "building-id") == ["2"]


def test_legible_labels_keeps_boxes_apart_in_priority_order():
    """Closed form: a 10-pixel font's 2-character labels are (0.7 × 2 + 0.3) × 10 = 17 px
    wide and (1.05 + 0.3) × 10 = 13.5 px high."""
    anchors = np.array([[0.0, 0.0], [16.9, 0.0], [17.1, 0.0], [0.0, 13.4], [0.0, 13.6], [np.nan, 0.0]])
    assert legible_labels([10, 11, 12, 13, 14, 15], anchors, 10.0) == [10, 12, 14]
    assert legible_labels([11, 10], anchors[[1, 0]], 10.0) == [11]
    assert legible_labels([], np.zeros((0, 2)), 10.0) == []


def test_grade_las(tmp_path):
    rng = np.random.default_rng(1)
    n = 3000
    xyz = rng.uniform([0, 0, 0], [300, 300, 30], (n, 3)).round(3)  # local, on the mm grid
    xyz[:5] += 0.0004  # and some not
    ids = rng.integers(0, 5, n)
    grades = {1: 0, 2: 5, 3: None, 4: 3}  # 3 not assessable, 0 no building
    path = tmp_path / "post_grades.las"
    write_grade_las(path, xyz, ORIGIN, "EPSG:32633", ids, grades)
    las = laspy.read(path)
    assert las.header.version.minor == 4 and las.point_format.id == 7
    assert np.allclose(las.header.scales, 0.001) and np.allclose(las.header.offsets, ORIGIN)
    assert las.header.parse_crs().to_epsg() == 32633
    world = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    assert np.abs(world - (xyz + ORIGIN)).max() <= 0.0005 + 1e-9
    assert np.array_equal(np.asarray(las.building_id), ids)
    want = np.array([255 if grades.get(int(i)) is None else grades[int(i)] for i in ids])
    assert np.array_equal(np.asarray(las.predicted_grade), want)
    rgb = np.column_stack([las.red, las.green, las.blue])
    for b, colour in ((0, BACKGROUND_COLOUR), (1, GRADE_COLOURS[0]), (2, GRADE_COLOURS[5]),
                      (3, NOT_ASSESSABLE_COLOUR), (4, GRADE_COLOURS[3])):
        assert np.all(rgb[ids == b] == np.array(rgb8(colour)) * 257), b
    _no_part(tmp_path)


def test_grade_las_keeps_register_ids_longer_than_32_bits(tmp_path):
    """Dutch BAG IDs have 15-16 digits: uint32 would wrap every one to 4294967295."""
    ids = np.array([0, 363100012185103, 363100012185103, 4294967296, 7], np.int64)
    path = tmp_path / "post_grades.las"
    write_grade_las(path, np.zeros((5, 3)), ORIGIN, None, ids, {363100012185103: 4, 4294967296: 0, 7: 5})
    las = laspy.read(path)
    assert las.point_format.dimension_by_name("building_id").dtype == np.uint64
    assert np.array_equal(np.asarray(las.building_id).astype(np.int64), ids)
    assert np.asarray(las.predicted_grade).tolist() == [255, 4, 4, 0, 5]
    write_grade_las(path, np.zeros((2, 3)), ORIGIN, None, np.array([1, 2]), {1: 0})
    assert laspy.read(path).point_format.dimension_by_name("building_id").dtype == np.uint32  # IDs that fit: 4 bytes


def test_grade_las_without_ids_or_crs_and_laz(tmp_path):
    path = tmp_path / "g.laz"
    write_grade_las(path, np.array([[1.0, 2.0, 3.0]]), ORIGIN, None, None, {1: 5})
    las = laspy.read(path)
    assert las.predicted_grade.tolist() == [255] and las.header.parse_crs() is None
    with pytest.raises(ResultsError, match=".las or .laz"):
        write_grade_las(tmp_path / "g.txt", np.zeros((1, 3)), ORIGIN, None, None, {})
    _no_part(tmp_path)


def test_failed_write_leaves_nothing(tmp_path):
    path = tmp_path / "b.csv"

    class Boom(BuildingResult):
        @property
        def label(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_csv([Boom(1, 1, 1, True, grade=0)], path, CLASSES)
    assert not path.exists()
    _no_part(tmp_path)


def test_the_graded_las_streams_its_source_in_chunks_and_keeps_every_attribute(tmp_path, monkeypatch):
    """The source file is converted a chunk at a time (never whole beside the epoch): the same
    file whatever the chunk, every attribute of a legacy format kept; a source of another
    length is refused by name."""
    import laspy

    rng = np.random.default_rng(4)
    n = 11
    src = laspy.create(point_format=1, file_version="1.2")
    src.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
    src.header.offsets, src.header.scales = ORIGIN, [0.001] * 3
    xyz = rng.uniform(0, 20, (n, 3))
    src.x, src.y, src.z = (xyz[:, k] + ORIGIN[k] for k in range(3))
    src.intensity = rng.integers(0, 60000, n)
    src.gps_time = rng.uniform(0, 1e5, n)
    src.scan_angle_rank = rng.integers(-30, 30, n)
    src.reflectance = rng.uniform(-10, 0, n).astype(np.float32)
    src.write(tmp_path / "src.las")
    ids = np.arange(n) % 3
    whole, chunked = tmp_path / "whole.las", tmp_path / "chunked.las"
    write_grade_las(whole, xyz, ORIGIN, None, ids, {1: 3, 2: 5}, source=tmp_path / "src.las")
    monkeypatch.setattr("quakescan.results.graded_cloud.SOURCE_CHUNK_POINTS", 3)
    write_grade_las(chunked, xyz, ORIGIN, None, ids, {1: 3, 2: 5}, source=tmp_path / "src.las")
    a, b = laspy.read(whole), laspy.read(chunked)
    assert a.header.point_count == b.header.point_count == n
    for dim in a.points.array.dtype.names:
        np.testing.assert_array_equal(a.points.array[dim], b.points.array[dim], err_msg=dim)
    np.testing.assert_array_equal(b.intensity, src.intensity)
    np.testing.assert_allclose(b.gps_time, src.gps_time)
    np.testing.assert_allclose(np.asarray(b.scan_angle) * 0.006, src.scan_angle_rank, atol=0.003)  # 0.006° steps
    np.testing.assert_array_equal(b.reflectance, src.reflectance)
    np.testing.assert_array_equal(b.predicted_grade, np.where(ids == 1, 3, np.where(ids == 2, 5, 255)))
    with pytest.raises(ResultsError, match=r"the source .*src.las has 11 points, the epoch 10"):
        write_grade_las(tmp_path / "bad.las", xyz[:10], ORIGIN, None, ids[:10], {}, source=tmp_path / "src.las")
