"""Shells and damage patterns on BMesh: each pattern changes the geometry as its parameters
say, against closed-form answers; meshes stay valid; same seed, same mesh."""
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402

from addon import ems98  # noqa: E402
from addon.geometry import mesh as gm  # noqa: E402
from addon.geometry import patterns as gp  # noqa: E402
from addon.geometry.common import PatternNotApplicable  # noqa: E402
from addon.geometry.shell import ShellSpec, build_shell, rect_footprint  # noqa: E402
from addon_measure import DEBRIS, INTERIOR, area, check_valid, hf_volume, tilt_deg, tri_normals  # noqa: E402

BID = 7


def masonry_gable(**kw):
    d = dict(footprint=rect_footprint(12, 9), storeys=3, storey_height=3.0, roof="gable", roof_pitch=30.0,
             chimney=[2.0, 1.0, 0.6, 1.5], material="masonry")
    d.update(kw)
    return ShellSpec(**d)


def rc_flat(**kw):
    d = dict(footprint=rect_footprint(24, 12), storeys=5, storey_height=3.2, roof="flat", parapet_height=0.8,
             bay_width=4.8, material="reinforced_concrete")
    d.update(kw)
    return ShellSpec(**d)


def rc_L(**kw):
    d = dict(footprint=[[0, 0], [20, 0], [20, 8], [8, 8], [8, 18], [0, 18]], storeys=4, storey_height=3.2,
             roof="flat", parapet_height=0.6, bay_width=4.0, material="reinforced_concrete")
    d.update(kw)
    return ShellSpec(**d)


def built(spec):
    bm = bmesh.new()
    build_shell(bm, spec, BID)
    return bm


def arr(bm):
    v, t, s, b, p = gm.arrays(bm)
    return v, t, s, b, p


def run(spec, name, seed=0, **params):
    bm = built(spec)
    before = arr(bm)
    rec = gp.apply_pattern(bm, spec, name, params or None, np.random.default_rng(seed), BID)
    after = arr(bm)
    check_valid(after[0], after[1], after[2], after[3], BID)
    return bm, before, after, rec["params"]


# --- shells ----------------------------------------------------------------------------------

@pytest.mark.parametrize("roof", ["flat", "gable", "hip"])
def test_shell_closed_form(roof):
    spec = masonry_gable(roof=roof, chimney=None, parapet_height=0.5 if roof == "flat" else 0.0)
    bm = built(spec)
    v, t, s, b, p = arr(bm)
    check_valid(v, t, s, b, BID)
    roof_area = area(v, t, p == gm.P_ROOF)
    if roof == "flat":
        assert roof_area == pytest.approx(108.0)
        assert area(v, t, p == gm.P_PARAPET) == pytest.approx(42 * 0.5)
    else:  # pitched planes: footprint / cos(pitch)
        assert roof_area == pytest.approx(108.0 / math.cos(math.radians(30)), rel=1e-5)
    assert area(v, t, p == gm.P_WALL) == pytest.approx(42 * 9.0)
    # floors: slabs at 3 and 6 m (+ attic floor under a pitched roof), all 'interior'
    slab_z = sorted({round(float(z), 3) for z in v[t[p == gm.P_SLAB]].reshape(-1, 3)[:, 2]})
    assert slab_z == ([3.0, 6.0] if roof == "flat" else [3.0, 6.0, 9.0])
    assert (s[p == gm.P_SLAB] == INTERIOR).all() and (s[p == gm.P_INNER] == INTERIOR).all()
    assert (p == gm.P_INNER).any()
    assert v[:, 2].max() == pytest.approx(spec.height + (0.5 if roof == "flat" else 0.0), abs=1e-5)
    if roof == "gable":
        assert area(v, t, p == gm.P_GABLE) == pytest.approx(2 * 0.5 * 9 * spec.ridge_rise, rel=1e-5)


def test_shell_walls_face_outwards():
    bm = built(rc_L())
    v, t, s, b, p = arr(bm)
    n = tri_normals(v, t)[p == gm.P_WALL]
    c = v[t[p == gm.P_WALL]].mean(axis=1)
    # moving a little along the normal leaves the footprint
    from addon.geometry import poly2d
    out = c[:, :2] + 0.01 * n[:, :2]
    assert not poly2d.contains(rc_L().poly, out).any()


