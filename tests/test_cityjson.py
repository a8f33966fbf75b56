"""CityJSON import: real LoD2 files (Zurich v1.1, Rotterdam v2.0) and small hand-made files."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from quakescan.errors import SceneError
from quakescan.formats.cityjson import import_cityjson, parse_reference_system
from quakescan.formats.scene import GROUND, ROOF, WALL, read_scene, triangle_areas, validate_scene, write_scene

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ZURICH = DATA / "zurich_subset_lod2.json"
ROTTERDAM = DATA / "rotterdam_subset.json"
REAL_FILES = [ZURICH, ROTTERDAM]


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real-data file {path} is absent (the shared data folder ../shared/data is not "
                    "available in this checkout)")
    return path


# ---------------------------------------------------------------- helpers computed from the JSON alone


def _doc(path: Path) -> dict:
    return json.loads(path.read_text())


def _real_vertices(doc: dict) -> np.ndarray:
    v = np.array(doc["vertices"], dtype=np.float64)
    t = doc.get("transform")
    return v * t["scale"] + t["translate"] if t else v


def _expected_building_ids(doc: dict) -> list[str]:
    """Top-level Buildings plus BuildingParts none of whose parents exist, sorted."""
    objs = doc["CityObjects"]
    ids = [k for k, o in objs.items() if o["type"] == "Building"]
    ids += [k for k, o in objs.items() if o["type"] == "BuildingPart"
            and not any(p in objs for p in o.get("parents", []))]
    return sorted(ids)


def _rings(boundaries):
    """All rings (lists of ints) of any boundary nesting."""
    if boundaries and isinstance(boundaries[0], int):
        yield boundaries
    else:
        for b in boundaries:
            yield from _rings(b)


def _polygon_area(points: np.ndarray) -> float:
    p = points - points[0]
    return 0.5 * float(np.linalg.norm(np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)))


def _surface_areas(doc: dict) -> dict[str, float]:
    """Area per semantic type from the file's MultiSurface polygons (outer minus holes)."""
    v = _real_vertices(doc)
    out: dict[str, float] = {}
    for o in doc["CityObjects"].values():
        for g in o.get("geometry", []):
            assert g["type"] == "MultiSurface"  # both real files; keeps this helper independent and small
            for poly, s in zip(g["boundaries"], g["semantics"]["values"]):
                t = g["semantics"]["surfaces"][s]["type"]
                area = _polygon_area(v[poly[0]]) - sum(_polygon_area(v[h]) for h in poly[1:])
                out[t] = out.get(t, 0.0) + area
    return out


