"""2.5-D and core-point building descriptors (core/change/surface.py): closed-form answers on sampled
box buildings, the same answers at very different densities, and the quality gate."""
import numpy as np
import pytest

from quakescan.change.pipeline import describe_pair
from quakescan.change.settings import PipelineSettings
from quakescan.change.surface import (
    SURFACE_DESCRIPTORS,
    SurfaceError,
    SurfaceGeometry,
    SurfaceSettings,
    describe_surfaces,
)
from quakescan.formats.pointcloud import Epoch
from quakescan.grid.density import planimetric_density


def sample_box(rng, density, x0, y0, x1, y1, top, noise=0.01, base=0.0, walls=True):
    """Points on the roof (z = top) and, optionally, the four walls of a box, `density` per m²."""
    parts = []
    area = (x1 - x0) * (y1 - y0)
    n = rng.poisson(density * area)
    parts.append(np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), np.full(n, top)]))
    if walls:
        h = top - base
        for (ax, ay, bx, by) in ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)):
            length = np.hypot(bx - ax, by - ay)
            m = rng.poisson(density * 0.5 * length * h)  # walls are seen obliquely: half the density
            t = rng.uniform(0, 1, m)
            parts.append(np.column_stack([ax + t * (bx - ax), ay + t * (by - ay), rng.uniform(base, top, m)]))
    pts = np.vstack(parts)
    return pts + rng.normal(0, noise, pts.shape)


def sample_ground(rng, density, size=40.0, noise=0.01):
    n = rng.poisson(density * size * size)
    return np.column_stack([rng.uniform(-size / 2, size / 2, (n, 2)), rng.normal(0, noise, n)])


def scene(rng, density, damaged, debris=False):
    """One 10 x 10 x 6 m building on 40 x 40 m of ground; `damaged`: its eastern half came down
    to 1 m (a heap)."""
    ground = sample_ground(rng, density)
    ground = ground[~((np.abs(ground[:, 0]) < 5) & (np.abs(ground[:, 1]) < 5))]
    if damaged:
        building = np.vstack([sample_box(rng, density, -5, -5, 0, 5, 6.0),
                              sample_box(rng, density, 0, -5, 5, 5, 1.0, walls=False)])
        building = building[~((building[:, 0] > 0.01) & (building[:, 2] > 1.2))]
    else:
        building = sample_box(rng, density, -5, -5, 5, 5, 6.0)
    parts, bid, cls = [ground, building], [np.zeros(len(ground), np.int64), np.ones(len(building), np.int64)], \
        [np.full(len(ground), 2, np.uint8), np.full(len(building), 6, np.uint8)]
    if debris:
        heap = sample_box(rng, density, 5.5, -4, 9, 4, 1.5, walls=False)
        ground_keep = ~((parts[0][:, 0] > 5.5) & (parts[0][:, 0] < 9) & (np.abs(parts[0][:, 1]) < 4))
        parts[0], bid[0], cls[0] = parts[0][ground_keep], bid[0][ground_keep], cls[0][ground_keep]
        parts.append(heap)
        bid.append(np.zeros(len(heap), np.int64))
        cls.append(np.full(len(heap), 1, np.uint8))
    return np.vstack(parts), np.concatenate(bid), np.concatenate(cls)


def describe(pre, post, density_pre, density_post, settings=None):
    s = settings or SurfaceSettings()
    geom = SurfaceGeometry.for_pair(s, density_pre, density_post)
    d, cores = describe_surfaces(pre[0], pre[1], pre[2] == 2, post[0], [1], s, geom, workers=1)
    return d[1], geom


def test_half_collapsed_box_gives_the_closed_form_shares():
    rng = np.random.default_rng(0)
    pre, post = scene(rng, 100, False), scene(rng, 100, True)
    d, geom = describe(pre, post, 100, 100)
    assert geom.cell_m == 0.5
    # half the footprint came down 5 m (of 6): > 1 m, > a storey and > half the height
    for k in ("s_lowered_1m", "s_lowered_storey", "s_lowered_half"):
        assert d[k] == pytest.approx(0.5, abs=0.06), k
    assert d["s_volume_loss"] == pytest.approx(0.5 * 5 / 6, abs=0.05)
    assert d["s_height_ratio_p10"] == pytest.approx(1 / 6, abs=0.05)
    assert d["m_lost"] > 0.2 and d["m_coherent"] > 0.3 and d["m_roof_changed"] > 0.4
    assert set(d) == set(SURFACE_DESCRIPTORS)


