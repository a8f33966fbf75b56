"""Closing real city models' open shells (`quakescan.formats.shell`): closed-form boxes, and the
real Rotterdam model, whose terrain under a roof no oblique view may reach after the import."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quakescan.formats.scene import GROUND, ROOF, WALL, triangle_areas
from quakescan.formats.shell import close_open_edges

ROTTERDAM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rotterdam_subset.json"


class _Mesh:
    """Quads (as two triangles) with surface codes, vertices not shared between quads (as
    polygons of a city model; the closing merges them by position)."""

    def __init__(self):
        self.v, self.t, self.s = [], [], []

    def quad(self, corners, surface):
        n = len(self.v)
        self.v += [list(map(float, c)) for c in corners]
        self.t += [[n, n + 1, n + 2], [n, n + 2, n + 3]]
        self.s += [surface] * 2
        return self

    def arrays(self):
        return np.array(self.v), np.array(self.t, np.int64), np.array(self.s, np.uint8)


def _box(x0, y0, x1, y1, z0, z1, walls=("s", "e", "n", "w"), mesh=None):
    m = mesh or _Mesh()
    m.quad([(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], ROOF)
    m.quad([(x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0)], GROUND)
    faces = {"s": [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
             "e": [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
             "n": [(x1, y1, z0), (x0, y1, z0), (x0, y1, z1), (x1, y1, z1)],
             "w": [(x0, y1, z0), (x0, y0, z0), (x0, y0, z1), (x0, y1, z1)]}
    for k in walls:
        m.quad(faces[k], WALL)
    return m


def _added(mesh):
    v, t, s = mesh.arrays()
    v2, t2, s2, area = close_open_edges(v, t, s)
    new = t2[len(t):]
    assert (s2[len(t):] == WALL).all()
    assert area == pytest.approx(triangle_areas(v2, new).sum())
    return v2, new, area


def test_a_closed_box_gets_nothing():
    v, new, area = _added(_box(0, 0, 10, 8, 0, 6))
    assert area == 0 and len(new) == 0


def test_a_missing_wall_is_put_back_where_it_was():
    v, new, area = _added(_box(0, 0, 10, 8, 0, 6, walls=("s", "e", "n")))
    assert area == pytest.approx(8 * 6)
    np.testing.assert_allclose(v[new][..., 0], 0.0)  # in the west wall's plane, x = 0


def test_a_party_wall_strip_above_an_absent_neighbour_is_closed_to_the_base():
    """3D BAG style: the west wall is only the strip above the neighbour's roof (15 -> 14.9 m);
    the neighbour is not in the file."""
    m = _box(0, 0, 10, 10, 0, 15, walls=("s", "e", "n"))
    m.quad([(0, 10, 14.9), (0, 0, 14.9), (0, 0, 15), (0, 10, 15)], WALL)
    v, new, area = _added(m)
    assert area == pytest.approx(10 * 14.9)
    assert v[new][..., 2].max() == pytest.approx(14.9)


def test_walls_split_under_a_whole_roof_edge_are_no_gap():
    """A T-junction: the south wall is two polygons, the roof's south edge one."""
    m = _box(0, 0, 10, 8, 0, 6, walls=("e", "n", "w"))
    m.quad([(0, 0, 0), (4, 0, 0), (4, 0, 6), (0, 0, 6)], WALL)
    m.quad([(4, 0, 0), (10, 0, 0), (10, 0, 6), (4, 0, 6)], WALL)
    assert _added(m)[2] == 0


def test_roof_planes_joined_without_a_shared_edge_get_no_wall_between_them():
    m = _Mesh()
    m.quad([(0, 0, 6), (5, 0, 6), (5, 10, 6), (0, 10, 6)], ROOF)
    m.quad([(5, 0, 6), (10, 0, 6), (10, 5, 6), (5, 5, 6)], ROOF)
    m.quad([(5, 5, 6), (10, 5, 6), (10, 10, 6), (5, 10, 6)], ROOF)
    m.quad([(0, 0, 0), (0, 10, 0), (10, 10, 0), (10, 0, 0)], GROUND)
    for a, b in [((0, 0), (10, 0)), ((10, 0), (10, 10)), ((10, 10), (0, 10)), ((0, 10), (0, 0))]:
        m.quad([(*a, 0), (*b, 0), (*b, 6), (*a, 6)], WALL)
    assert _added(m)[2] == 0


def test_a_step_without_its_wall_is_closed_and_one_with_it_is_not():
    def stepped(with_step_wall):
        m = _Mesh()
        m.quad([(0, 0, 12), (5, 0, 12), (5, 10, 12), (0, 10, 12)], ROOF)  # high part
        m.quad([(5, 0, 6), (10, 0, 6), (10, 10, 6), (5, 10, 6)], ROOF)  # low part
        m.quad([(0, 0, 0), (0, 10, 0), (10, 10, 0), (10, 0, 0)], GROUND)
        m.quad([(0, 0, 0), (5, 0, 0), (5, 0, 12), (0, 0, 12)], WALL)
        m.quad([(5, 0, 0), (10, 0, 0), (10, 0, 6), (5, 0, 6)], WALL)
        m.quad([(10, 0, 0), (10, 10, 0), (10, 10, 6), (10, 0, 6)], WALL)
        m.quad([(10, 10, 0), (5, 10, 0), (5, 10, 6), (10, 10, 6)], WALL)
        m.quad([(5, 10, 0), (0, 10, 0), (0, 10, 12), (5, 10, 12)], WALL)
        m.quad([(0, 10, 0), (0, 0, 0), (0, 0, 12), (0, 10, 12)], WALL)
        if with_step_wall:
            m.quad([(5, 0, 6), (5, 10, 6), (5, 10, 12), (5, 0, 12)], WALL)
        return m

    assert _added(stepped(True))[2] == 0
    v, new, area = _added(stepped(False))
    # the high roof's open edge, down to the building's base (the part below 6 m is inside)
    assert area == pytest.approx(10 * 12)
    np.testing.assert_allclose(v[new][..., 0], 5.0)


