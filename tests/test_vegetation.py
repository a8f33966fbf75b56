"""Vegetation and objects in the scene contract and porous tree crowns in the scanner."""
import math

import laspy
import numpy as np
import pytest

from quakescan.acquisition.raycast import RayCaster
from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import preset
from quakescan.acquisition.vegetation import RayIds
from quakescan.errors import SceneError
from quakescan.formats.scene import OBJECT, VEGETATION, read_scene, write_scene
from quakescan.formats.synthetic import box_city, box_mesh, flat_ground, with_trees


def _nadir_rays_over_disc(caster, radius, n_side=120, z=30.0):
    g = np.stack(np.meshgrid(np.linspace(-radius, radius, n_side), np.linspace(-radius, radius, n_side)),
                 -1).reshape(-1, 2)
    g = g[np.hypot(g[:, 0], g[:, 1]) < radius]
    o = np.column_stack([g, np.full(len(g), z)]) - caster.local_origin
    return o, np.tile([0.0, 0.0, -1.0], (len(g), 1))


@pytest.mark.parametrize("t", [0.5, 0.3])
def test_crown_crossings_follow_the_transmission_in_closed_form(t):
    """Parallel nadir rays over a spherical crown (radius 3 m, centre 5 m up): returned on the
    upper side with 1 - t, the lower side with t(1 - t), on the ground with t²."""
    scene = with_trees(flat_ground(100.0), [(0.0, 0.0, 5.0, 3.0)], transmission=t)
    caster = RayCaster(scene)
    o, d = _nadir_rays_over_disc(caster, 2.5)  # inside the low-poly silhouette: two crossings each
    face, rng = caster.cast(o, d, 100.0, ray_ids=RayIds(7, 0, np.arange(len(o))))
    z = (o + d * rng[:, None])[:, 2] + caster.local_origin[2]
    n = len(z)
    shares = {"first": np.mean(z > 5.0), "second": np.mean((z < 5.0) & (z > 0.5)), "ground": np.mean(z < 0.01)}
    expected = {"first": 1 - t, "second": t * (1 - t), "ground": t * t}
    for k, p in expected.items():
        assert abs(shares[k] - p) < 4 * math.sqrt(p * (1 - p) / n), (k, shares[k], p, n)
    assert (face >= 0).all()
    # without ray identities (the DIM simulator) the crown is opaque
    face_opaque, rng_opaque = caster.cast(o, d, 100.0)
    assert ((o + d * rng_opaque[:, None])[:, 2] + caster.local_origin[2] > 5.0).all()


def test_transmission_draws_are_reproducible_and_differ_by_seed():
    scene = with_trees(flat_ground(100.0), [(0.0, 0.0, 5.0, 3.0)])
    caster = RayCaster(scene)
    o, d = _nadir_rays_over_disc(caster, 2.5, n_side=40)
    a = caster.cast(o, d, 100.0, ray_ids=RayIds(1, 0, np.arange(len(o))))[0]
    b = caster.cast(o, d, 100.0, ray_ids=RayIds(1, 0, np.arange(len(o))))[0]
    c = caster.cast(o, d, 100.0, ray_ids=RayIds(2, 0, np.arange(len(o))))[0]
    assert (a == b).all() and (a != c).any()


def _tree_beside_building():
    # a 12 x 12 x 6 m box, a tree 1.5 m east of its wall (x = 12) whose crown (radius 4 m,
    # 6.5-14.5 m up) overhangs the roof
    return with_trees(box_city(rows=1, cols=1, height=6.0), [(13.5, 6.0, 10.5, 4.0)])