def test_an_unchanged_rescan_shows_nothing_beyond_noise():
    rng = np.random.default_rng(1)
    d, _ = describe(scene(rng, 100, False), scene(rng, 100, False), 100, 100)
    for k in ("s_lowered_1m", "s_lowered_storey", "s_lowered_half", "s_raised", "s_debris_ring", "m_lost",
              "m_coherent"):
        assert d[k] < 0.02, k
    assert d["m_changed"] < 0.1 and d["s_volume_loss"] < 0.02
    assert d["s_height_ratio_mean"] == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("damaged", [False, True])
def test_descriptors_mean_the_same_at_200_and_at_6_points_per_m2(damaged):
    """Density invariance: a drone-dense pair, an airborne-sparse pair and a cross-density pair
    (sparse before, dense after) of the same building agree within 0.1 on every raster share
    and within 0.15 on the core-point shares (about 100 roof core points at the sparse grid:
    their sampling spread alone is a few hundredths)."""
    rng = np.random.default_rng(2)
    dense, _ = describe(scene(rng, 200, False), scene(rng, 200, damaged), 200, 200)
    sparse, g = describe(scene(rng, 6, False, ), scene(rng, 6, damaged), 6, 6)
    cross, _ = describe(scene(rng, 6, False), scene(rng, 200, damaged), 6, 200)
    assert g.cell_m > 0.8  # the grid follows the sparser epoch
    shares = [k for k in SURFACE_DESCRIPTORS if not k.startswith("m_distance") and k != "m_lod_median"]
    for k in shares:
        tol = 0.15 if k.startswith("m_") else 0.1
        assert abs(dense[k] - sparse[k]) < tol, (k, dense[k], sparse[k])
        assert abs(dense[k] - cross[k]) < tol, (k, dense[k], cross[k])
    assert sparse["m_lod_median"] > dense["m_lod_median"]  # fewer points, wider level of detection


def test_debris_outside_the_footprint_is_seen_in_the_ring():
    rng = np.random.default_rng(3)
    d, _ = describe(scene(rng, 50, False), scene(rng, 50, True, debris=True), 50, 50)
    assert d["s_debris_ring"] > 0.05 and d["s_debris_volume"] > 0.02
    quiet, _ = describe(scene(rng, 50, False), scene(rng, 50, True), 50, 50)
    assert quiet["s_debris_ring"] < 0.01


def test_planimetric_density_counts_roof_points_per_square_metre_of_interior_cells():
    rng = np.random.default_rng(4)
    pts = sample_box(rng, 12.0, 0, 0, 20, 20, 5.0, walls=True)
    assert planimetric_density(pts) == pytest.approx(12.0, rel=0.08)  # walls below the eaves left out
    assert planimetric_density(np.zeros((0, 3))) == 0.0
    small = sample_box(rng, 12.0, 0, 0, 1.5, 1.5, 3.0, walls=False)  # no interior cell: mean over its cells
    assert 0 < planimetric_density(small) < 13


def test_bad_settings_and_a_building_without_points_are_refused_by_name():
    with pytest.raises(SurfaceError, match="storey_m"):
        SurfaceSettings(storey_m=0)
    rng = np.random.default_rng(5)
    pre = scene(rng, 20, False)
    s = SurfaceSettings()
    with pytest.raises(SurfaceError, match="building 7"):
        describe_surfaces(pre[0], pre[1], pre[2] == 2, pre[0], [7], s, SurfaceGeometry.for_pair(s, 20, 20))


def epoch(pts, origin=(0.0, 0.0, 0.0)):
    xyz, bid, cls = pts
    return Epoch(xyz.copy(), np.asarray(origin, float), cls.copy(), building_id=bid.copy(), source="synthetic")