# --- openings --------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_roof_holes_area(seed):
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "roof_holes", seed, n_holes=6,
                                                              area_fraction=0.15, hole_min=0.5, hole_max=3.0)
    removed = area(v0, t0, p0 == gm.P_ROOF) - area(v1, t1, p1 == gm.P_ROOF)
    assert removed == pytest.approx(prm["hole_area"], rel=1e-4)
    assert 3 <= prm["n_holes"] <= 15
    assert prm["area_fraction"] == pytest.approx(0.15, abs=0.02)
    # through to the attic: the attic floor is intact below
    assert area(v1, t1, p1 == gm.P_SLAB) == pytest.approx(area(v0, t0, p0 == gm.P_SLAB))


def test_wall_holes_area():
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "wall_holes", 3, n_facades=2,
                                                              holes_per_facade=3, area_fraction=0.06,
                                                              hole_min=0.5, hole_max=2.0, corner_breakouts=2)
    removed = area(v0, t0, p0 == gm.P_WALL) - area(v1, t1, p1 == gm.P_WALL)
    assert removed == pytest.approx(prm["hole_area"], rel=1e-4)
    assert prm["n_facades"] == 2
    for f in prm["facades"]:
        assert 0.02 <= f["area_fraction"] <= 0.10
        assert 1 <= f["holes"] <= 4
    # two corner notches, each 0.5-1.5 m into both walls and 0.8-2 m high
    assert prm["corner_breakouts"] == 2
    assert 2 * 2 * 0.5 * 0.8 - 1e-6 <= prm["corner_area"] <= 2 * 2 * 1.5 * 2.0 + 1e-6


def test_infill_blowout_panels_and_debris():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "infill_blowout", 1, panels=2,
                                                              debris_height=0.6, solid_fraction=0.15, bulking=1.5)
    bay = 24 / 5  # 5 bays of 4.8 m on the long facades, 12/round(12/4.8)=6 m on the short ones
    opened = area(v0, t0, p0 == gm.P_WALL) - area(v1, t1, p1 == gm.P_WALL)
    assert opened == pytest.approx(prm["opened_area"], rel=1e-6)
    assert prm["panels"] == 2
    h = 3.2 - 0.1 - 0.5
    assert opened in (pytest.approx(2 * (bay - 0.35) * h), pytest.approx(2 * (6 - 0.35) * h),
                      pytest.approx(((bay - 0.35) + (6 - 0.35)) * h))
    vol = hf_volume(v1, t1, s1 == DEBRIS)
    assert vol == pytest.approx(0.15 * 1.5 * opened * 1.0, rel=1e-4)
    assert vol == pytest.approx(prm["debris_volume"], rel=1e-4)


def test_infill_blowout_storey_share():
    spec = rc_flat()
    bm, _, (v1, t1, s1, b1, p1), prm = run(spec, "infill_blowout", 2, panels=0, storey_share=0.5,
                                           debris_height=0.6, solid_fraction=0.15, bulking=1.5)
    assert prm["mode"] == "storey"
    storeys = {k for _, k, _ in prm["panel_list"]}
    assert len(storeys) == 1
    assert prm["panels"] == round(0.5 * 14)  # 5+2+5+2 panels per storey


# --- elements ------------------------------------------------------------------------------

def test_chimney_loss_height():
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "chimney_loss", 0, removed_height=1.0,
                                                              fragment_distance=2.0, n_fragments=4)
    top0 = v0[t0[p0 == gm.P_CHIMNEY]].reshape(-1, 3)[:, 2].max()
    top1 = v1[t1[p1 == gm.P_CHIMNEY]].reshape(-1, 3)[:, 2].max()
    assert top0 - top1 == pytest.approx(1.0, abs=1e-4)
    frag = v1[t1[s1 == DEBRIS]].reshape(-1, 3)
    d = np.hypot(frag[:, 0] - 2.0, frag[:, 1] - 1.0)
    assert d.max() <= 2.0 + 0.6  # within the distance (plus the fragment size)
    assert hf_volume(v1, t1, s1 == DEBRIS, base_z=0.0) == pytest.approx(prm["debris_volume"], rel=1e-3)