def test_a_sliver_along_a_roof_edge_does_not_hide_the_missing_wall_under_it():
    """A roof polygon with an extra vertex on its straight north edge, triangulated with a
    zero-area triangle along that edge (as earcut leaves it), and no north wall in the file:
    the wall is put back (the sliver shared the roof triangle's edge, so it looked inner)."""
    m = _box(0, 0, 10, 8, 0, 6, walls=("s", "e", "w"))
    v, t, s = m.arrays()
    n = len(v)
    v = np.vstack([v, [(10, 8, 6), (4, 8, 6), (0, 8, 6)]])  # on the north edge, x = 4 in between
    t = np.vstack([t, [(n, n + 1, n + 2)]])  # collinear: no area
    s = np.append(s, ROOF)
    v2, t2, s2, area = close_open_edges(v, t, s)
    assert area == pytest.approx(10 * 6)
    np.testing.assert_allclose(v2[t2[len(t):]][..., 1], 8.0)  # in the north wall's plane


def test_a_wall_rising_from_a_roof_edge_does_not_close_the_facade_under_it():
    """A storey's wall strip (6 -> 8 m) standing on the roof's north edge and sharing it, the
    facade under that edge missing: the facade is put back. With the facade there (a parapet
    over a closed wall), nothing is added."""
    def strip(with_facade):
        m = _box(0, 0, 10, 8, 0, 6, walls=("s", "e", "w") + (("n",) if with_facade else ()))
        m.quad([(10, 8, 6), (0, 8, 6), (0, 8, 8), (10, 8, 8)], WALL)
        return m

    v, new, area = _added(strip(False))
    assert area == pytest.approx(10 * 6)
    np.testing.assert_allclose(v[new][..., 1], 8.0)
    assert v[new][..., 2].max() == pytest.approx(6.0)
    assert _added(strip(True))[2] == 0


def test_a_vertical_or_base_edge_is_left_alone():
    """A ground polygon's edges and a wall's vertical side never make walls."""
    m = _Mesh()
    m.quad([(0, 0, 0), (0, 10, 0), (10, 10, 0), (10, 0, 0)], GROUND)
    m.quad([(0, 0, 0), (10, 0, 0), (10, 0, 6), (0, 0, 6)], WALL)
    v, new, area = _added(m)
    # the wall's top edge stands over the wall itself: nothing
    assert area == 0


@pytest.mark.realdata
def test_no_oblique_view_reaches_the_terrain_under_a_rotterdam_roof():
    """Every terrain triangle under a roof of the real Rotterdam model (open shells in the file:
    party walls kept only above neighbours the subset does not hold) is hidden from every
    direction 45 degrees above the horizon."""
    if not ROTTERDAM.is_file():
        pytest.skip(f"{ROTTERDAM} is absent")
    from quakescan.acquisition.raycast import RayCaster
    from quakescan.formats.cityjson import import_cityjson

    scene = import_cityjson(ROTTERDAM)
    caster = RayCaster(scene)
    v = scene.vertices - caster.local_origin
    terrain = scene.faces[scene.face_building == 0]
    centre = v[terrain].mean(axis=1) + [0.0, 0.0, 0.01]
    up = np.tile([0.0, 0.0, 1.0], (len(centre), 1))
    face, _ = caster.cast(centre, up, 200.0)
    under = np.flatnonzero((face >= 0) & (scene.face_building[np.maximum(face, 0)] > 0))
    assert len(under) > 100
    owner = scene.face_building[face[under]]
    for bid in np.unique(owner):
        # each building alone: a neighbour in the file must not hide a gap that a city
        # without it (or a street between them) leaves open (building 6's north facade under
        # a sliver, and under a wall strip on a lower part's roof edge; building 12's likewise)
        alone = RayCaster(_only_building(scene, bid))
        mine = centre[under][owner == bid] + caster.local_origin - alone.local_origin
        for az in np.radians(np.arange(0, 360, 30)):
            for elevation in (np.radians(45), np.radians(60)):
                d = np.tile([np.cos(az) * np.cos(elevation), np.sin(az) * np.cos(elevation), np.sin(elevation)],
                            (len(mine), 1))
                face, _ = alone.cast(mine, d, 500.0)
                escaped = face < 0
                assert not escaped.any(), (f"building {bid}: {escaped.sum()} terrain triangles under its roof "
                                           f"seen from azimuth {az:.2f}, elevation {elevation:.2f}")


def _only_building(scene, bid):
    from dataclasses import replace

    keep = scene.face_building == bid
    return replace(scene, faces=scene.faces[keep], face_building=scene.face_building[keep],
                   face_surface=scene.face_surface[keep], face_porous=None,
                   buildings=[b for b in scene.buildings if b.id == bid])