def test_pipelinequality_gate_names_the_density_and_surface_rows_match_at_utm():
    rng = np.random.default_rng(6)
    pre, post = scene(rng, 30, False), scene(rng, 30, True)
    s = PipelineSettings(surface=SurfaceSettings(), per_point_lod=True, min_density_pts_m2=50.0)
    rows = describe_pair(epoch(pre), epoch(post), s, workers=1)
    assert not rows[0].assessable and rows[0].reason.startswith("density ") and "< 50" in rows[0].reason
    s_ok = PipelineSettings(surface=SurfaceSettings(), per_point_lod=True)
    local = describe_pair(epoch(pre), epoch(post), s_ok, workers=1)[0]
    assert local.assessable and set(local.descriptors) == set(s_ok.descriptor_names())
    assert local.quality["density_pre"] == pytest.approx(30, rel=0.25)
    # a 10 x 10 m footprint on 0.5 m cells (the smallest: 30 pts/m² asks for 0.37 m) spans
    # 20 x 20 cells, 21 or 22 a side where the walls' noise reaches the next cell
    assert 20 * 20 <= local.quality["cells"] <= 22 * 22
    small = PipelineSettings(surface=SurfaceSettings(), per_point_lod=True, min_cells=500)
    row = describe_pair(epoch(pre), epoch(post), small, workers=1)[0]
    assert not row.assessable and row.reason.startswith(f"footprint of {local.quality['cells']} raster cells < 500")
    with pytest.raises(Exception, match="minimum raster cells"):
        PipelineSettings(surface=SurfaceSettings(), min_cells=-1)
    # the same scene with UTM coordinates in the points themselves (no local origin)
    shift = np.array([500_000.0, 5_000_000.0, 200.0])
    utm = describe_pair(epoch((pre[0] + shift, pre[1], pre[2])), epoch((post[0] + shift, post[1], post[2])),
                        s_ok, workers=1)[0]
    for k, v in local.descriptors.items():
        assert utm.descriptors[k] == pytest.approx(v, abs=1e-6), k


def test_changes_count_only_as_areas_not_as_single_cells_or_points():
    """A 95 % test flags single cells and core points of an unchanged surface at random, so a
    lowering counts in patches of >= 2 cells and a changed surface in patches of >= 3 core
    points: a 2 x 2 m roof hole is seen, a 0.3 m one (one cell) is not."""
    rng = np.random.default_rng(7)
    pre = scene(rng, 100, False)

    def with_hole(half):
        xyz, bid, cls = scene(rng, 100, False)
        hole = (np.abs(xyz[:, 0] - 2) < half) & (np.abs(xyz[:, 1] - 2) < half) & (xyz[:, 2] > 5.5)
        floor = np.column_stack([rng.uniform(2 - half, 2 + half, (400, 2)), np.full(400, 3.0)])
        return (np.vstack([xyz[~hole], floor]), np.concatenate([bid[~hole], np.ones(400, np.int64)]),
                np.concatenate([cls[~hole], np.full(400, 6, np.uint8)]))

    big, _ = describe(pre, with_hole(1.0), 100, 100)
    small, _ = describe(pre, with_hole(0.15), 100, 100)
    assert big["s_lowered_1m"] == pytest.approx(4.0 / 100, abs=0.02) and big["m_holes"] > 0
    assert small["s_lowered_1m"] == 0.0 and small["m_changed"] == 0.0


def test_a_roof_step_sampled_only_on_its_lower_side_is_no_lowering():
    """A dense pre-event scan sees both roofs of a 3 m roof step inside the cells that straddle
    it; a sparse post-event scan that happens to catch only the lower roof there (here: the
    upper roof's strip along the step has no point) leaves the building as it was. A real
    lowering of the upper roof is still seen."""
    rng = np.random.default_rng(11)
    step_x = 0.3

    def stepped(density, keep_upper_strip=True, upper=9.0):
        xyz = np.vstack([sample_box(rng, density, -5, -5, step_x, 5, upper),
                         sample_box(rng, density, step_x, -5, 5, 5, 6.0)])
        inner_step = (np.abs(xyz[:, 0] - step_x) < 0.02) & (xyz[:, 2] <= 6.05)  # the other box's wall
        xyz = xyz[~inner_step]
        if not keep_upper_strip:  # no point of the upper roof within 1.3 m (more than a cell) of
            # the step, nor of the step's wall: what a sparse airborne pass can miss
            xyz = xyz[~((xyz[:, 0] > step_x - 1.3) & (xyz[:, 0] < step_x + 0.1) & (xyz[:, 2] > 6.5))]
        ground = sample_ground(rng, density)
        ground = ground[~((np.abs(ground[:, 0]) < 5) & (np.abs(ground[:, 1]) < 5))]
        pts = np.vstack([ground, xyz])
        return (pts, np.concatenate([np.zeros(len(ground), np.int64), np.ones(len(xyz), np.int64)]),
                np.concatenate([np.full(len(ground), 2, np.uint8), np.full(len(xyz), 6, np.uint8)]))

    d, geom = describe(stepped(100), stepped(3, keep_upper_strip=False), 100, 3)
    assert geom.cell_m < 1.3
    for k in ("s_lowered_1m", "s_lowered_storey", "s_volume_loss"):
        assert d[k] == 0.0, k
    lowered, _ = describe(stepped(100), stepped(3, upper=6.0), 100, 3)  # the upper storey is gone
    assert lowered["s_lowered_1m"] == pytest.approx(5.3 / 10, abs=0.08)  # the upper roof's share