def test_parapet_loss_length():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "parapet_loss", 4, length_fraction=0.3,
                                                              solid_fraction=0.15, bulking=1.5)
    removed = area(v0, t0, p0 == gm.P_PARAPET) - area(v1, t1, p1 == gm.P_PARAPET)
    assert removed == pytest.approx(0.3 * 72 * 0.8, rel=1e-4)
    assert prm["length_fraction"] == pytest.approx(0.3, abs=1e-4)
    assert hf_volume(v1, t1, s1 == DEBRIS) == pytest.approx(0.15 * 1.5 * removed, rel=1e-4)


@pytest.mark.parametrize("fraction", [0.3, 1.0])
def test_gable_fall(fraction):
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "gable_fall", 1, gable_fraction=fraction,
                                                              fan_height=0.5, solid_fraction=0.2, bulking=1.5)
    hg = spec.ridge_rise
    removed = area(v0, t0, p0 == gm.P_GABLE) - area(v1, t1, p1 == gm.P_GABLE)
    assert removed == pytest.approx(fraction * 0.5 * 9 * hg, rel=1e-4)
    vol = hf_volume(v1, t1, s1 == DEBRIS)
    assert vol == pytest.approx(0.2 * 1.5 * removed, rel=1e-4)
    assert 0.5 - 1e-6 <= prm["fan_reach"] <= 1.0 + 1e-6
    # the fan lies outside the gable wall (x = +-6), no further than its reach
    deb = v1[t1[s1 == DEBRIS]].reshape(-1, 3)
    dist = np.abs(deb[:, 0]) - 6.0
    assert dist.min() >= 0 and dist.max() <= prm["fan_reach"] * hg + 0.05


def test_gable_fall_needs_a_gable():
    with pytest.raises(PatternNotApplicable, match="no gable"):
        run(rc_flat(), "gable_fall", 0)


def test_facade_topple():
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "facade_topple", 2, facade_fraction=0.5,
                                                              height_fraction=0.67, fan_height=1.0,
                                                              solid_fraction=0.2, bulking=1.5)
    m = prm["collapsed_storeys"]
    assert m == 2
    L = 12.0 if prm["facade"] in (0, 2) else 9.0
    removed = area(v0, t0, np.isin(p0, [gm.P_WALL, gm.P_GABLE])) - area(v1, t1, np.isin(p1, [gm.P_WALL, gm.P_GABLE]))
    assert removed == pytest.approx(0.5 * L * m * 3.0, rel=1e-4)
    assert hf_volume(v1, t1, s1 == DEBRIS) == pytest.approx(0.2 * 1.5 * removed, rel=1e-4)
    assert 0.5 - 1e-6 <= prm["fan_reach"] <= 1.0 + 1e-6
    # holes reveal the interior: slabs untouched
    assert area(v1, t1, p1 == gm.P_SLAB) == pytest.approx(area(v0, t0, p0 == gm.P_SLAB))


def _roof_drop_integral(v0, t0, p0, v1, t1, p1):
    """∫ (z before − z after) dA over the horizontal projection of a flat roof at one height:
    the roof volume the sag took away (before: every roof triangle at the same height)."""
    z_roof = float(v0[t0[p0 == gm.P_ROOF]][..., 2].max())
    tri = v1[t1[p1 == gm.P_ROOF]]
    e1, e2 = tri[:, 1, :2] - tri[:, 0, :2], tri[:, 2, :2] - tri[:, 0, :2]
    proj = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return float(np.sum(proj * (z_roof - tri[:, :, 2].mean(axis=1))))