def _normals(scene) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3) unit face normals and (m,) areas."""
    v, f = scene.vertices, scene.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1)
    return n / length[:, None], length / 2


def _terrain_z(scene, xy: np.ndarray) -> np.ndarray:
    """Height of the terrain TIN at (q, 2) points (NaN outside), by barycentric search."""
    v, f = scene.vertices, scene.faces[scene.face_building == 0]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    out = np.full(len(xy), np.nan)
    for i, p in enumerate(xy):
        d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        l1 = ((p[0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[1] - a[:, 1])) / d
        l2 = ((b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (p[0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / d
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9)
        if inside.any():
            j = int(np.flatnonzero(inside)[0])
            out[i] = a[j, 2] + l1[j] * (b[j, 2] - a[j, 2]) + l2[j] * (c[j, 2] - a[j, 2])
    return out


@pytest.fixture(scope="module", params=REAL_FILES, ids=["zurich_v1.1", "rotterdam_v2.0"])
def real(request):
    path = _need(request.param)
    return path, _doc(path), import_cityjson(path)


# ---------------------------------------------------------------- real files


@pytest.mark.realdata
def test_real_buildings_ids_and_labels(real):
    path, doc, scene = real
    expected = _expected_building_ids(doc)
    assert len(scene.buildings) == len(expected)
    assert [b.id for b in scene.buildings] == list(range(1, len(expected) + 1))
    assert [b.extra["source_id"] for b in scene.buildings] == expected
    for b in scene.buildings:
        assert b.typology == "cityjson" and b.material == "masonry" and b.storeys >= 1 and b.grade == 0
    validate_scene(scene)  # every building has faces, no duplicate IDs, no degenerate faces
    assert set(np.unique(scene.face_building[scene.face_building > 0])) == set(range(1, len(expected) + 1))


@pytest.mark.realdata
def test_zurich_counts_and_crs():
    path = _need(ZURICH)
    doc = _doc(path)
    scene = import_cityjson(path)
    n_top = sum(o["type"] == "Building" for o in doc["CityObjects"].values())
    assert len(scene.buildings) == n_top == 49  # the 161 BuildingParts are merged into them
    assert scene.crs == "EPSG:2056"


@pytest.mark.realdata
def test_rotterdam_v2_has_no_crs():
    path = _need(ROTTERDAM)
    doc = _doc(path)
    assert doc["version"] == "2.0" and "metadata" not in doc
    scene = import_cityjson(path)
    assert len(scene.buildings) == 16
    assert scene.crs is None


@pytest.mark.realdata
def test_real_origin_and_bbox(real):
    path, doc, scene = real
    np.testing.assert_array_equal(scene.origin, np.array(doc["transform"]["translate"], dtype=np.float64))
    used = sorted({i for o in doc["CityObjects"].values() for g in o.get("geometry", [])
                   for r in _rings(g["boundaries"]) for i in r})
    real_v = _real_vertices(doc)[used]
    building_v = scene.vertices[np.unique(scene.faces[scene.face_building > 0])]
    assert scene.vertices.dtype == np.float64
    np.testing.assert_allclose(building_v.min(axis=0) + scene.origin, real_v.min(axis=0), rtol=0, atol=1e-3)
    np.testing.assert_allclose(building_v.max(axis=0) + scene.origin, real_v.max(axis=0), rtol=0, atol=1e-3)


@pytest.mark.realdata
def test_real_areas_match_the_files_polygons(real):
    """Triangulation keeps every semantic surface's area (outer rings minus holes)."""
    path, doc, scene = real
    expected = _surface_areas(doc)
    area = triangle_areas(scene.vertices, scene.faces)
    for code, name in [(GROUND, "GroundSurface"), (ROOF, "RoofSurface")]:
        got = area[(scene.face_building > 0) & (scene.face_surface == code)].sum()
        assert got == pytest.approx(expected[name], rel=1e-4), name
    # walls: the file's, and those that close its open shells (quakescan.formats.shell), vertical
    walls = (scene.face_building > 0) & (scene.face_surface == WALL)
    assert area[walls].sum() >= expected["WallSurface"] * (1 - 1e-4)
    normal, _ = _normals(scene)
    added = area[walls].sum() - expected["WallSurface"]
    assert (np.abs(normal[walls, 2]) * area[walls]).sum() < 0.01 * area[walls].sum()
    assert added < 1.0 * expected["WallSurface"]


@pytest.mark.realdata
def test_real_normals(real):
    """Roofs face up, walls are vertical, grounds face down (CityJSON surfaces face outwards)."""
    path, doc, scene = real
    normal, area = _normals(scene)
    bld = scene.face_building > 0
    for b in scene.buildings:
        roof = (scene.face_building == b.id) & (scene.face_surface == ROOF)
        assert roof.any(), b
        mean = (normal[roof] * area[roof, None]).sum(axis=0)
        assert mean[2] / np.linalg.norm(mean) > 0.8, b
    wall = bld & (scene.face_surface == WALL)
    assert np.abs(normal[wall & (area > 1e-3), 2]).max() < 0.3  # no sliver lies across a wall
    assert (np.abs(normal[wall, 2]) * area[wall]).sum() / area[wall].sum() < 0.01
    ground = bld & (scene.face_surface == GROUND)
    assert (normal[ground, 2] < -0.9).all()


