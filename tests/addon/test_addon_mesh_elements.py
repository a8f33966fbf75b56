"""Elements from a building mesh's own faces (addon/geometry/mesh_elements.py): an L-shaped
building with a gable roof built from vertices; closed-form volumes, no overlaps, shards
that tile the elements. numpy only."""
import math

import numpy as np
import pytest

from addon.geometry import fracture as fr
from addon.geometry import mesh_elements as mel
from addon.geometry import poly2d
from tests.addon.l_building import EAVE, FOOTPRINT, PITCH, RIDGE, l_building, roof_z

COS = math.cos(math.radians(PITCH))
M = fr.MATERIAL["masonry"]
FOOT_AREA = 20 * 8 + 8 * 10


def _build(**kw):
    v, f, s = l_building()
    return mel.mesh_elements(v, f, s, material="masonry", **kw)


def _top(e) -> float:
    return float(np.concatenate(e.solid.faces)[:, 2].max())


def _count(els, q):
    return sum(e.solid.contains(q, tol=-1e-9).astype(int) for e in els)


def test_l_outline_eaves_and_closed_form_volumes():
    mb = _build(storeys=2, storey_height=3.0)
    assert mb.footprint_source == "ground"
    assert sorted(map(tuple, mb.footprint.tolist())) == sorted(map(tuple, np.array(FOOTPRINT, float).tolist()))
    assert poly2d.area(mb.footprint) == pytest.approx(FOOT_AREA)  # counter-clockwise
    eave = EAVE - M["roof"] / COS  # under the roof plates' undersides
    assert np.allclose(mb.eaves, eave)
    assert (mb.storeys, mb.storey_height, mb.roof_planes, mb.roof_faces_skipped) == (2, 3.0, 4, 0)
    by = {}
    for e in mb.elements:
        by[e.part] = by.get(e.part, 0.0) + e.volume
    # the four roof planes cover the footprint; plates M["roof"] thick across their plane
    assert by[fr.P_ROOF] == pytest.approx(FOOT_AREA * M["roof"] / COS, rel=1e-9)
    ring = FOOT_AREA - (19.2 * 7.2 + 7.2 * 10)  # footprint minus the walls' inner outline
    assert by[fr.P_WALL] == pytest.approx(ring * (eave - M["slab"]), rel=1e-9)  # cut where the slab passes
    assert by[fr.P_SLAB] == pytest.approx(FOOT_AREA * M["slab"], rel=1e-9)  # one floor at 3 m; no attic floor
    # the gable walls at x = 20 and y = 18 reach up under the ridge
    top = {}
    for e in mb.elements:
        if e.part == fr.P_GABLE:
            top[e.elem] = max(top.get(e.elem, 0.0), float(np.concatenate(e.solid.faces)[:, 2].max()))
    for x, y in ((20, 4), (4, 18)):
        i = [k for k in range(6) if poly2d.boundary_distance(mb.footprint[[k, (k + 1) % 6]], [(x, y)])[0] < 1e-9][0]
        assert top[i] == pytest.approx(RIDGE - M["roof"] / COS, abs=1e-6)


def test_l_elements_do_not_overlap_and_stay_inside_the_building():
    mb = _build(storeys=2, storey_height=3.0)
    rng = np.random.default_rng(1)
    q = rng.uniform((0, 0, 0), (20, 18, RIDGE), (40000, 3))
    c = _count(mb.elements, q)
    assert c.max() == 1
    inside = poly2d.contains(np.array(FOOTPRINT, float), q[:, :2]) & (q[:, 2] < roof_z(q[:, 0], q[:, 1]))
    assert not c[~inside].any()  # nothing outside the footprint or above the roof
    for e in mb.elements:
        v = np.concatenate(e.solid.faces)
        assert (v[:, 2] <= roof_z(v[:, 0], v[:, 1]) + 1e-9).all()
        assert (poly2d.signed_distance(np.array(FOOTPRINT, float), v[:, :2]) <= 1e-9).all()


def test_l_shards_tile_the_elements():
    mb = _build(storeys=2, storey_height=3.0)
    rng = np.random.default_rng(4)
    total = n = 0
    for e in mb.elements:
        cells = fr.voronoi_cells(e.solid, fr.seed_points(e.solid, rng, (0, 0, 0), 0.6, 2.0))
        n += len(cells)
        total += sum(c.volume() for _, c in cells)
    assert total == pytest.approx(sum(e.volume for e in mb.elements), rel=1e-9)
    assert n > 3 * len(mb.elements)


def test_storeys_from_the_eaves_when_not_given():
    mb = _build()
    assert mb.storey_height == mel.DEFAULT_STOREY_HEIGHT
    assert mb.storeys == round((EAVE - M["roof"] / COS) / mel.DEFAULT_STOREY_HEIGHT)
    slabs = {round(_top(e), 9) for e in mb.elements if e.part == fr.P_SLAB}
    assert slabs == {3.0}