def test_facade_topple_roof_sags_over_the_fallen_wall():
    # flat roof at 9 m, top two storeys fall (z0 = 3 m): the strip 3 m deep behind the fallen
    # half of the facade hinges down, edge 1.5 m lower; a wedge of 1/2 · 1.5 · 3 · segment
    spec = masonry_gable(roof="flat", chimney=None, parapet_height=0.5)
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "facade_topple", 2, facade_fraction=0.5,
                                                              height_fraction=0.67, fan_height=1.0,
                                                              solid_fraction=0.2, bulking=1.5, roof_drop=1.5,
                                                              sag_depth=3.0)
    L = 12.0 if prm["facade"] in (0, 2) else 9.0
    assert prm["roof_drop"] == pytest.approx(1.5)
    assert prm["sagged_roof_area"] > 0.5 * L * 3.0  # the plate got steeper, so larger than its plan
    assert _roof_drop_integral(v0, t0, p0, v1, t1, p1) == pytest.approx(0.5 * 1.5 * 3.0 * 0.5 * L, rel=1e-4)
    roof_z = v1[t1[p1 == gm.P_ROOF]][..., 2]
    assert roof_z.min() == pytest.approx(9.0 - 1.5)
    # the floor at 6 m spanned onto the fallen wall: its part in the strip fell; the one at 3 m
    # (the top of the wall left standing) stays
    assert prm["fallen_floor_area"] == pytest.approx(0.5 * L * 3.0, rel=1e-4)
    slab = p1 == gm.P_SLAB
    assert area(v1, t1, slab) == pytest.approx(area(v0, t0, p0 == gm.P_SLAB) - 0.5 * L * 3.0, rel=1e-4)
    at_3m = (np.abs(v1[t1][..., 2] - 3.0) < 1e-6).all(axis=1)
    assert area(v1, t1, slab & at_3m) == pytest.approx(108.0)


def test_facade_topple_roof_rests_on_the_wall_left_standing():
    # one storey falls (z0 = 6 m): a 10 m drop asked, the edge comes to rest 0.1 m above the wall
    spec = masonry_gable(roof="flat", chimney=None, parapet_height=0.5)
    _, _, (v1, t1, s1, b1, p1), prm = run(spec, "facade_topple", 4, facade_fraction=1.0, height_fraction=0.2,
                                          fan_height=1.0, solid_fraction=0.2, bulking=1.5, roof_drop=10.0,
                                          sag_depth=2.0)
    assert prm["collapsed_storeys"] == 1
    assert prm["roof_drop"] == pytest.approx(9.0 - 6.0 - 0.1)
    assert v1[t1[p1 == gm.P_ROOF]][..., 2].min() == pytest.approx(6.1)
    assert prm["fallen_floor_area"] == 0.0  # no floor above the wall left standing under a flat roof


def test_facade_topple_sag_under_a_pitched_roof():
    # gable roof, the gable ends party walls (so an eave side falls): the eave over the fallen
    # part drops as asked, and no floor is left above the sagged roof (the attic floor in the
    # strip fell with it)
    spec = masonry_gable(party_walls=[1, 3])
    for seed in range(4):
        _, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(
            spec, "facade_topple", seed, facade_fraction=0.6, height_fraction=0.34, fan_height=1.0,
            solid_fraction=0.2, bulking=1.5, roof_drop=2.0, sag_depth=3.0)
        assert prm["facade"] in (0, 2) and prm["roof_drop"] == pytest.approx(2.0)
        assert v1[t1[p1 == gm.P_ROOF]][..., 2].min() == pytest.approx(9.0 - 2.0)
        attic = (np.abs(v1[t1][..., 2] - 9.0) < 1e-6).all(axis=1) & (p1 == gm.P_SLAB)
        assert area(v1, t1, attic) == pytest.approx(108.0 - prm["fallen_floor_area"])
        assert prm["fallen_floor_area"] == pytest.approx(0.6 * 12.0 * 3.0, rel=1e-4)


def test_party_walls_are_not_used_for_facades():
    spec = masonry_gable(party_walls=[1, 3])
    for seed in range(5):
        _, _, _, prm = run(spec, "facade_topple", seed)
        assert prm["facade"] in (0, 2)
        _, _, _, prm = run(spec, "wall_holes", seed, n_facades=4, holes_per_facade=2, area_fraction=0.05,
                           hole_min=0.5, hole_max=2.0)
        assert {f["facade"] for f in prm["facades"]} <= {0, 2}
    with pytest.raises(PatternNotApplicable):
        run(spec, "gable_fall", 0)  # both gables are party walls