def low_shed(rng, density, top=1.3, lowered_to=None):
    """A 4 x 4 m flat-roofed shed `top` m high (lower than a sparse pair's raster cell), roof and
    walls sampled at `density` per m² on 20 x 20 m of ground; `lowered_to`: its roof came down
    to that height."""
    roof_z = top if lowered_to is None else lowered_to
    box = sample_box(rng, density, -2, -2, 2, 2, roof_z)
    ground = sample_ground(rng, density, size=20.0)
    ground = ground[~((np.abs(ground[:, 0]) < 2) & (np.abs(ground[:, 1]) < 2))]
    pts = np.vstack([ground, box])
    return (pts, np.concatenate([np.zeros(len(ground), np.int64), np.ones(len(box), np.int64)]),
            np.concatenate([np.full(len(ground), 2, np.uint8), np.full(len(box), 6, np.uint8)]))


def test_the_height_ratio_of_an_unchanged_building_lower_than_a_cell_is_one():
    """The post/pre height ratio divides by the cell's own height above ground. A building
    between 1 m and one raster cell high (sheds, garages, carports under a sparse pair's
    1.5 m cells) kept its height; dividing by the cell size instead read it as 10-20 % lower
    (AHN3 tile 1 against its 25 % thinning: the only building of 90 called damaged, a shed
    with no other change at all). Closed form both ways: unchanged 1, roof down to half
    height 0.5."""
    rng = np.random.default_rng(13)
    d, geom = describe(low_shed(rng, 6.0), low_shed(rng, 1.8), 6.0, 1.8)
    assert geom.cell_m == pytest.approx(np.sqrt(4.0 / 1.8)) and geom.cell_m > 1.3
    assert d["s_height_ratio_mean"] == 1.0 and d["s_height_ratio_p10"] == 1.0
    assert d["s_volume_loss"] == 0.0
    rng = np.random.default_rng(14)
    d, _ = describe(low_shed(rng, 100.0, top=1.8), low_shed(rng, 100.0, top=1.8, lowered_to=0.9), 100.0, 100.0)
    assert d["s_height_ratio_p10"] == pytest.approx(0.5, abs=0.03)


def test_a_density_just_under_the_limit_never_reads_as_equal_to_it():
    from quakescan.change.pipeline import BuildingRow, quality_gate

    settings = PipelineSettings(surface=SurfaceSettings(), paper_descriptors=False, min_density_pts_m2=1.9)
    row = quality_gate(BuildingRow(building_id=7, n_pre=400, n_post=100, assessable=True,
                                    quality={"density_pre": 4.0, "density_post": 1.899, "coverage": 1.0}), settings)
    assert not row.assessable and row.reason == "density 1.89 pts/m² < 1.9"



