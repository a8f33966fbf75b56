"""The surface scene of a real cloud (`injection.surface_model`): the city another sensor flies over.

Closed forms: a flat-roofed box on flat ground, sampled in UTM coordinates, gives the roof's
and the ground's heights exactly at every cell centre, walls only within a cell of the
outline, the roof's area within one cell's strip of the outline; noise returns 50 m above the
roof are not surface; a roof quarter without a return takes the roof's height, not the
ground's; a footprint with no return of its own is not a building. Real file: on the AHN3
tile 2, every cell holding a return of its own region is at that cell's highest such return.
"""
import math

import numpy as np
import pytest
import shapely

from quakescan.formats.footprints import Footprints, assign_buildings, read_footprints
from quakescan.formats.scene import GROUND, ROOF, VEGETATION, WALL
from quakescan.injection.surface_model import SurfaceModelError, surface_scene

E0, N0 = 500_000.0, 5_400_000.0  # UTM-sized coordinates: the surface is built in world metres
ROOF_Z = 9.0
BOX = (E0 + 10.0, N0 + 10.0, E0 + 20.0, N0 + 20.0)
CELL = 0.5


def _grid(x0, y0, x1, y1, step):
    x, y = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step), indexing="ij")
    return np.c_[x.ravel(), y.ravel()]


def _city(drop_roof_quarter=False):
    """Ground (class 2) at z 0 over 30 x 30 m, one 10 x 10 m building (class 6) at ROOF_Z,
    four samples per cell; a 2 x 2 m tree (class 5) at 4 m; noise (class 7) 50 m above the roof."""
    xy = _grid(E0, N0, E0 + 30.0, N0 + 30.0, CELL / 2)
    box = shapely.box(*BOX)
    inside = shapely.contains_xy(box, xy[:, 0], xy[:, 1])
    tree = (np.abs(xy[:, 0] - (E0 + 4.0)) < 1.0) & (np.abs(xy[:, 1] - (N0 + 4.0)) < 1.0)
    z = np.where(inside, ROOF_Z, np.where(tree, 4.0, 0.0))
    cls = np.where(inside, 6, np.where(tree, 5, 2))
    keep = np.ones(len(xy), bool)
    if drop_roof_quarter:  # the roof's north-east quarter without a single return
        keep = ~(inside & (xy[:, 0] > E0 + 15.0) & (xy[:, 1] > N0 + 15.0))
    noise = np.c_[E0 + 15.2, N0 + 15.2, ROOF_Z + 50.0].repeat(30, axis=0)
    xyz = np.r_[np.c_[xy, z][keep], noise]
    cls = np.r_[cls[keep], np.full(len(noise), 7)]
    return xyz, cls, Footprints(np.array([3]), [box], "EPSG:32632")


ORIGIN = np.array([E0, N0, 0.0])


def _cell_centres(scene):
    return scene.vertices[:, :2] + ORIGIN[:2]


def test_a_flat_roofed_box_has_its_heights_exact_at_cell_centres_and_walls_on_its_outline():
    xyz, cls, fp = _city()
    scene = surface_scene(xyz, cls, fp, ORIGIN, cell_m=CELL, crs="EPSG:32632")
    assert scene.crs == "EPSG:32632" and [b.id for b in scene.buildings] == [3]
    assert scene.buildings[0].grade == 0 and scene.buildings[0].storeys == 3
    centres = _cell_centres(scene)
    in_box = shapely.contains_xy(shapely.box(*BOX), centres[:, 0], centres[:, 1])
    in_tree = (np.abs(centres[:, 0] - (E0 + 4.0)) < 1.0) & (np.abs(centres[:, 1] - (N0 + 4.0)) < 1.0)
    z = scene.vertices[:, 2]
    assert (z[in_box] == ROOF_Z).all()  # exact: the noise 50 m above is not surface
    assert (z[in_tree] == 4.0).all() and (z[~in_box & ~in_tree] == 0.0).all()
    tri = scene.vertices[scene.faces]
    centroid = tri.mean(axis=1)[:, :2] + ORIGIN[:2]
    ring = shapely.box(*BOX).exterior
    walls = scene.face_surface == WALL
    assert walls.any() and (scene.face_building[walls] == 3).all()
    # a wall spans the step between the last roof cell and the first ground cell
    assert shapely.distance(ring, shapely.points(centroid[walls])).max() <= CELL * math.sqrt(2) / 2 + 1e-9
    roof = (scene.face_building == 3) & (scene.face_surface == ROOF)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normal[:, 2] > 0).all()  # every triangle faces up (counter-clockwise from above)
    roof_area = 0.5 * np.linalg.norm(normal[roof], axis=1).sum()
    assert abs(roof_area - 100.0) <= ring.length * CELL  # within a cell's strip of the outline
    assert (tri[roof][..., 2] == ROOF_Z).all()  # a triangle reaching the ground is steep: a wall
    outside = scene.face_building == 0
    assert set(np.unique(scene.face_surface[outside])) == {GROUND, VEGETATION}
    tree_faces = outside & (scene.face_surface == VEGETATION)
    assert np.all(np.abs(centroid[tree_faces] - [E0 + 4.0, N0 + 4.0]) < 1.0 + CELL)