# --- collapses -------------------------------------------------------------------------------

def test_partial_roof_collapse_drop_and_tilt():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "partial_roof_collapse", 3,
                                                              area_fraction=0.4, drop=1.5, tilt=20.0)
    assert prm["area_fraction"] == pytest.approx(0.4, abs=1e-6)
    roof = p1 == gm.P_ROOF
    n = tri_normals(v1, t1)[roof]
    c = v1[t1[roof]].mean(axis=1)
    fallen = c[:, 2] < spec.eave_height - 1e-3
    assert fallen.any() and (~fallen).any()
    tilts = [tilt_deg(x) for x in n[fallen]]
    assert np.allclose(tilts, 20.0, atol=1e-3)
    # the fallen plates' centroid dropped by `drop` (area-weighted), within the catalogue range
    idx = np.flatnonzero(roof)[fallen]
    a = np.array([area(v1, t1[i:i + 1], np.array([True])) for i in idx])
    zc = float((v1[t1[idx]].mean(axis=1)[:, 2] * a).sum() / a.sum())
    assert spec.eave_height - zc == pytest.approx(prm["drop"], abs=1e-3)
    assert prm["drop"] == pytest.approx(1.5, abs=1e-6)
    assert area(v1, t1, roof) == pytest.approx(area(v0, t0, p0 == gm.P_ROOF), rel=0.1)


def test_partial_roof_collapse_pitched_breaks_attic_floor():
    spec = masonry_gable()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "partial_roof_collapse", 0,
                                                              area_fraction=0.5, drop=2.5, tilt=15.0)
    assert prm["floor_collapsed"]
    attic0 = area(v0, t0, (p0 == gm.P_SLAB) & (v0[t0][:, :, 2].mean(axis=1) > 8.9))
    attic1 = area(v1, t1, (p1 == gm.P_SLAB) & (v1[t1][:, :, 2].mean(axis=1) > 8.9))
    assert attic1 == pytest.approx(attic0 * 0.5, rel=1e-4)
    roof = v1[t1[p1 == gm.P_ROOF]].reshape(-1, 3)
    assert roof[:, 2].min() >= spec.z_level(2) + 0.1 - 1e-4  # resting at most on the floor below


def test_top_storey_collapse():
    spec = masonry_gable(chimney=None)
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "top_storey_collapse", 1,
                                                              footprint_fraction=0.4, solid_fraction=0.2,
                                                              bulking=1.5)
    assert prm["footprint_fraction"] == pytest.approx(0.4, abs=1e-6)
    top_walls0 = area(v0, t0, (p0 == gm.P_WALL) & (v0[t0][:, :, 2].mean(axis=1) > 6))
    top_walls1 = area(v1, t1, (p1 == gm.P_WALL) & (v1[t1][:, :, 2].mean(axis=1) > 6))
    # both long facades lose 40 % and one end wall goes entirely
    assert top_walls0 - top_walls1 == pytest.approx(2 * 0.4 * 12 * 3 + 9 * 3, rel=1e-4)
    assert area(v1, t1, p1 == gm.P_ROOF) == pytest.approx(0.6 * area(v0, t0, p0 == gm.P_ROOF), rel=1e-4)
    expected = 0.2 * 1.5 * (0.4 * 108 * 3 + 0.4 * (spec.gross_volume - 108 * 9))
    assert hf_volume(v1, t1, s1 == DEBRIS, base_z=6.0) == pytest.approx(expected, rel=1e-4)


def _slab_tilt_and_z(v, t, p, storey_faces_mask):
    n = tri_normals(v, t)[storey_faces_mask]
    z = v[t[storey_faces_mask]].reshape(-1, 3)[:, 2]
    return max(tilt_deg(x) for x in n), z.min(), z.max()