@pytest.mark.realdata
def test_real_roofs_cover_footprints(real):
    """Per building, the roofs' horizontal projection covers at least the ground surface."""
    path, doc, scene = real
    normal, area = _normals(scene)
    for b in scene.buildings:
        mine = scene.face_building == b.id
        roof = mine & (scene.face_surface == ROOF)
        ground = mine & (scene.face_surface == GROUND)
        # horizontal projections: some Zurich ground surfaces are sloped (up to 2.8 m)
        footprint = -(area[ground] * normal[ground, 2]).sum()
        assert footprint > 0, b
        assert (area[roof] * normal[roof, 2]).sum() >= 0.99 * footprint, b
        assert area[roof].sum() >= 0.99 * footprint, b


@pytest.mark.realdata
def test_real_terrain(real):
    path, doc, scene = real
    terrain = scene.face_building == 0
    assert terrain.sum() > 0
    assert (scene.face_surface[terrain] == GROUND).all()
    normal, area = _normals(scene)
    assert (area[terrain] > 1e-10).all()
    assert (normal[terrain, 2] > 0).all()  # counter-clockwise seen from above
    tv = scene.vertices[np.unique(scene.faces[terrain])]
    bv = scene.vertices[np.unique(scene.faces[~terrain])]
    # default margin 20 m around the buildings' x/y box
    np.testing.assert_allclose(tv[:, :2].min(axis=0), bv[:, :2].min(axis=0) - 20.0, atol=1e-6)
    np.testing.assert_allclose(tv[:, :2].max(axis=0), bv[:, :2].max(axis=0) + 20.0, atol=1e-6)
    # every building's lowest vertex stands on the terrain, also on Zurich's slopes
    lowest = []
    for b in scene.buildings:
        v = scene.vertices[np.unique(scene.faces[scene.face_building == b.id])]
        lowest.append(v[np.argmin(v[:, 2])])
    lowest = np.array(lowest)
    z = _terrain_z(scene, lowest[:, :2])
    assert np.isfinite(z).all()  # inside the TIN
    np.testing.assert_allclose(z, lowest[:, 2], atol=0.05)


@pytest.mark.realdata
def test_real_round_trip(real, tmp_path):
    path, doc, scene = real
    folder = write_scene(scene, tmp_path / "scene")
    back = read_scene(folder)
    np.testing.assert_array_equal(back.vertices, scene.vertices)
    np.testing.assert_array_equal(back.faces, scene.faces)
    np.testing.assert_array_equal(back.face_building, scene.face_building)
    np.testing.assert_array_equal(back.face_surface, scene.face_surface)
    np.testing.assert_array_equal(back.origin, scene.origin)
    assert back.crs == scene.crs
    assert [(b.id, b.storeys, b.extra["source_id"]) for b in back.buildings] == \
        [(b.id, b.storeys, b.extra["source_id"]) for b in scene.buildings]


# ---------------------------------------------------------------- hand-made files

BOX_FACES = [  # outward: bottom, top, 4 walls (vertex numbers of a box, see _box_vertices)
    ([0, 3, 2, 1], "GroundSurface"), ([4, 5, 6, 7], "RoofSurface"),
    ([0, 1, 5, 4], "WallSurface"), ([1, 2, 6, 5], "WallSurface"),
    ([2, 3, 7, 6], "WallSurface"), ([3, 0, 4, 7], "WallSurface"),
]