def test_points_seen_through_roof_holes_smaller_than_the_top_of_a_cell():
    """Seven 0.9 x 0.9 m roof holes (a cell's top stays on the roof around each: no lowering)
    with the floor 3 m below seen through them: the share of the footprint seen through is
    the holes' cells (each hole touches 2 x 2 to 3 x 3 of the 0.5 m cells: 28-63 of the 484
    cells of the footprint and its walls); an
    unchanged rescan and a drone rescan that sees the walls lower down than before show none."""
    rng = np.random.default_rng(13)
    centres = [(-3.2, -3.2), (-3.2, 0.1), (-3.2, 3.1), (0.3, -3.0), (0.2, 3.3), (3.1, -0.4), (3.3, 3.0)]

    def holed(density):
        xyz, bid, cls = scene(rng, density, False)
        keep = np.ones(len(xyz), bool)
        floors = []
        for cx, cy in centres:
            keep &= ~((np.abs(xyz[:, 0] - cx) < 0.45) & (np.abs(xyz[:, 1] - cy) < 0.45) & (xyz[:, 2] > 5.5))
            m = rng.poisson(density * 0.5)  # the floor is seen through the opening only in part
            floors.append(np.column_stack([rng.uniform(cx - 0.4, cx + 0.4, m), rng.uniform(cy - 0.4, cy + 0.4, m),
                                           np.full(m, 3.0)]))
        floor = np.vstack(floors)
        return (np.vstack([xyz[keep], floor]), np.concatenate([bid[keep], np.ones(len(floor), np.int64)]),
                np.concatenate([cls[keep], np.full(len(floor), 6, np.uint8)]))

    pre = scene(rng, 200, False)
    d, geom = describe(pre, holed(200), 200, 200)
    assert geom.cell_m == 0.5
    assert d["s_lowered_1m"] == 0.0  # below the 2.5-D descriptors' scale
    assert 28 / 484 <= d["s_see_through"] <= 63 / 484
    same, _ = describe(pre, scene(rng, 200, False), 200, 200)
    assert same["s_see_through"] == 0.0
    for lowest_wall_point in (3.0, 5.9):  # archives that saw the walls' upper half, or no wall at all
        xyz, bid, cls = scene(rng, 200, False)
        keep = (xyz[:, 2] >= lowest_wall_point) | (cls == 2)
        drone, _ = describe((xyz[keep], bid[keep], cls[keep]), scene(rng, 200, False), 200, 200)
        assert drone["s_see_through"] == 0.0, lowest_wall_point


def test_the_interior_seen_through_a_wall_opening_is_the_share_of_its_inner_cells():
    """An airborne archive saw the roof only (20 pts/m²); after the event a drone (100 pts/m²)
    sees every wall, and through a 4 m wide opening in the east wall the floor inside. On the
    0.5 m grid the footprint is 20 x 20 cells, of which those at least 1 m in from the outline
    are x, y in [-4, 4). Floor seen 2.5 m deep (x 2.5-5 m, y -2-2 m) covers 3 x 8 of them:
    24/400 exactly; seen 1.4 m deep, 1 x 8: 8/400, which s_see_through (1.5 m in) misses. The same drone rescan without the opening, and an opening that shows the floor
    only 0.8 m deep (what an intact wall seen lower down also looks like), give 0."""
    rng = np.random.default_rng(21)
    ground = sample_ground(rng, 20.0, noise=0.0)
    ground = ground[~((np.abs(ground[:, 0]) < 5.5) & (np.abs(ground[:, 1]) < 5.5))]
    roof = sample_box(rng, 20.0, -5, -5, 5, 5, 6.0, noise=0.0, walls=False)
    pre = (np.vstack([ground, roof]), np.r_[np.zeros(len(ground), np.int64), np.ones(len(roof), np.int64)],
           np.r_[np.full(len(ground), 2, np.uint8), np.full(len(roof), 6, np.uint8)])

    def drone(seen_depth):
        g = sample_ground(rng, 100.0)
        g = g[~((np.abs(g[:, 0]) < 5.5) & (np.abs(g[:, 1]) < 5.5))]
        box = sample_box(rng, 100.0, -5, -5, 5, 5, 6.0)
        floor = np.zeros((0, 3))
        if seen_depth:
            box = box[~((box[:, 0] > 4.9) & (np.abs(box[:, 1]) < 2) & (box[:, 2] > 2) & (box[:, 2] < 4))]
            n = rng.poisson(100.0 * 4 * seen_depth)
            floor = np.column_stack([rng.uniform(5 - seen_depth, 5, n), rng.uniform(-2, 2, n), np.zeros(n)])
        b = np.vstack([box, floor])
        return (np.vstack([g, b]), np.r_[np.zeros(len(g), np.int64), np.ones(len(b), np.int64)],
                np.r_[np.full(len(g), 2, np.uint8), np.full(len(b), 6, np.uint8)])

    d, geom = describe(pre, drone(2.5), 20.0, 100.0)
    assert geom.cell_m == 0.5  # so the fine grid is 0.5 m too
    assert d["s_interior_seen"] == pytest.approx(24 / 400)
    shallow, _ = describe(pre, drone(1.4), 20.0, 100.0)
    assert shallow["s_interior_seen"] == pytest.approx(8 / 400)
    assert shallow["s_see_through"] == 0.0 and shallow["s_lowered_1m"] == 0.0
    for depth in (0.0, 0.8):
        intact, _ = describe(pre, drone(depth), 20.0, 100.0)
        assert intact["s_interior_seen"] == 0.0, depth