def test_soft_storey_collapse():
    spec = rc_flat(storeys=4)
    bm = built(spec)
    rec = gp.apply_pattern(bm, spec, "soft_storey_collapse", dict(drop=3.0, tilt=4.0, offset=1.0,
                                                                   solid_fraction=0.15, bulking=1.5),
                           np.random.default_rng(5), BID)["params"]
    v, t, s, b, p = arr(bm)
    check_valid(v, t, s, b, BID)
    assert rec["drop"] == pytest.approx(3.0)
    assert rec["tilt"] == pytest.approx(4.0)
    # ground-storey walls are gone, the upper storeys intact
    lab = gm.Labels(bm)
    assert not gm.faces_where(bm, lab, parts={gm.P_WALL}, storeys={0})
    assert len(gm.faces_where(bm, lab, parts={gm.P_WALL}, storeys={1, 2, 3})) == 12
    # first-floor slab: lowest at 3.2 - 3.0 above ground, tilted 4 degrees
    tilt, zmin, zmax = _slab_tilt_and_z(v, t, p, (p == gm.P_SLAB) & (v[t][:, :, 2].mean(axis=1) < 3.0))
    assert tilt == pytest.approx(4.0, abs=1e-3)
    assert zmin == pytest.approx(0.2, abs=1e-3)
    # upper block shifted by the offset towards the hinge side
    roof_c = v[t[p == gm.P_ROOF]].reshape(-1, 3)[:, :2].mean(axis=0)
    assert np.hypot(*roof_c) == pytest.approx(1.0, abs=0.8)
    total = 0.15 * 1.5 * 24 * 12 * 3.2
    assert rec["debris_volume_total"] == pytest.approx(total, rel=1e-3)
    assert hf_volume(v, t, s == DEBRIS) == pytest.approx(rec["debris_volume"], rel=1e-4)
    assert 0.3 * total - 1e-6 <= rec["debris_volume"] <= total


def test_soft_storey_drop_capped_by_storey_height():
    spec = rc_flat(storeys=3, storey_height=3.0)
    _, _, _, prm = run(spec, "soft_storey_collapse", 0, drop=4.0, tilt=0.0, offset=0.5, solid_fraction=0.15,
                       bulking=1.5)
    assert prm["drop"] == pytest.approx(3.0 - 0.15)


def test_mid_storey_and_top_floor_pancake():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "mid_storey_collapse", 1, residual_height=0.5,
                                                              tilt=0.0, offset=0.0, solid_fraction=0.15,
                                                              bulking=1.5)
    assert 1 <= prm["storey"] <= 3
    roof_z = v1[t1[p1 == gm.P_ROOF]].reshape(-1, 3)[:, 2]
    assert roof_z.max() == pytest.approx(16.0 - (3.2 - 0.5), abs=1e-3)
    bm, _, (v1, t1, s1, b1, p1), prm = run(spec, "top_floor_pancake", 0, residual_height=0.4,
                                           solid_fraction=0.15, bulking=1.5)
    assert prm["storey"] == 4 and prm["residual_height"] == pytest.approx(0.4)
    roof_z = v1[t1[p1 == gm.P_ROOF]].reshape(-1, 3)[:, 2]
    assert np.allclose(roof_z, 12.8 + 0.4, atol=1e-4)


def test_pancake_collapse():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "pancake_collapse", 2,
                                                              final_height_fraction=0.15, max_slab_tilt=15.0,
                                                              spread_fraction=0.2, solid_fraction=0.15, bulking=1.5)
    assert not (p1 == gm.P_WALL).any() and not (p1 == gm.P_INNER).any()
    assert prm["final_height_fraction"] == pytest.approx(0.15, abs=0.01)
    assert 0.10 <= prm["final_height_fraction"] <= 0.25
    for mask in (p1 == gm.P_SLAB, p1 == gm.P_ROOF):
        assert max(tilt_deg(x) for x in tri_normals(v1, t1)[mask]) <= 15.0 + 1e-3
    assert v1[:, 2].min() >= -1e-6
    total = 0.15 * 1.5 * spec.gross_volume
    assert prm["debris_volume_total"] == pytest.approx(total, rel=1e-3)
    assert hf_volume(v1, t1, s1 == DEBRIS) == pytest.approx(prm["debris_volume"], rel=1e-4)
    deb = v1[t1[s1 == DEBRIS]].reshape(-1, 3)
    assert np.abs(deb[:, 0]).max() <= 12 + prm["spread_fraction"] * spec.height + 1e-6