def test_outline_from_the_walls_without_a_ground_face():
    v, f, s = l_building()
    keep = [i for i in range(len(f)) if s[i] != 0]
    mb = mel.mesh_elements(v, [f[i] for i in keep], s[keep], storeys=2, storey_height=3.0)
    assert mb.footprint_source == "walls"
    assert abs(poly2d.area(mb.footprint)) == pytest.approx(FOOT_AREA)
    same = _build(storeys=2, storey_height=3.0)
    assert sum(e.volume for e in mb.elements) == pytest.approx(sum(e.volume for e in same.elements), rel=1e-12)


def test_non_planar_and_degenerate_roof_faces_are_skipped():
    v, f, s = l_building()
    roof = [i for i in range(len(f)) if s[i] == 1]
    v = v.copy()
    a_south = roof[0]  # (0,0,H) (20,0,H) (20,4,R) (4,4,R): lift the corner at (20, 4) off its plane
    v[f[a_south][2], 2] += 0.5
    n = len(v)
    v = np.vstack([v, [(10, 0, EAVE), (10.001, 0, EAVE), (10.0005, 0.0, EAVE)]])  # zero area
    f = f + [[n, n + 1, n + 2]]
    s = np.append(s, 1)
    mb = mel.mesh_elements(v, f, s, storeys=2, storey_height=3.0)
    assert mb.roof_faces_skipped == 2 and mb.roof_planes == 3
    # no plate stands for the skipped plane: the roof's volume is the three others'
    roof = sum(e.volume for e in mb.elements if e.part == fr.P_ROOF)
    south = 0.5 * (20 + 16) * 4  # A south's projection: a trapezoid
    assert roof == pytest.approx((FOOT_AREA - south) * M["roof"] / COS, rel=1e-9)
    q = np.random.default_rng(2).uniform((0, 0, 0), (20, 18, RIDGE + 1), (20000, 3))
    assert _count(mb.elements, q).max() == 1


def test_short_facade_steps_are_closed_up():
    p = np.array([(0, 0), (10, 0), (10, 5), (10.2, 5), (10.2, 8), (0, 8)], float)
    q = mel.close_short_edges(p)
    assert len(q) == 5 and abs(poly2d.area(q) - poly2d.area(p)) < 0.2 * 3


def test_a_mesh_without_an_outline_is_refused():
    v, f, s = l_building()
    roof = [i for i in range(len(f)) if s[i] == 1]
    with pytest.raises(mel.MeshElementsError, match="outline"):
        mel.mesh_elements(v, [f[i] for i in roof], s[roof])


def _stepped():
    """10 x 8 m, a flat roof at 6 m over x < 5 and at 9 m over x > 5 (a step wall between)."""
    v, f, s = [], [], []

    def face(pts, code):
        f.append(list(range(len(v), len(v) + len(pts))))
        v.extend(pts)
        s.append(code)
    face([(0, 0, 0), (0, 8, 0), (10, 8, 0), (10, 0, 0)], 0)
    face([(0, 0, 0), (10, 0, 0), (10, 0, 9), (5, 0, 9), (5, 0, 6), (0, 0, 6)], 2)
    face([(10, 8, 0), (0, 8, 0), (0, 8, 6), (5, 8, 6), (5, 8, 9), (10, 8, 9)], 2)
    face([(10, 0, 0), (10, 8, 0), (10, 8, 9), (10, 0, 9)], 2)
    face([(0, 8, 0), (0, 0, 0), (0, 0, 6), (0, 8, 6)], 2)
    face([(5, 0, 6), (5, 0, 9), (5, 8, 9), (5, 8, 6)], 2)
    face([(0, 0, 6), (5, 0, 6), (5, 8, 6), (0, 8, 6)], 1)
    face([(5, 0, 9), (10, 0, 9), (10, 8, 9), (5, 8, 9)], 1)
    return np.array(v, dtype=np.float64), f, np.array(s)


def test_stepped_roof_walls_and_slabs_follow_each_level():
    v, f, s = _stepped()
    mb = mel.mesh_elements(v, f, s, storeys=3, storey_height=3.0)
    tr, ts = M["roof"], M["slab"]
    assert mb.roof_planes == 2
    q = np.random.default_rng(5).uniform((0, 0, 0), (10, 8, 9), (30000, 3))
    assert _count(mb.elements, q).max() == 1
    walls = [e for e in mb.elements if e.part == fr.P_WALL]
    low_part = [e for e in walls if np.concatenate(e.solid.faces)[:, 0].max() <= 5 + 1e-9]
    assert max(_top(e) for e in low_part) == pytest.approx(6 - tr)
    assert max(_top(e) for e in walls) == pytest.approx(9 - tr)
    slab = {}
    for e in mb.elements:
        if e.part == fr.P_SLAB:
            slab[round(_top(e), 9)] = slab.get(round(_top(e), 9), 0.0) + e.volume
    # a floor at 3 m everywhere, at 6 m under the high roof only (the low roof is there)
    assert slab == pytest.approx({3.0: 80 * ts, 6.0: 40 * ts})
    assert sum(e.volume for e in mb.elements if e.part == fr.P_ROOF) == pytest.approx(80 * tr)