def _grid(spacing, x0, y0, x1, y1, z):
    """Points on a regular grid of `spacing`, at the centres of its squares: 1/spacing² per m²."""
    xs, ys = np.meshgrid(np.arange(x0 + spacing / 2, x1, spacing), np.arange(y0 + spacing / 2, y1, spacing))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, float(z))])


@pytest.mark.parametrize("spacing", [0.5, 0.25])
def test_an_interior_patch_counts_only_where_the_pre_event_density_would_have_seen_it(spacing):
    """A sparse airborne pair with no change: both epochs sample a flat 10 x 10 m roof 6 m up on
    a regular grid (4 pts/m² at 0.5 m, 16 at 0.25 m), and the post-event epoch alone reaches the
    floor of a light well in its middle, 1.5 m² (2 x 3 cells of the 0.5 m grid) or 2 m²
    (2 x 4). Had the well been in view before, the pre-event epoch would have put Poisson
    density x area points on it: none with chance exp(-6) = 0.0025 and exp(-8) = 0.00034 at
    4 pts/m², at most exp(-24) at 16. Kept below 1e-3 (MISSED_CHANCE): at 4 pts/m² only the
    2 m² well, as 8 of the footprint's 400 cells; at 16 pts/m² both."""
    from quakescan.change.surface import MISSED_CHANCE, chance_missed

    assert chance_missed(np.array([1.5, 2.0]), 4.0) == pytest.approx(np.exp([-6.0, -8.0]))
    assert MISSED_CHANCE == 1e-3
    density = 1 / spacing ** 2
    ground = _grid(spacing, -15, -15, 15, 15, 0.0)
    ground = ground[~((np.abs(ground[:, 0]) < 5) & (np.abs(ground[:, 1]) < 5))]
    shares = {}
    for width in (1.5, 2.0):
        roof = _grid(spacing, -5, -5, 5, 5, 6.0)
        well = (np.abs(roof[:, 0]) < 0.5) & (roof[:, 1] >= 0) & (roof[:, 1] < width)
        pre_xyz = np.vstack([ground, roof[~well]])
        post_xyz = np.vstack([ground, roof[~well], roof[well] * [1, 1, 0]])
        assert planimetric_density(roof[~well]) == pytest.approx(density)

        def epoch_of(xyz):
            building = (np.abs(xyz[:, 0]) < 5) & (np.abs(xyz[:, 1]) < 5)
            return xyz, building.astype(np.int64), np.where(building, 6, 2).astype(np.uint8)

        d, geom = describe(epoch_of(pre_xyz), epoch_of(post_xyz), density, density)
        assert geom.cell_m <= 1.0  # so the interior grid is 0.5 m
        shares[width] = d["s_interior_seen"]
    if spacing == 0.5:
        assert shares == {1.5: 0.0, 2.0: pytest.approx(8 / 400)}
    else:
        assert shares == {1.5: pytest.approx(6 / 400), 2.0: pytest.approx(8 / 400)}


def test_the_chance_a_sparse_epoch_missed_a_surface_is_poisson_and_has_no_extreme_failures():
    """exp(-area x density): the smallest patch (3 cells of 0.5 m, 0.75 m²) is kept only above
    ln(1000) / 0.75 = 9.21 pts/m²; no area or no density is a certain miss; a large area at any
    real density underflows to 0 without a warning, not to NaN."""
    import warnings

    from quakescan.change.surface import MISSED_CHANCE, chance_missed

    boundary = np.log(1 / MISSED_CHANCE) / 0.75
    assert boundary == pytest.approx(9.2103, abs=1e-4)
    assert chance_missed(0.75, boundary * 0.999) > MISSED_CHANCE > chance_missed(0.75, boundary * 1.001)
    assert chance_missed(0.0, 50.0) == 1.0 and chance_missed(5.0, 0.0) == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert chance_missed(np.array([1e4, 1e6]), 1e3).tolist() == [0.0, 0.0]