def test_corner_failure():
    spec = rc_flat()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "corner_failure", 0, drop=2.0, tilt=20.0,
                                                              solid_fraction=0.15, bulking=1.5)
    cx, cy = prm["corner"]
    roof = v1[t1[p1 == gm.P_ROOF]].reshape(-1, 3)
    at_corner = roof[np.hypot(roof[:, 0] - cx, roof[:, 1] - cy) < 1e-3]
    assert at_corner[:, 2] == pytest.approx(16.0 - prm["drop"], abs=1e-3)
    assert 1.0 <= prm["drop"] <= 3.0 and 10.0 <= prm["tilt"] <= 30.0
    assert math.degrees(math.atan2(prm["drop"], prm["extent"])) == pytest.approx(prm["tilt"], abs=1e-3)
    far = roof[np.hypot(roof[:, 0] + cx, roof[:, 1] + cy) < 1e-3]
    assert far[:, 2] == pytest.approx(16.0, abs=1e-4)  # the opposite corner stays


def test_wing_collapse():
    spec = rc_L()
    bm, (v0, t0, s0, b0, p0), (v1, t1, s1, b1, p1), prm = run(spec, "wing_collapse", 1, footprint_fraction=0.4,
                                                              spread_fraction=0.2, solid_fraction=0.15, bulking=1.5)
    assert prm["footprint_fraction"] == pytest.approx(0.4, abs=1e-6)
    assert area(v1, t1, p1 == gm.P_ROOF) == pytest.approx(0.6 * area(v0, t0, p0 == gm.P_ROOF), rel=1e-4)
    assert hf_volume(v1, t1, s1 == DEBRIS) == pytest.approx(0.15 * 1.5 * 0.4 * spec.gross_volume, rel=1e-4)


def test_debris_heap():
    spec = masonry_gable()
    bm, _, (v1, t1, s1, b1, p1), prm = run(spec, "debris_heap", 3, heap_height_fraction=0.25, stub_fraction=0.2,
                                           stub_height_fraction=0.8, solid_fraction=0.2, bulking=1.5)
    assert set(np.unique(p1).tolist()) <= {gm.P_DEBRIS, gm.P_STUB}
    assert hf_volume(v1, t1, s1 == DEBRIS) == pytest.approx(0.2 * 1.5 * spec.gross_volume, rel=1e-4)
    H = spec.height
    peak = v1[t1[s1 == DEBRIS]].reshape(-1, 3)[:, 2].max()
    assert peak / H == pytest.approx(prm["heap_height_fraction"], abs=1e-4)
    assert 0.10 <= prm["heap_height_fraction"] <= 0.40
    assert 0.1 - 1e-6 <= prm["spread_fraction"] <= 0.67 + 1e-6
    stubs = v1[t1[p1 == gm.P_STUB]].reshape(-1, 3)
    assert stubs[:, 2].max() <= 0.8 * 3.0 + 1e-6
    assert 0 < prm["stub_fraction"] <= 0.3


# --- rigid -----------------------------------------------------------------------------------

@pytest.mark.parametrize("angle", [2.0, 8.0])
def test_tilt_angle(angle):
    spec = rc_flat()
    bm, _, (v1, t1, s1, b1, p1), prm = run(spec, "tilt", 0, angle=angle)
    assert max(tilt_deg(x) for x in tri_normals(v1, t1)[p1 == gm.P_ROOF]) == pytest.approx(angle, abs=1e-3)
    wall_n = tri_normals(v1, t1)[p1 == gm.P_WALL]
    assert max(90 - tilt_deg(x) for x in wall_n) == pytest.approx(angle, abs=1e-3)