@pytest.mark.parametrize("beam", ["single", "adaptive", "full"])
def test_roof_under_an_overhanging_crown_gets_returns_and_crowns_are_class_5(tmp_path, beam):
    s = preset("paper").replace(beam=beam, pulse_rate_hz=100_000.0)
    summary = scan(_tree_beside_building(), s, tmp_path / "v.las", seed=1)
    las = laspy.read(tmp_path / "v.las")
    crown = np.asarray(las.surface) == VEGETATION
    assert crown.sum() > 500 and summary.points_by_surface["vegetation"] == crown.sum()
    assert set(np.unique(las.classification[crown])) == {5}
    x, y = np.asarray(las.x), np.asarray(las.y)
    under = (np.hypot(x - 13.5, y - 6.0) < 3.5) & (x < 11.8)
    roof_under = under & (np.asarray(las.surface) == 1)
    assert roof_under.sum() > 20
    # most pulses there stop in the crown, some reach the roof
    assert (under & crown).sum() > roof_under.sum()
    if beam != "single":
        # one pulse returns from the crown and from what lies below it
        nret = np.asarray(las.number_of_returns)
        multi = nret > 1
        assert multi.sum() > 100
        assert (crown & multi).any() and ((np.asarray(las.surface) != VEGETATION) & multi).any()


@pytest.mark.parametrize("beam", ["single", "adaptive", "full"])
def test_vegetation_scans_are_reproducible_and_the_numpy_reference_agrees(tmp_path, beam):
    s = preset("paper").replace(beam=beam, pulse_rate_hz=60_000.0)
    scene = _tree_beside_building()
    scan(scene, s, tmp_path / "a.las", seed=3, batch_rays=100_000, workers=1)
    scan(scene, s, tmp_path / "b.las", seed=3, batch_rays=100_000, workers=3)
    scan(scene, s, tmp_path / "ref.las", seed=3, batch_rays=100_000, fast=False)
    scan(scene, s, tmp_path / "c.las", seed=4, batch_rays=100_000)
    a = (tmp_path / "a.las").read_bytes()
    assert a == (tmp_path / "b.las").read_bytes() == (tmp_path / "ref.las").read_bytes()
    assert a != (tmp_path / "c.las").read_bytes()


def test_hedges_are_low_vegetation_and_objects_unclassified():
    scene = flat_ground(50.0)
    hv, hf, _ = box_mesh(-5, -0.5, 5, 0.5, 0.0, 1.2)  # hedge: opaque, 1.2 m
    cv, cf, _ = box_mesh(3, 3, 7.5, 4.8, 0.0, 1.5)  # a car
    n = len(scene.vertices)
    v = np.concatenate([scene.vertices, hv, cv])
    f = np.concatenate([scene.faces, hf + n, cf + n + len(hv)])
    surf = np.concatenate([scene.face_surface, np.full(len(hf), VEGETATION, np.uint8),
                           np.full(len(cf), OBJECT, np.uint8)])
    from quakescan.formats.scene import Scene
    sc = Scene(v, f, np.zeros(len(f), np.int32), surf, [])
    caster = RayCaster(sc)
    assert set(caster.face_class[surf == VEGETATION]) == {3}
    assert set(caster.face_class[surf == OBJECT]) == {1}
    assert caster.face_porous is None  # nothing porous: the plain, unchanged cast