def test_a_roof_quarter_without_returns_takes_the_roofs_height_and_an_empty_footprint_is_no_building():
    xyz, cls, fp = _city(drop_roof_quarter=True)
    empty = shapely.box(E0 + 24.0, N0 + 24.0, E0 + 28.0, N0 + 28.0)  # over ground, no return of its own
    ground_only = (assign_buildings(xyz[:, 0], xyz[:, 1], Footprints(np.array([9]), [empty])) == 9)
    xyz, cls = xyz[~ground_only], cls[~ground_only]
    fp = Footprints(np.array([3, 9]), [fp.polygons[0], empty], "EPSG:32632")
    scene = surface_scene(xyz, cls, fp, ORIGIN, cell_m=CELL)
    centres = _cell_centres(scene)
    quarter = ((centres[:, 0] > E0 + 15.0) & (centres[:, 0] < E0 + 20.0)
               & (centres[:, 1] > N0 + 15.0) & (centres[:, 1] < N0 + 20.0))
    assert quarter.sum() == 100 and (scene.vertices[quarter, 2] == ROOF_Z).all()
    assert [b.id for b in scene.buildings] == [3] and 9 not in set(scene.face_building.tolist())
    in_empty = shapely.contains_xy(empty, centres[:, 0], centres[:, 1])
    assert (scene.vertices[in_empty, 2] == 0.0).all()


def test_a_return_counts_only_for_a_cell_of_its_own_region():
    # a roof return just outside the outline (a ray that grazed the eave) does not raise the ground
    xyz, cls, fp = _city()
    eave = np.array([[BOX[2] + 0.1, N0 + 15.1, ROOF_Z]])
    scene = surface_scene(np.r_[xyz, eave], np.r_[cls, 6], fp, ORIGIN, cell_m=CELL,
                          building_of_point=np.r_[assign_buildings(xyz[:, 0], xyz[:, 1], fp), 3])
    centres = _cell_centres(scene)
    cell = (np.abs(centres[:, 0] - (BOX[2] + 0.25)) < 1e-6) & (np.abs(centres[:, 1] - (N0 + 15.25)) < 1e-6)
    assert cell.sum() == 1 and scene.vertices[cell, 2][0] == 0.0


def test_bad_input_is_refused_with_what_is_wrong():
    xyz, cls, fp = _city()
    with pytest.raises(SurfaceModelError, match=r"points must be \(n, 3\), got shape \(5, 2\)"):
        surface_scene(np.zeros((5, 2)), None, fp, ORIGIN)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(SurfaceModelError, match="cell size must be a positive number of metres"):
            surface_scene(xyz, cls, fp, ORIGIN, cell_m=bad)
    with pytest.raises(SurfaceModelError, match="holds no return that is not noise"):
        surface_scene(xyz, np.full(len(xyz), 7), fp, ORIGIN)
    with pytest.raises(SurfaceModelError, match="spans 1 x 1 cells of 0.5 m"):
        surface_scene(np.array([[E0, N0, 1.0], [E0 + 0.1, N0 + 0.1, 2.0]]), None, fp, ORIGIN)


def test_the_real_tile_keeps_each_cells_highest_return_of_its_own_region(shared_data):
    import laspy

    las = laspy.read(shared_data / "ahn3_cropped_2.laz")
    xyz = np.c_[las.x, las.y, las.z]
    cls = np.asarray(las.classification)
    fp = read_footprints(shared_data / "ahn3_footprints_rd.geojson")
    origin = np.r_[np.floor(xyz[:, :2].min(axis=0)), 0.0]
    scene = surface_scene(xyz, cls, fp, origin, cell_m=1.0, crs="EPSG:28992")
    keep = ~np.isin(cls, (7, 18))
    xyz = xyz[keep]
    region_pt = assign_buildings(xyz[:, 0], xyz[:, 1], fp)
    lo = np.floor(xyz[:, :2].min(axis=0))  # the grid sits on multiples of the cell size
    centres = scene.vertices[:, :2] + origin[:2]
    ny = len(np.unique(np.round(centres[:, 1], 6)))
    region_cell = assign_buildings(centres[:, 0], centres[:, 1], fp)
    ij = np.floor((xyz[:, :2] - lo) / 1.0).astype(np.int64)
    cell = ij[:, 0] * ny + ij[:, 1]
    own = region_pt == region_cell[cell]
    top = np.full(len(centres), -np.inf)
    np.maximum.at(top, cell[own], xyz[own, 2])
    measured = np.isfinite(top)
    assert measured.mean() > 0.5
    assert np.array_equal(scene.vertices[measured, 2] + origin[2], top[measured])
    ids = {b.id for b in scene.buildings}
    # the buildings: every footprint with a return in one of its own cells, no other
    assert ids == set(np.unique(region_cell[cell[own]]).tolist()) - {0} and len(ids) >= 20
    assert set(np.unique(scene.face_building).tolist()) - {0} == ids