def test_the_m3c2_kernels_run_on_the_threads_asked_for_with_the_same_descriptors(monkeypatch):
    """A Dask worker describes with one thread (its process is the parallelism): the cylinder
    kernel must not take every core beside the other workers. Same numbers either way."""
    import numba

    from quakescan.change import m3c2 as m3c2_module
    from quakescan.runtime.workers import kernel_threads

    before = numba.get_num_threads()
    with kernel_threads(1):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == before
    seen = []
    real = m3c2_module.ColumnGrid.cylinders

    def spy(self, *a, **kw):
        seen.append(numba.get_num_threads())
        return real(self, *a, **kw)

    monkeypatch.setattr(m3c2_module.ColumnGrid, "cylinders", spy)
    rng = np.random.default_rng(3)
    pre, post = scene(rng, 100, False), scene(rng, 100, True)
    s = SurfaceSettings()
    geom = SurfaceGeometry.for_pair(s, 100, 100)
    one, _ = describe_surfaces(pre[0], pre[1], pre[2] == 2, post[0], [1], s, geom, workers=1)
    assert seen and set(seen) == {1}
    every, _ = describe_surfaces(pre[0], pre[1], pre[2] == 2, post[0], [1], s, geom, workers=-1)
    assert seen[-1] == before
    assert one == every


def test_compiled_top_band_counts_are_numpys_to_the_last_bit():
    from quakescan.grid.cells import top_band_counts, top_band_counts_reference

    rng = np.random.default_rng(3)
    cell = rng.integers(0, 50, 20_000)
    z = np.round(rng.normal(5.0, 2.0, 20_000), 3)  # ties at the band's edge happen
    for band in (0.0, 1.0, 3.7):
        top, counts = top_band_counts(cell, z, 60, band)
        ref_top, ref_counts = top_band_counts_reference(cell, z, 60, band)
        np.testing.assert_array_equal(top, ref_top)
        np.testing.assert_array_equal(counts, ref_counts)
    assert np.isneginf(top[50:]).all() and not counts[50:].any()  # empty cells


@pytest.mark.parametrize("spread, masked", [(300.0, False), (300.0, True), (3.0, True), (1e6, False)])
def test_planimetric_density_on_a_dense_grid_is_the_sorted_cells_to_the_last_bit(spread, masked, monkeypatch):
    """The dense-grid count (no per-point arrays) gives the measure of the cells found by
    sorting, to the last bit: a city, a building too small for an interior cell, and a cloud
    scattered over 1000 km (which falls back to sorting)."""
    from quakescan.grid import density

    rng = np.random.default_rng(4)
    n = 60_000
    xyz = np.c_[rng.uniform(0, spread, n) + 500_000.0, rng.uniform(0, 200, n) - 100, rng.uniform(0, 20, n)]
    where = rng.random(n) < 0.6 if masked else None
    dense = density.planimetric_density(xyz, where)
    monkeypatch.setattr(density, "_dense_planimetric_density", lambda *a: None)
    assert dense == density.planimetric_density(xyz, where)