def test_bundle_with_vegetation_round_trips_and_bad_labels_are_named(tmp_path):
    scene = with_trees(box_city(rows=1, cols=1), [(20.0, 5.0, 5.0, 3.0)], transmission=0.35)
    write_scene(scene, tmp_path / "veg")
    back = read_scene(tmp_path / "veg")
    assert back.transmission == 0.35
    assert (back.face_porous == scene.face_porous).all()
    assert (back.face_surface == scene.face_surface).all()
    # a scene without porous faces keeps the old layout: no porous property, no vegetation record
    write_scene(box_city(rows=1, cols=1), tmp_path / "plain")
    assert b"porous" not in (tmp_path / "plain" / "mesh.ply").read_bytes()[:400]
    assert "vegetation" not in (tmp_path / "plain" / "scene.json").read_text()
    assert read_scene(tmp_path / "plain").face_porous is None

    bad = with_trees(box_city(rows=1, cols=1), [(20.0, 5.0, 5.0, 3.0)])
    bad.face_porous = bad.face_porous.copy()
    bad.face_porous[0] = True  # a ground face
    with pytest.raises(SceneError, match="porous but its surface is 'ground'"):
        write_scene(bad, tmp_path / "bad")
    bad = with_trees(box_city(rows=1, cols=1), [(20.0, 5.0, 5.0, 3.0)])
    bad.face_building = bad.face_building.copy()
    bad.face_building[-1] = 1
    with pytest.raises(SceneError, match="vegetation and objects are not buildings"):
        write_scene(bad, tmp_path / "bad")
    bad = box_city(rows=1, cols=1)
    bad.face_surface = bad.face_surface.copy()
    bad.face_surface[0] = 7
    with pytest.raises(SceneError, match="surface code 7"):
        write_scene(bad, tmp_path / "bad")
    text = (tmp_path / "veg" / "scene.json").read_text().replace('"transmission": 0.35', '"transmission": 1.5')
    (tmp_path / "veg" / "scene.json").write_text(text)
    with pytest.raises(SceneError, match="vegetation.transmission must be a number in"):
        read_scene(tmp_path / "veg")


def test_dim_sees_crowns_as_opaque_surfaces(tmp_path):
    """Photogrammetry reconstructs a crown's outer surface: class 5 points on it, no ground
    matched beside the trunk under a crown reaching down to 0.5 m, where no camera sees the
    ground past the crown's surface (the laser scan, seeing through, has some there)."""
    from quakescan.acquisition.dim import simulate_dim
    from quakescan.acquisition.dim_settings import preset_dim
    scene = with_trees(box_city(rows=1, cols=1, height=6.0), [(30.0, 6.0, 3.5, 3.0)])
    simulate_dim(scene, preset_dim("paper").replace(margin_m=60.0), tmp_path / "dim.las", seed=1)
    las = laspy.read(tmp_path / "dim.las")
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    crown = np.asarray(las.surface) == VEGETATION
    assert crown.sum() > 100 and set(np.unique(las.classification[crown])) == {5}
    def near_trunk(x, y, z):
        r = np.hypot(np.asarray(x) - 30.0, np.asarray(y) - 6.0)
        return (r > 0.2) & (r < 0.6) & (np.asarray(z) < 0.1)
    assert not near_trunk(x, y, z).any()
    scan(scene, preset("paper").replace(pulse_rate_hz=100_000.0), tmp_path / "uls.las", seed=1)
    u = laspy.read(tmp_path / "uls.las")
    assert near_trunk(u.x, u.y, u.z).any()


def test_scene_fingerprint_sees_the_porous_faces_and_transmission():
    from quakescan.runtime.fingerprint import scene_fingerprint
    plain = box_city(rows=1, cols=1)
    a = with_trees(plain, [(20.0, 5.0, 5.0, 3.0)])
    b = with_trees(plain, [(20.0, 5.0, 5.0, 3.0)], transmission=0.2)
    c = with_trees(plain, [(20.0, 5.0, 5.0, 3.0)])
    c.face_porous = np.zeros_like(c.face_porous)
    c.face_porous[-1] = True
    assert len({scene_fingerprint(x) for x in (a, b, c)}) == 3
    assert scene_fingerprint(plain) == scene_fingerprint(box_city(rows=1, cols=1))


@pytest.mark.skipif(__import__("importlib").util.find_spec("bpy") is None, reason="bpy module not installed")
def test_demo_generate_passes_the_streetscape_through(tmp_path):
    from quakescan.generator import GenerationSpec, generate
    generate(GenerationSpec("generic", "mixed", 6, 1, tmp_path / "street", streetscape="typical"))
    generate(GenerationSpec("generic", "mixed", 6, 1, tmp_path / "plain"))
    street, plain = read_scene(tmp_path / "street" / "pre"), read_scene(tmp_path / "plain" / "pre")
    assert street.has_porous and (street.face_surface == OBJECT).any()
    assert plain.face_porous is None and (plain.face_surface < VEGETATION).all()
