"""geometry.poly2d (numpy only)."""
import math

import numpy as np

from addon.geometry import poly2d


def test_area_centroid_contains():
    sq = poly2d.rect(0, 0, 4, 2)
    assert poly2d.area(sq) == 8.0
    assert poly2d.area(sq[::-1]) == -8.0
    np.testing.assert_allclose(poly2d.centroid(sq), [2, 1])
    assert poly2d.contains(sq, [(1, 1), (5, 1), (-0.1, 0.5)]).tolist() == [True, False, False]


def test_signed_distance():
    sq = poly2d.rect(0, 0, 4, 2)
    d = poly2d.signed_distance(sq, [(2, 1), (6, 1), (2, 5)])
    np.testing.assert_allclose(d, [-1, 2, 3])


def test_convex_overlap_with_tolerance():
    sq = poly2d.rect(0, 0, 4, 2)
    assert poly2d.convex_overlap(sq, poly2d.rect(3, 1, 6, 4), 0.0)
    assert not poly2d.convex_overlap(sq, poly2d.rect(4, 0, 6, 2), 0.0)  # touching is not overlapping
    assert not poly2d.convex_overlap(sq, poly2d.rect(3.99, 0, 6, 2), 0.05)  # within the tolerance
    diamond = np.array([[5, 1], [6, 0], [7, 1], [6, 2]], float)
    assert not poly2d.convex_overlap(sq, diamond, 0.0)
    assert poly2d.convex_overlap(sq, diamond - (1.5, 0), 0.0)

def test_clip_halfplane_and_lines():
    L = np.array([[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]], float)
    part = poly2d.clip_halfplane(L, (6, 0), (-1, 0))  # keep x >= 6
    assert abs(abs(poly2d.area(part)) - 16.0) < 1e-9
    segs = poly2d.line_segments_inside(L, (-1, 2), (1, 0))
    assert [(round(a, 6), round(b, 6)) for a, b in segs] == [(1.0, 11.0)]
    segs = poly2d.line_segments_inside(L, (-1, 6), (1, 0))
    assert [(round(a, 6), round(b, 6)) for a, b in segs] == [(1.0, 5.0)]


def test_irregular_polygon_has_exact_area_and_is_simple():
    rng = np.random.default_rng(1)
    for a in (0.2, 1.0, 7.0):
        p = poly2d.irregular_polygon(rng, a)
        assert math.isclose(abs(poly2d.area(p)), a, rel_tol=1e-9)
        assert poly2d.contains(p, [(0.0, 0.0)])[0]