@pytest.mark.parametrize("spacing", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("table", [True, False])
def test_compiled_patches_and_neighbour_counts_are_numpys(spacing, table, monkeypatch):
    """`_patch_kernels` against `_patch_reference` on core points of a roof with holes, a wall
    and scattered points, several points to some voxels, with the voxel table and with the
    search of the sorted keys: the same patch sizes, the same coherent points and the same
    largest patch (labels may be numbered differently)."""
    from quakescan.change import _patch_kernels as K
    from quakescan.change import _patch_reference as R

    if not table:
        monkeypatch.setattr(K, "TABLE_PER_POINT", -10 ** 9)
    from quakescan.change.core_points import coherence, patch_sizes

    rng = np.random.default_rng(31)
    g = np.arange(0, 20, 0.5)
    roof = np.array([(x, y, 6.0) for x in g for y in g])
    wall = np.array([(x, 0.0, z) for x in g for z in np.arange(0, 6, 0.5)])
    xyz = np.vstack([roof, wall, rng.uniform(0, 20, (300, 3)), roof[:200] + 0.01])  # doubled voxels too
    for share in (0.02, 0.2, 0.6):
        changed = rng.random(len(xyz)) < share
        changed[:400] |= (roof[:400, 0] > 5) & (roof[:400, 0] < 8)  # one real patch
        valid = changed | (rng.random(len(xyz)) < 0.7)
        np.testing.assert_array_equal(patch_sizes(xyz, changed, spacing), R.patch_sizes(xyz, changed, spacing))
        coherent, largest = coherence(xyz, changed, valid, spacing)
        want_coherent, want_largest = R.coherence(xyz, changed, valid, spacing)
        np.testing.assert_array_equal(coherent, want_coherent)
        assert largest == want_largest >= 2
    assert (len(K.voxel_keys(xyz, spacing).first) > 0) == table
    none = np.zeros(len(xyz), bool)
    assert not patch_sizes(xyz, none, spacing).any() and coherence(xyz, none, none, spacing)[1] == 0


def _cell_tops_numpy(xyz, lo, cell, width, layer_m):
    """The numpy reference of _CellTops' compiled loops."""
    from quakescan.change.surface import _BAND_STRIDE_M

    ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    key = ij[:, 0] * width + ij[:, 1]
    order = np.argsort(key, kind="stable")
    k = key[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    z = xyz[order, 2]
    top = np.maximum.reduceat(z, starts)
    bottom = np.minimum.reduceat(z, starts)
    cell_of = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(k)]))
    z0 = -float(z.min())
    band = np.sort(cell_of * _BAND_STRIDE_M + (z + z0))
    layer = z >= top[cell_of] - layer_m
    n = np.bincount(cell_of[layer], minlength=len(starts))
    mean = np.bincount(cell_of[layer], weights=z[layer], minlength=len(starts)) / n
    dev = z[layer] - mean[cell_of[layer]]
    var = np.bincount(cell_of[layer], weights=dev * dev, minlength=len(starts)) / np.maximum(n - 1, 1)
    return {"keys": k[starts], "top": mean, "bottom": bottom, "n": n, "_band_key": band, "_start": starts,
            "count": np.diff(np.r_[starts, len(k)]), "std": np.where(n >= 2, np.sqrt(var), layer_m / np.sqrt(12.0)),
            "_z0": z0}


@pytest.mark.parametrize("offset", [0.0, 4.0e5])
def test_compiled_cell_tops_are_numpys_to_the_last_bit(offset):
    """_CellTops' compiled loops against the numpy expressions they replaced: a roof, a wall
    through some cells, ground, single points and a far-off scatter (a sparse key span: the
    argsort path), at local and at large coordinates."""
    from quakescan.change.surface import _CellTops

    rng = np.random.default_rng(12)
    roof = np.column_stack([rng.uniform(0, 30, (20_000, 2)), 8 + 0.1 * rng.normal(size=20_000)])
    wall = np.column_stack([rng.uniform(0, 30, 3_000), np.full(3_000, 10.2), rng.uniform(0, 8, 3_000)])
    ground = np.column_stack([rng.uniform(-10, 40, (5_000, 2)), rng.normal(0, 0.02, 5_000)])
    far = rng.uniform(-3_000, 3_000, (40, 3))
    for xyz in (np.vstack([roof, wall, ground]), np.vstack([roof, far]), roof[:1]):
        xyz = xyz + [offset, offset, 0.0]
        lo = np.floor(xyz[:, :2].min(axis=0) / 0.7) * 0.7 - 7
        width = int(np.ceil((xyz[:, 1].max() - lo[1]) / 0.7)) + 20
        got = _CellTops(xyz, lo, 0.7, width, 0.35)
        for name, want in _cell_tops_numpy(xyz, lo, 0.7, width, 0.35).items():
            np.testing.assert_array_equal(getattr(got, name), want, err_msg=name)


def test_points_grouped_by_the_caller_give_the_same_descriptors():
    """The pipeline hands its grouping of the points by building to describe_surfaces (one
    grouping a run); the function's own grouping gives the same rows."""
    rng = np.random.default_rng(12)
    pre, post = scene(rng, 40, False), scene(rng, 40, True)
    s = SurfaceSettings()
    geom = SurfaceGeometry.for_pair(s, 40, 40)
    own = describe_surfaces(pre[0], pre[1], pre[2] == 2, post[0], [1], s, geom, workers=1)[0]
    given = describe_surfaces(pre[0], pre[1], pre[2] == 2, post[0], [1], s, geom, workers=1,
                              groups={1: np.flatnonzero(pre[1] == 1)})[0]
    assert given == own and own[1]["s_lowered_1m"] > 0.3