def test_overturn():
    spec = rc_flat(storeys=3)
    bm, _, (v1, t1, s1, b1, p1), prm = run(spec, "overturn", 0, angle=90.0)
    assert v1[:, 2].min() >= -1e-4
    # roof now vertical, base visible
    assert tri_normals(v1, t1)[p1 == gm.P_ROOF][:, 2] == pytest.approx(0.0, abs=1e-4)
    assert (p1 == gm.P_BASE).any()
    c = v1.mean(axis=0)
    assert np.hypot(c[0], c[1]) <= spec.height + 12


# --- every pattern ---------------------------------------------------------------------------

SPECS = {"masonry_gable": masonry_gable, "masonry_hip": lambda: masonry_gable(roof="hip", chimney=None),
         "rc_flat": rc_flat, "rc_L": rc_L}


@pytest.mark.parametrize("spec_name", list(SPECS))
@pytest.mark.parametrize("name", ems98.PATTERN_NAMES)
def test_every_pattern_valid_and_seeded(spec_name, name):
    spec = SPECS[spec_name]()
    grade = max(ems98.PATTERNS[name].grades)
    outs = []
    for _ in range(2):
        bm = built(spec)
        rng = np.random.default_rng(11)
        params = ems98.sample_params(name, rng, grade, spec.material)
        try:
            rec = gp.apply_pattern(bm, spec, name, params, rng, BID)
        except PatternNotApplicable:
            assert not ems98.requirements_met(name, spec.features()) or name in ("chimney_loss",)
            return
        v, t, s, b, p = arr(bm)
        check_valid(v, t, s, b, BID)
        assert (b == BID).all()
        assert rec["name"] == name and isinstance(rec["params"], dict)
        if ems98.PATTERNS[name].stage < 3:
            assert v[:, 2].min() >= -1e-4  # nothing below ground except tilted/overturned buildings
        outs.append((v, t, s))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


@pytest.mark.parametrize("grade", [3, 4, 5])
@pytest.mark.parametrize("spec_name", list(SPECS))
def test_damage_for_grade(spec_name, grade):
    spec = SPECS[spec_name]()
    bm = built(spec)
    new, records = gp.damage_for_grade(bm, spec, grade, gp.pattern_rng(4, grade), BID)
    v, t, s, b, p = arr(new)
    check_valid(v, t, s, b, BID)
    assert records and any(grade in ems98.PATTERNS[r["name"]].grades for r in records)
    # the input mesh is untouched
    assert len(arr(bm)[1]) == len(arr(built(spec))[1])
    new.free()


def test_adding_a_pattern_changes_no_other_pattern_s_output(monkeypatch):
    """Each pattern draws from a stream salted by its name: a new secondary pattern that
    draws many numbers (and leaves the mesh alone) changes nothing the others make. With one
    stream for the whole building its draws shifted the primary pattern's geometry."""
    def draws(bm, spec, rng, building_id, n=5):
        rng.random(1000)
        return {"n": n}

    def damage(seed):
        spec = masonry_gable()
        bm = built(spec)
        new, records = gp.damage_for_grade(bm, spec, 4, gp.pattern_rng(seed, 4), BID, secondary_probability=1.0)
        v, t = arr(new)[:2]
        new.free()
        return records, v, t

    monkeypatch.setitem(ems98.SECONDARY, ems98.MASONRY, [])  # no secondary damage
    before = [damage(seed) for seed in range(3)]
    monkeypatch.setitem(ems98.PATTERNS, "test_draws", ems98.Pattern(
        "test_draws", "draws numbers", (ems98.MASONRY,), (3,), {"n": ems98.Param(1, 9, "int", "", "")}))
    monkeypatch.setattr(ems98, "PATTERN_NAMES", ("test_draws",) + ems98.PATTERN_NAMES)
    monkeypatch.setitem(gp.FUNCTIONS, "test_draws", draws)
    monkeypatch.setitem(ems98.SECONDARY, ems98.MASONRY, [("test_draws", 1.0)])
    for seed, (records, v, t) in enumerate(before):
        records2, v2, t2 = damage(seed)
        assert [r["name"] for r in records2] == ["test_draws"] + [r["name"] for r in records]
        assert records2[1:] == records
        np.testing.assert_array_equal(v2, v)
        np.testing.assert_array_equal(t2, t)