def _box_vertices(x0, y0, x1, y1, z0, z1):
    return [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
            [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]


class _Model:
    """Builds a small CityJSON document (real coordinates, written with a transform)."""

    def __init__(self, version="2.0"):
        self.version = version
        self.vertices: list = []
        self.objects: dict = {}

    def box_geometry(self, x0, y0, x1, y1, z0, z1, kind="Solid", lod="2", semantics=True):
        n = len(self.vertices)
        self.vertices += _box_vertices(x0, y0, x1, y1, z0, z1)
        surfaces = [[[n + i for i in ring]] for ring, _ in BOX_FACES]
        names = ["GroundSurface", "RoofSurface", "WallSurface"]
        values = [names.index(t) for _, t in BOX_FACES]
        if kind == "Solid":
            boundaries, values = [surfaces], [values]
        elif kind == "MultiSolid":
            boundaries, values = [[surfaces]], [[values]]
        else:
            boundaries = surfaces
        g = {"type": kind, "lod": lod, "boundaries": boundaries}
        if semantics:
            g["semantics"] = {"surfaces": [{"type": t} for t in names], "values": values}
        return g

    def add(self, oid, kind, geometry=(), **extra):
        self.objects[oid] = {"type": kind, "geometry": list(geometry), **extra}

    def write(self, path: Path, translate=(2600000.0, 1200000.0, 400.0), crs="urn:ogc:def:crs:EPSG::2056"):
        scale = 0.001
        ints = [[round((c - t) / scale) for c, t in zip(v, translate)] for v in self.vertices]
        doc = {"type": "CityJSON", "version": self.version, "CityObjects": self.objects, "vertices": ints,
               "transform": {"scale": [scale] * 3, "translate": list(translate)}}
        if crs:
            doc["metadata"] = {"referenceSystem": crs}
        path.write_text(json.dumps(doc))
        return path


def test_parse_reference_system():
    assert parse_reference_system("https://www.opengis.net/def/crs/EPSG/0/2056") == "EPSG:2056"
    assert parse_reference_system("http://www.opengis.net/def/crs/EPSG/0/7415") == "EPSG:7415"
    assert parse_reference_system("urn:ogc:def:crs:EPSG::7415") == "EPSG:7415"
    assert parse_reference_system("EPSG:2056") == "EPSG:2056"
    assert parse_reference_system(None) is None
    assert parse_reference_system("https://www.opengis.net/def/crs/OGC/1.3/CRS84") is None


def test_solid_box_parts_and_precision(tmp_path):
    """Building → BuildingPart → BuildingPart (+ installation) is one building; coordinates
    of millions of metres keep their millimetres; an orphan part is a building of its own."""
    m = _Model()
    m.add("B", "Building", [m.box_geometry(0, 0, 10, 8, 0, 9)], children=["P1"],
          attributes={"measuredHeight": 12.2})
    m.add("P1", "BuildingPart", [m.box_geometry(10, 0, 14, 8, 0, 6, kind="MultiSolid")], parents=["B"],
          children=["P2"])
    m.add("P2", "BuildingPart", [m.box_geometry(14, 0, 16.001, 8, 0, 3, kind="CompositeSurface")])
    m.add("I", "BuildingInstallation", [m.box_geometry(0, 8, 2, 9, 0, 2, kind="MultiSurface")], parents=["P1"])
    m.add("A-orphan", "BuildingPart", [m.box_geometry(40, 0, 45, 5, 1, 4)], parents=["gone"])
    scene = import_cityjson(m.write(tmp_path / "city.json"), terrain_margin=5.0)
    validate_scene(scene)
    assert [b.extra["source_id"] for b in scene.buildings] == ["A-orphan", "B"]
    orphan, main = scene.buildings
    assert main.storeys == 4  # measuredHeight 12.2 m / 3 m
    assert orphan.storeys == 1  # 3 m box
    assert scene.crs == "EPSG:2056"
    np.testing.assert_array_equal(scene.origin, [2600000.0, 1200000.0, 400.0])
    # 4 boxes × 12 triangles in building 2, 12 in building 1
    assert (scene.face_building == 2).sum() == 48 and (scene.face_building == 1).sum() == 12
    v = scene.vertices[np.unique(scene.faces[scene.face_building == 2])]
    assert v[:, 0].max() == pytest.approx(16.001 - 2600000.0, abs=1e-9)
    assert v[:, 2].min() == pytest.approx(-400.0, abs=1e-9)
    normal, area = _normals(scene)
    bld = scene.face_building > 0
    assert (normal[bld & (scene.face_surface == ROOF), 2] > 0.999).all()
    assert (normal[bld & (scene.face_surface == GROUND), 2] < -0.999).all()
    assert (np.abs(normal[bld & (scene.face_surface == WALL), 2]) < 1e-9).all()


def test_holes_orientation_and_missing_semantics(tmp_path):
    """A flat roof with a courtyard hole keeps its area and faces up; faces without semantics
    are labelled by their normal; the courtyard gets the walls the file does not hold."""
    m = _Model(version="1.1")
    m.vertices = _box_vertices(0, 0, 20, 20, 0, 6) + [[5, 5, 6], [5, 15, 6], [15, 15, 6], [15, 5, 6]]
    walls = [[ring] for ring, t in BOX_FACES if t == "WallSurface"]
    roof = [[4, 5, 6, 7], [8, 9, 10, 11]]  # outer counter-clockwise from above, hole clockwise
    ground = [[0, 3, 2, 1]]
    m.add("B", "Building", [{"type": "MultiSurface", "lod": 2, "boundaries": [roof, ground] + walls}])
    scene = import_cityjson(m.write(tmp_path / "c.json", crs=None))
    assert scene.crs is None
    normal, area = _normals(scene)
    b = scene.face_building == 1
    roof_faces = b & (scene.face_surface == ROOF)
    assert area[roof_faces].sum() == pytest.approx(400 - 100)
    assert (normal[roof_faces, 2] > 0.999).all()
    assert area[b & (scene.face_surface == GROUND)].sum() == pytest.approx(400)
    # the outer walls, and the courtyard's, which the file leaves out: they close its shell
    assert area[b & (scene.face_surface == WALL)].sum() == pytest.approx(4 * 20 * 6 + 4 * 10 * 6)
    assert scene.buildings[0].storeys == 2  # 6 m / 3 m from the geometry


def test_lod_selection(tmp_path):
    m = _Model()
    m.add("B", "Building", [m.box_geometry(0, 0, 10, 10, 0, 3, lod="1"),
                            m.box_geometry(0, 0, 10, 10, 0, 12, lod="2.2")])
    path = m.write(tmp_path / "c.json")

    def top(scene):
        return scene.vertices[np.unique(scene.faces[scene.face_building > 0]), 2].max() + scene.origin[2]

    assert top(import_cityjson(path)) == pytest.approx(12)  # highest LoD by default
    assert top(import_cityjson(path, lod="1")) == pytest.approx(3)
    assert top(import_cityjson(path, lod="2")) == pytest.approx(12)  # "2" accepts "2.2"
    with pytest.raises(SceneError, match=r"c\.json.*LoD '3'.*\['1', '2\.2'\]"):
        import_cityjson(path, lod="3")


def test_buildings_lacking_the_requested_lod_are_left_out(tmp_path, caplog):
    m = _Model()
    m.add("A", "Building", [m.box_geometry(0, 0, 10, 10, 0, 3, lod="1")])
    m.add("B", "Building", [m.box_geometry(20, 0, 30, 10, 0, 3, lod="1"),
                            m.box_geometry(20, 0, 30, 10, 0, 6, lod="2")])
    with caplog.at_level(logging.WARNING, logger="quakescan.formats.cityjson"):
        scene = import_cityjson(m.write(tmp_path / "c.json"), lod="2")
    assert [(b.id, b.extra["source_id"]) for b in scene.buildings] == [(1, "B")]
    assert "1 buildings have no surface geometry at LoD '2'" in caplog.text
    assert len(import_cityjson(tmp_path / "c.json", lod=1).buildings) == 2  # CityJSON 1.0 numbers work too


def test_degenerate_and_closure_polygons_are_dropped(tmp_path, caplog):
    m = _Model()
    g = m.box_geometry(0, 0, 10, 10, 0, 6, kind="MultiSurface")
    n = len(m.vertices)
    m.vertices += [[0, 0, 0], [5, 0, 0], [10, 0, 0]]  # collinear
    g["boundaries"] += [[[0, 0, 1, 1]], [[n, n + 1, n + 2]], [[0, 1, 5]]]
    g["semantics"]["surfaces"].append({"type": "ClosureSurface"})
    g["semantics"]["values"] += [2, 2, 3]
    m.add("B", "Building", [g])
    with caplog.at_level(logging.INFO, logger="quakescan.formats.cityjson"):
        scene = import_cityjson(m.write(tmp_path / "c.json"))
    validate_scene(scene)
    assert (scene.face_building == 1).sum() == 12  # the box only
    text = caplog.text
    assert "short_polygons_dropped 1" in text and "degenerate_polygons_dropped 1" in text
    assert "closure_surfaces_dropped 1" in text


def test_without_transform_origin_is_floor_of_min_corner(tmp_path):
    m = _Model()
    m.add("B", "Building", [m.box_geometry(2600000.123, 1200000.456, 2600010.5, 1200008.25, 401.75, 410.0)])
    doc = json.loads(m.write(tmp_path / "c.json").read_text())
    doc["vertices"] = m.vertices
    del doc["transform"]
    (tmp_path / "c.json").write_text(json.dumps(doc))
    scene = import_cityjson(tmp_path / "c.json")
    np.testing.assert_array_equal(scene.origin, [2600000.0, 1200000.0, 401.0])
    v = scene.vertices[np.unique(scene.faces[scene.face_building == 1])]
    np.testing.assert_array_equal(v.min(axis=0), np.array([2600000.123, 1200000.456, 401.75]) - scene.origin)


# ---------------------------------------------------------------- errors


def _write(tmp_path, doc, name="bad.json"):
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


def test_error_missing_file(tmp_path):
    with pytest.raises(SceneError, match=r"nope\.json: CityJSON file does not exist"):
        import_cityjson(tmp_path / "nope.json")


def test_error_not_json(tmp_path):
    with pytest.raises(SceneError, match=r"bad\.json: not valid JSON"):
        import_cityjson(_write(tmp_path, "{not json"))


def test_error_not_cityjson(tmp_path):
    with pytest.raises(SceneError, match=r"bad\.json: not a CityJSON file \(type is 'FeatureCollection'"):
        import_cityjson(_write(tmp_path, {"type": "FeatureCollection", "features": []}))


def test_error_unsupported_version(tmp_path):
    doc = {"type": "CityJSON", "version": "0.9", "CityObjects": {}, "vertices": []}
    with pytest.raises(SceneError, match=r"bad\.json: CityJSON version '0\.9' is not supported"):
        import_cityjson(_write(tmp_path, doc))


def test_error_no_buildings(tmp_path):
    doc = {"type": "CityJSON", "version": "2.0", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
           "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
           "CityObjects": {"t": {"type": "TINRelief", "geometry": [
               {"type": "CompositeSurface", "lod": "1", "boundaries": [[[0, 1, 2]]]}]}}}
    with pytest.raises(SceneError, match=r"bad\.json: no Building objects.*TINRelief"):
        import_cityjson(_write(tmp_path, doc))


def test_error_vertex_index_out_of_range(tmp_path):
    m = _Model()
    g = m.box_geometry(0, 0, 10, 10, 0, 6)
    g["boundaries"][0][1] = [[4, 5, 6, 99]]
    m.add("B", "Building", [g])
    with pytest.raises(SceneError, match=r"c\.json: CityObject 'B' refers to vertex 99 but the file has only 8"):
        import_cityjson(m.write(tmp_path / "c.json"))


def test_error_buildings_without_geometry(tmp_path):
    m = _Model()
    m.add("B", "Building", [])
    with pytest.raises(SceneError, match=r"c\.json: none of the 1 buildings has surface geometry"):
        import_cityjson(m.write(tmp_path / "c.json"))


@pytest.mark.realdata
def test_import_keeps_the_buildings_of_a_box_and_warns_about_wide_scenes(tmp_path, capsys):
    """Rotterdam: 15 buildings within 80 m and one 500 m away; a box around the cluster
    keeps the 15 and the terrain around them only. Zurich's 49 buildings span kilometres:
    the import says so before anyone flies a survey over it."""
    from quakescan.cli import main
    from quakescan.formats.scene import read_scene

    if not ROTTERDAM.is_file() or not ZURICH.is_file():
        pytest.skip("real city models absent")
    assert main(["import-cityjson", str(ROTTERDAM), "-o", str(tmp_path / "box"), "--bbox",
                 "90900,435600,91000,435700", "--buffer", "10"]) == 0
    scene = read_scene(tmp_path / "box")
    assert len(scene.buildings) == 15
    span = scene.bounds()[1, :2] - scene.bounds()[0, :2]
    assert span.max() < 150  # not the 590 m of the whole model
    with pytest.raises(SystemExit):
        main(["import-cityjson", str(ROTTERDAM), "-o", str(tmp_path / "bad"), "--bbox", "1,2,0,3"])
    capsys.readouterr()
    assert main(["import-cityjson", str(ZURICH), "-o", str(tmp_path / "zurich")]) == 0
    assert "warning: the scene spans" in capsys.readouterr().err


# ---------------------------------------------------------------- terrain patches, --crs, --material


def test_terrain_only_around_each_cluster_of_buildings(tmp_path):
    """Two clusters 5.8 km apart: the terrain is the two clusters' boxes grown by the margin
    (65 m × 48 m and 50 m × 48 m = 5 520 m²), not the 15 km² of the whole extent."""
    m = _Model()
    m.add("A1", "Building", [m.box_geometry(0, 0, 10, 8, 0, 9)])
    m.add("A2", "Building", [m.box_geometry(15, 0, 25, 8, 0, 6)])  # 5 m from A1: the same cluster
    m.add("B", "Building", [m.box_geometry(5000, 3000, 5010, 3008, 0, 12)])
    scene = import_cityjson(m.write(tmp_path / "two.json", translate=(0.0, 0.0, 0.0)), terrain_margin=20.0)
    terrain = scene.face_building == 0
    area = triangle_areas(scene.vertices, scene.faces[terrain]).sum()
    assert area == pytest.approx(65 * 48 + 50 * 48, rel=1e-9)
    # each building still stands on terrain, and the patches do not overlap
    for b in scene.buildings:
        v = scene.vertices[np.unique(scene.faces[scene.face_building == b.id])]
        assert np.isfinite(_terrain_z(scene, v[:, :2].mean(axis=0, keepdims=True))).all()


def test_clusters_whose_grown_boxes_overlap_share_one_patch():
    from quakescan.formats.cityjson import building_clusters

    boxes = np.array([[0, 0, 10, 10], [55, 0, 65, 10], [200, 0, 210, 10], [30, 60, 40, 70.0]])
    # 0 and 1 are 45 m apart (< 2 × 25): one cluster; its grown box [-25, 90] × [-25, 35] and
    # box 3's grown [5, 65] × [35, 95] touch at y = 35: merged as well; 2 stays alone
    labels = building_clusters(boxes, 25.0)
    assert labels[0] == labels[1] == labels[3] != labels[2]
    assert len(set(building_clusters(boxes, 1.0).tolist())) == 4


def test_crs_for_files_that_name_none_and_a_disagreement_is_refused(tmp_path, caplog):
    m = _Model()
    m.add("B", "Building", [m.box_geometry(0, 0, 10, 8, 0, 9)])
    none = m.write(tmp_path / "none.json", crs=None)
    assert import_cityjson(none).crs is None
    assert import_cityjson(none, crs="EPSG:2056").crs == "EPSG:2056"
    named = m.write(tmp_path / "named.json")  # urn:ogc:def:crs:EPSG::2056
    assert import_cityjson(named, crs="epsg:2056").crs == "EPSG:2056"
    with pytest.raises(SceneError, match=r"named\.json: the file names its CRS EPSG:2056 .* but --crs is 'EPSG:28992'"):
        import_cityjson(named, crs="EPSG:28992")
    for bad, text in (("EPSG:999999", "not a coordinate reference system PROJ knows"),
                      ("EPSG:4326", r"axes in \['degree'\]")):
        with pytest.raises(SceneError, match=text):
            import_cityjson(m.write(tmp_path / "bad.json", crs=bad))
        with pytest.raises(SceneError, match=f"--crs {bad}: .*{text}"):
            import_cityjson(none, crs=bad)
    with pytest.raises(SceneError, match=r"--crs 'garbage': expected an EPSG code"):
        import_cityjson(none, crs="garbage")
    garbage = m.write(tmp_path / "garbage.json", crs="garbage")
    with pytest.raises(SceneError, match=r"garbage\.json: metadata\.referenceSystem 'garbage' is not an EPSG code"):
        import_cityjson(garbage)
    with caplog.at_level(logging.WARNING):
        assert import_cityjson(garbage, crs="EPSG:2056").crs == "EPSG:2056"
    assert "using --crs EPSG:2056" in caplog.text


def test_material_for_every_imported_building(tmp_path):
    m = _Model()
    m.add("B", "Building", [m.box_geometry(0, 0, 10, 8, 0, 9)])
    m.add("C", "Building", [m.box_geometry(20, 0, 30, 8, 0, 9)])
    path = m.write(tmp_path / "c.json")
    assert {b.material for b in import_cityjson(path).buildings} == {"masonry"}
    assert {b.material for b in import_cityjson(path, material="reinforced_concrete").buildings} == \
        {"reinforced_concrete"}
    with pytest.raises(SceneError, match=r"--material\) must be one of"):
        import_cityjson(path, material="wood")


@pytest.mark.parametrize("version", ["1.1", "2.0"])
def test_a_file_without_transform_is_read_by_its_version(tmp_path, version, caplog):
    """1.1 and 2.0 require a transform: integers without one have no known scale and are
    refused (they were read as metres: 1000 times too large); real numbers are coordinates."""
    m = _Model(version)
    m.add("B", "Building", [m.box_geometry(2600000.5, 1200000.25, 2600010.5, 1200008.25, 400.0, 409.0)])
    doc = json.loads(m.write(tmp_path / "c.json").read_text())
    del doc["transform"]  # the integer millimetres stay
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=rf"c\.json: CityJSON {version} requires 'transform'"):
        import_cityjson(tmp_path / "c.json")
    doc["vertices"] = m.vertices
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        scene = import_cityjson(tmp_path / "c.json")
    assert "read as coordinates in metres" in caplog.text
    span = scene.bounds()[1] - scene.bounds()[0]
    assert span[0] == pytest.approx(10.0 + 40.0)  # the building and 20 m of terrain either side


def test_cityjson_1_0_without_transform_has_real_coordinates(tmp_path):
    m = _Model("1.0")
    m.add("B", "Building", [m.box_geometry(1000, 2000, 1010, 2008, 0, 9)])
    doc = json.loads(m.write(tmp_path / "c.json").read_text())
    doc["vertices"] = m.vertices  # integers, and metres
    del doc["transform"]
    (tmp_path / "c.json").write_text(json.dumps(doc))
    scene = import_cityjson(tmp_path / "c.json")
    v = scene.vertices[np.unique(scene.faces[scene.face_building == 1])] + scene.origin
    np.testing.assert_allclose(v.min(axis=0), [1000, 2000, 0])
    np.testing.assert_allclose(v.max(axis=0), [1010, 2008, 9])
