"""Fracture maths (addon/geometry/fracture.py): convex clipping, Voronoi shards, building
elements as non-overlapping solids. Closed-form volumes; no Blender scene needed (bpy only
provides mathutils for ShellSpec's module)."""
import numpy as np
import pytest

from addon.geometry import fracture as fr

pytest.importorskip("bpy")  # ShellSpec's module imports mathutils
from addon.geometry.shell import ShellSpec, rect_footprint  # noqa: E402


def test_box_volume_centroid_and_clip_in_closed_form():
    b = fr.box((0, 0, 0), (2, 3, 4))
    assert b.volume() == pytest.approx(24.0, rel=1e-12)
    assert np.allclose(b.centroid(), (1, 1.5, 2))
    # the plane x + y + z = 2 cuts off the corner tetrahedron of volume 2^3 / 6
    tet = fr.clip(b, (2, 0, 0), (-1, -1, -1), 7)
    assert tet.volume() == pytest.approx(24.0 - 8.0 / 6.0, rel=1e-12)
    assert 7 in tet.tags
    assert fr.clip(b, (5, 0, 0), (1, 0, 0), 0) is b  # plane beyond: unchanged
    assert fr.clip(b, (-1, 0, 0), (1, 0, 0), 0) is None  # everything cut away


def test_voronoi_shards_tile_the_solid_without_overlap():
    rng = np.random.default_rng(3)
    solid = fr.box((0, 0, 0), (5, 0.4, 3))  # a wall panel
    seeds = fr.seed_points(solid, rng, origin=(0, 0, 0), near=0.5, far=2.0)
    assert len(seeds) > 5
    cells = fr.voronoi_cells(solid, seeds)
    total = sum(c.volume() for _, c in cells)
    assert total == pytest.approx(solid.volume(), rel=1e-9)
    q = rng.uniform((0, 0, 0), (5, 0.4, 3), (5000, 3))
    count = sum(c.contains(q, tol=-1e-9).astype(int) for _, c in cells)
    assert (count == 1).mean() > 0.999  # each point in exactly one shard (up to the boundary)
    assert count.max() == 1
    # a fracture face of cell i tagged j lies on the bisector of seeds i and j
    i, c = cells[0]
    for f, t in zip(c.faces, c.tags):
        if t >= 0:
            mid = (seeds[i] + seeds[t]) / 2
            assert np.allclose((f - mid) @ (seeds[t] - seeds[i]), 0, atol=1e-9)


def test_cells_are_denser_near_the_origin():
    rng = np.random.default_rng(0)
    solid = fr.box((0, 0, 0), (20, 0.4, 3))
    s = fr.seed_points(solid, rng, origin=(0, 0.2, 1.5), near=0.5, far=3.0, max_cells=500)
    assert (s[:, 0] < 5).sum() > 2 * (s[:, 0] > 15).sum()


def test_same_seed_same_shards():
    def shards(seed):
        rng = np.random.default_rng(seed)
        solid = fr.box((0, 0, 0), (4, 3, 0.2))
        cells = fr.voronoi_cells(solid, fr.seed_points(solid, rng, (0, 0, 0), 0.6, 2.0))
        return [np.concatenate(c.faces) for _, c in cells]
    a, b, c = shards(5), shards(5), shards(6)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    assert len(a) != len(c) or not all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, c))


def _elements_volume_closed_form():
    # 12 x 9 m, 3 storeys of 3 m, flat roof with a 0.8 m parapet, masonry
    t, ts, tr, ti, tp = 0.4, 0.2, 0.2, 0.15, 0.25
    inner_area = (12 - 2 * t) * (9 - 2 * t)
    walls = (12 * 9 - inner_area) * 3 * (3.0 - ts)  # each storey's walls end under the slab above
    slabs = 2 * 12 * 9 * ts  # slabs and roof span the footprint, bearing on the walls
    roof = 12 * 9 * tr
    parapet = (12 * 9 - (12 - 2 * tp) * (9 - 2 * tp)) * 0.8
    # cross walls at x = -2, 2 across the inner depth; the spine along the inner length
    # minus the two crossings; every storey up to the slab (or roof) above
    inner_len = 2 * (9 - 2 * t) + (12 - 2 * t) - 2 * ti
    inner = inner_len * ti * 3 * (3.0 - ts)
    return walls + slabs + roof + parapet + inner


def test_building_elements_have_the_closed_form_volume_and_do_not_overlap():
    spec = ShellSpec(footprint=rect_footprint(12, 9), storeys=3, storey_height=3.0, roof="flat",
                     parapet_height=0.8, material="masonry")
    els = fr.building_elements(spec)
    assert sum(e.volume for e in els) == pytest.approx(_elements_volume_closed_form(), rel=1e-9)
    q = np.random.default_rng(1).uniform((-6, -4.5, 0), (6, 4.5, 10.5), (20000, 3))
    count = sum(e.solid.contains(q, tol=-1e-9).astype(int) for e in els)
    assert count.max() == 1
    parts = {e.part for e in els}
    assert {fr.P_WALL, fr.P_SLAB, fr.P_ROOF, fr.P_INNER, fr.P_PARAPET} <= parts


@pytest.mark.parametrize("roof", ["gable", "hip"])
def test_pitched_roofs_and_an_l_footprint_do_not_overlap_and_shards_tile_them(roof):
    spec = ShellSpec(footprint=rect_footprint(10, 8), storeys=2, storey_height=3.0, roof=roof, roof_pitch=35)
    els = fr.building_elements(spec)
    roof_vol = sum(e.volume for e in els if e.part in (fr.P_ROOF, fr.P_GABLE))
    assert roof_vol > 0
    q = np.random.default_rng(2).uniform((-5, -4, 0), (5, 4, spec.height), (20000, 3))
    count = sum(e.solid.contains(q, tol=-1e-9).astype(int) for e in els)
    assert count.max() == 1
    # everything under the roof surface that is not air lies within an element: the
    # solids stay inside the building's envelope
    for e in els:
        v = np.concatenate(e.solid.faces)
        assert (v[:, 2] <= spec.roof_z(v[:, 0], v[:, 1]) + 1e-9).all()
    rng = np.random.default_rng(4)
    total = shards = 0.0
    for e in els:
        cells = fr.voronoi_cells(e.solid, fr.seed_points(e.solid, rng, (5, 4, 0), 0.6, 2.0))
        shards += len(cells)
        total += sum(c.volume() for _, c in cells)
    assert total == pytest.approx(sum(e.volume for e in els), rel=1e-6)
    assert shards > 3 * len(els)


def test_l_shaped_footprint_slabs_are_convex_pieces_of_the_footprint():
    spec = ShellSpec(footprint=[[0, 0], [20, 0], [20, 8], [8, 8], [8, 18], [0, 18]], storeys=2, roof="flat")
    els = fr.building_elements(spec)
    slab = [e for e in els if e.part == fr.P_SLAB]
    assert len(slab) == 2  # two convex pieces of the L
    assert sum(e.volume for e in slab) == pytest.approx((20 * 8 + 8 * 10) * 0.2, rel=1e-9)
    # a slab's edges on the outline are facade (wall), the edge between the pieces is not
    walls = [sum(1 for t in range(len(e.solid.faces)) if e.face_surface(e.solid.tags[t]) == fr.SURFACE_WALL)
             for e in slab]
    assert all(w >= 2 for w in walls)
    q = np.random.default_rng(3).uniform((0, 0, 0), (20, 18, 6.5), (20000, 3))
    assert sum(e.solid.contains(q, tol=-1e-9).astype(int) for e in els).max() == 1
