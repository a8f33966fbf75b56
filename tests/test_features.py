"""Per-point features: closed-form geometry, reference agreement, UTM invariance, degenerate rule."""
import math

import numpy as np
import pytest

from quakescan.change import _feature_kernels as K
from quakescan.change import _feature_reference as R
from quakescan.change import features as F
from quakescan.change._feature_reference import reference_features
from quakescan.change.features import FEATURES, compute_features
from quakescan.errors import QuakeScanError


def grid_plane(h=0.05, half=3.0):
    k = round(half / h)
    i, j = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    return np.column_stack([i.ravel() * h, j.ravel() * h, np.zeros(i.size)]), i.ravel(), j.ravel()


def test_plane_disc_closed_form():
    h, r = 0.05, 1.0 + 1e-6  # no lattice point on the sphere itself
    xyz, i, j = grid_plane(h)
    centre = np.flatnonzero((i == 0) & (j == 0))
    f = compute_features(xyz, r, core_points=xyz[centre] + [0, 0, 0])
    # lattice points of the disc: sum of i^2 over them, exact in integers
    k = int(r / h) + 1
    ii, jj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    inside = (ii * h) ** 2 + (jj * h) ** 2 <= r * r
    n = int(inside.sum())
    lam = float((ii[inside] ** 2).sum()) * h * h / n  # isotropic by the 90° symmetry
    assert f["num_neighbours"][0] == n
    assert f["eigenvalue1"][0] == pytest.approx(lam, rel=1e-12)
    assert f["eigenvalue2"][0] == pytest.approx(lam, rel=1e-12)
    assert abs(f["eigenvalue3"][0]) < 1e-15
    assert lam == pytest.approx(r * r / 4, rel=0.03)  # continuous disc: r^2/4
    assert f["planarity"][0] == pytest.approx(1.0, abs=1e-10)
    assert f["linearity"][0] == pytest.approx(0.0, abs=1e-10)
    assert f["sphericity"][0] == pytest.approx(0.0, abs=1e-12)
    assert f["eigenentropy"][0] == pytest.approx(math.log(2), rel=1e-10)  # 0 ln 0 := 0
    assert f["omnivariance"][0] == pytest.approx(0.0, abs=1e-5)
    assert abs(f["normal_z"][0]) == pytest.approx(1.0)
    assert f["verticality"][0] == pytest.approx(0.0, abs=1e-12)  # roof
    assert f["curvature"][0] == pytest.approx(0.0, abs=1e-9)
    assert f["surface_density"][0] == pytest.approx(n / (math.pi * r * r))
    assert f["volume_density"][0] == pytest.approx(n / (4 / 3 * math.pi * r ** 3))
    assert f["point_density"][0] == pytest.approx(n / (math.pi * r * r))  # flat: cylinder = sphere
    assert f["echo_ratio"][0] == pytest.approx(100.0)
    assert f["z_range"][0] == 0.0


def test_line_closed_form():
    h, m = 0.1, 10
    xyz = np.column_stack([np.arange(-50, 51) * h, np.zeros(101), np.zeros(101)])
    f = compute_features(xyz, m * h + 1e-9)
    c = 50
    assert f["num_neighbours"][c] == 2 * m + 1
    assert f["eigenvalue1"][c] == pytest.approx(h * h * m * (m + 1) / 3, rel=1e-12)
    assert f["linearity"][c] == pytest.approx(1.0)
    assert f["planarity"][c] == pytest.approx(0.0, abs=1e-12)
    # collinear: no plane, so no normal, verticality, roughness, curvature (the rule)
    for name in ("normal_x", "verticality", "roughness", "curvature"):
        assert np.isnan(f[name][c])
    assert np.isfinite(f["eigenentropy"][c]) and f["eigenentropy"][c] == pytest.approx(0.0, abs=1e-12)


def test_tilted_plane_normal_zrange_and_wall():
    xyz, _, _ = grid_plane(0.05, 2.5)
    t = math.radians(30)
    rot = np.array([[math.cos(t), 0, -math.sin(t)], [0, 1, 0], [math.sin(t), 0, math.cos(t)]])
    tilted = xyz @ rot.T
    q = np.array([[0.0, 0.0, 0.0]])
    f = compute_features(tilted, 1.0 + 1e-6, core_points=q)
    n = np.array([f["normal_x"][0], f["normal_y"][0], f["normal_z"][0]])
    assert np.allclose(n, rot @ [0, 0, 1], atol=1e-9)
    assert f["z_range"][0] == pytest.approx(2 * math.sin(t), rel=0.03)
    assert f["verticality"][0] == pytest.approx(1 - math.cos(t), abs=1e-9)
    assert f["roughness"][0] == pytest.approx(0.0, abs=1e-9)
    wall = xyz[:, [0, 2, 1]]  # the plane x-z: a wall facing y
    fw = compute_features(wall, 1.0, features=["verticality", "point_density", "surface_density"],
                          core_points=q)
    assert fw["verticality"][0] == pytest.approx(1.0)
    assert fw["point_density"][0] > fw["surface_density"][0]  # a wall piles up in the cylinder


def test_sphere_curvature_and_normal():
    rng = np.random.default_rng(3)
    R = 10.0
    n = 40000
    # uniform on the cap z > 0.85 R
    zc = rng.uniform(0.85 * R, R, n)
    phi = rng.uniform(0, 2 * math.pi, n)
    rho = np.sqrt(R * R - zc * zc)
    xyz = np.column_stack([rho * np.cos(phi), rho * np.sin(phi), zc])
    d = np.array([0.3, 0.2, 0.0])
    d[2] = math.sqrt(R * R - d @ d) * 0.999999
    q = (d / np.linalg.norm(d) * R)[None, :]
    f = compute_features(xyz, 1.5, core_points=q)
    assert f["curvature"][0] == pytest.approx(1 / R, rel=0.03)
    n_ = np.array([f["normal_x"][0], f["normal_y"][0], f["normal_z"][0]])
    assert np.allclose(n_, q[0] / R, atol=0.01)


def _same_normals(a, b):
    """Walls (n_z ~ 0) have no preferred sign: align the reference's normals to ours."""
    na = np.column_stack([a["normal_x"], a["normal_y"], a["normal_z"]])
    nb = np.column_stack([b["normal_x"], b["normal_y"], b["normal_z"]])
    flip = (np.abs(nb[:, 2]) < 1e-6) & (np.sum(na * nb, axis=1) < 0)
    for k, c in enumerate("xyz"):
        b[f"normal_{c}"] = np.where(flip, -nb[:, k], nb[:, k])


def test_reference_agrees_with_fast():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 8, (2500, 2))
    ground = np.column_stack([xy, 0.1 * xy[:, 0] + 0.02 * rng.normal(size=2500)])
    wall = np.column_stack([rng.uniform(0, 8, 800), np.full(800, 4.0), rng.uniform(0, 3, 800)])
    xyz = np.vstack([ground, wall, rng.uniform(0, 8, (300, 3)), ground[:5], [[20.0, 20, 20]]])
    a = compute_features(xyz, 1.0)
    b = reference_features(xyz, 1.0)
    _same_normals(a, b)
    for name in FEATURES:
        assert np.array_equal(np.isnan(a[name]), np.isnan(b[name])), name
        ok = ~np.isnan(b[name])
        np.testing.assert_allclose(a[name][ok], b[name][ok], rtol=1e-6, atol=1e-9, err_msg=name)
    core = rng.uniform(0, 8, (50, 3))
    a = compute_features(xyz, 1.0, core_points=core)
    b = reference_features(xyz, 1.0, core_points=core)
    _same_normals(a, b)
    for name in FEATURES:
        ok = ~np.isnan(b[name])
        assert np.array_equal(np.isnan(a[name]), ~ok), name
        np.testing.assert_allclose(a[name][ok], b[name][ok], rtol=1e-6, atol=1e-9, err_msg=name)


def test_utm_shift_invariance():
    rng = np.random.default_rng(1)
    # coordinates on a 1/1024 m lattice: exactly representable at UTM magnitudes too
    xyz = np.round(rng.uniform(0, 10, (3000, 3)) * [1, 1, 0.1] * 1024) / 1024
    shifted = xyz + [500000.0, 5000000.0, 200.0]
    a = compute_features(xyz, 1.5)
    b = compute_features(shifted, 1.5)
    for name in FEATURES:
        assert np.array_equal(np.isnan(a[name]), np.isnan(b[name])), name
        ok = ~np.isnan(a[name])
        np.testing.assert_allclose(b[name][ok], a[name][ok], rtol=1e-9, atol=1e-12, err_msg=name)


def test_degenerate_rule():
    two = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    f = compute_features(two, 1.0)
    assert np.all(f["num_neighbours"] == 2) and np.all(np.isfinite(f["surface_density"]))
    for name in set(FEATURES) - {"num_neighbours", "surface_density", "volume_density",
                                  "point_density", "echo_ratio"}:
        assert np.all(np.isnan(f[name])), name
    dup = np.repeat([[1.0, 2.0, 3.0]], 10, axis=0) + [500000.0, 5000000.0, 0]
    f = compute_features(dup, 1.0)
    assert np.all(f["num_neighbours"] == 10)
    for name in ("planarity", "eigenentropy", "normal_z", "roughness", "curvature"):
        assert np.all(np.isnan(f[name])), name
    assert np.all(f["z_range"] == 0)
    square = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]])
    f = compute_features(square, 2.0)
    for name in FEATURES:
        assert not np.any(np.isinf(f[name])), name
    assert np.all(np.isfinite(f["eigenentropy"])) and np.all(f["sphericity"] == 0)
    assert np.all(f["roughness"] == 0)


def test_only_requested_features(monkeypatch):
    xyz = np.random.default_rng(2).uniform(0, 5, (500, 3))
    seen = []
    orig = K.neighbourhoods

    def spy(*args):
        seen.append(args[25:30])  # do_eig, do_rough, do_z, do_curv, do_cyl
        return orig(*args)

    monkeypatch.setattr(K, "neighbourhoods", spy)
    f = compute_features(xyz, 1.0, features=["num_neighbours", "z_range"])
    assert set(f) == {"num_neighbours", "z_range"}
    assert seen == [(False, False, True, False, False)]  # no eigen, no cylinder count
    seen.clear()
    compute_features(xyz, 1.0, features=["planarity"])
    assert seen == [(True, False, False, False, False)]
    seen.clear()
    compute_features(xyz, 1.0, features=["point_density", "curvature"])
    assert seen == [(False, False, False, True, True)]  # one kernel run for both


def test_bad_input():
    with pytest.raises(QuakeScanError, match="unknown features"):
        compute_features(np.zeros((3, 3)), 1.0, features=["nope"])
    with pytest.raises(QuakeScanError, match="radius"):
        compute_features(np.zeros((3, 3)), -1.0)
    with pytest.raises(QuakeScanError, match=r"\(n, 3\)"):
        compute_features(np.zeros((3, 2)), 1.0)


def _local(xyz):
    o = xyz.min(axis=0)
    return [np.ascontiguousarray(xyz[:, k] - o[k]) for k in range(3)]


def _assert_same(a, b, names=FEATURES, rtol=1e-6, atol=1e-9):
    if "normal_x" in a:
        _same_normals(a, b)
    for name in names:
        assert np.array_equal(np.isnan(a[name]), np.isnan(b[name])), name
        ok = ~np.isnan(b[name])
        np.testing.assert_allclose(a[name][ok], b[name][ok], rtol=rtol, atol=atol, err_msg=name)


def test_default_pipeline_features():
    assert set(F.DEFAULT_PIPELINE_FEATURES) <= set(FEATURES)
    assert "curvature" in F.DEFAULT_PIPELINE_FEATURES and len(set(F.DEFAULT_PIPELINE_FEATURES)) == 13


def test_exact_fallback_planes_and_lines_at_utm():
    """Near-exact planes and collinear points at UTM coordinates take the two-pass path and
    give the reference's answers (sphericity 0 / finite eigenentropy on planes, NaN normals,
    roughness and curvature on lines)."""
    rng = np.random.default_rng(5)
    utm = np.array([500000.0, 5000000.0, 200.0])
    g, _, _ = grid_plane(0.1, 2.0)
    flat = g + utm  # exact horizontal plane: l3 = 0 exactly
    t = rng.uniform(-2, 2, 400)
    tilted = np.column_stack([t, rng.uniform(-2, 2, 400), np.zeros(400)])
    tilted[:, 2] = 0.3 * tilted[:, 0] - 0.2 * tilted[:, 1]  # a plane up to rounding at UTM
    tilted += utm + [10.0, 0, 0]
    line = utm + [0, 10.0, 0] + np.outer(np.linspace(-2, 2, 300), [1.0, 2.0, 0.5])
    for xyz in (flat, tilted, line):
        st = {}
        F._kernel_measures(_local(xyz), None, 1.0, FEATURES, None, stats=st)
        assert st["exact_share"] > 0.9
        a = compute_features(xyz, 1.0)
        b = reference_features(xyz, 1.0)
        # omnivariance = cbrt(e1 e2 e3) turns l3 ~ 1e-18 of UTM round-off into ~1e-6 that
        # no two eigen solvers share: only its size is compared on the rounded plane
        _assert_same(a, b, [f for f in FEATURES if f != "omnivariance"])
        assert np.nanmax(np.abs(a["omnivariance"] - b["omnivariance"])) < 1e-4
    f = compute_features(flat, 1.0)
    assert np.all(f["sphericity"] == 0) and np.all(np.isfinite(f["eigenentropy"]))
    f = compute_features(line, 1.0)
    for name in ("normal_z", "verticality", "roughness", "curvature"):
        assert np.all(np.isnan(f[name])), name
    assert np.all(np.isfinite(f["linearity"]))


def test_one_pass_is_used_on_noisy_surfaces_and_agrees():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 6, (3000, 2))
    xyz = np.column_stack([xy, 0.2 * np.sin(xy[:, 0]) + 0.01 * rng.normal(size=3000)]) + [500000.0, 5000000.0, 0]
    st = {}
    F._kernel_measures(_local(xyz), None, 1.0, FEATURES, None, stats=st)
    assert st["exact_share"] < 0.01
    _assert_same(compute_features(xyz, 1.0), reference_features(xyz, 1.0))


@pytest.mark.parametrize("cells", [1, 2, 3, 5])
def test_cell_size_gives_identical_neighbourhoods(cells, monkeypatch):
    """Finer grid columns (with per-query culling) find exactly the reference's neighbours,
    also on an integer lattice where many points lie exactly at distance r."""
    monkeypatch.setattr(F, "CELLS_PER_RADIUS", cells)
    rng = np.random.default_rng(7)
    lattice = np.stack(np.meshgrid(*[np.arange(7.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    blob = np.column_stack([rng.uniform(0, 9, (2000, 2)), rng.uniform(0, 1, 2000)])
    wall = np.column_stack([rng.uniform(0, 9, 600), np.full(600, 4.0), rng.uniform(0, 6, 600)])
    for xyz, r in ((lattice, 2.0), (np.vstack([blob, wall]), 1.3)):
        names = ("num_neighbours", "point_density", "echo_ratio", "z_rank", "z_range", "planarity", "roughness")
        a = compute_features(xyz, r, features=names)
        b = reference_features(xyz, r, features=names)
        for name in ("num_neighbours", "point_density", "z_rank", "z_range"):
            assert np.array_equal(a[name], b[name]), name
        _assert_same(a, b, names)
        core = np.vstack([rng.uniform(-2, 11, (200, 3)), [[-5.0, -5, -5], [20.0, 20, 20]]])
        a = compute_features(xyz, r, features=names, core_points=core)
        b = reference_features(xyz, r, features=names, core_points=core)
        for name in ("num_neighbours", "point_density", "z_rank", "z_range"):
            assert np.array_equal(a[name], b[name], equal_nan=True), name
        _assert_same(a, b, names)


def test_threads_give_identical_results():
    xyz = np.random.default_rng(8).uniform(0, 6, (4000, 3)) * [1, 1, 0.2]
    a = compute_features(xyz, 1.0, workers=1)
    b = compute_features(xyz, 1.0, workers=2)
    for name in FEATURES:
        assert np.array_equal(a[name], b[name], equal_nan=True), name


def test_points_on_the_sphere_counted_as_the_reference():
    """Points within an ulp of distance r are neighbours (the tolerance of 1e-9 r keeps such
    ties inside in any frame), points 1e-7 r beyond are not: kernel and reference agree."""
    rng = np.random.default_rng(9)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    q = np.array([[3.3, 4.4, 5.5]])
    r = 1.7
    xyz = np.vstack([q, q + r * u, q + r * (1 + 1e-7) * u[:3000], q + 2 * r * u[:500]])
    o = xyz.min(axis=0)
    d = (xyz - o) - (q - o)  # the reference's frame and test
    strict = np.sum(d * d, axis=1) <= r * r
    assert 1000 < (~strict[:20001]).sum() < 19000  # without the tolerance many would fall outside
    want = 20001
    assert reference_features(xyz, r, ("num_neighbours",), core_points=q)["num_neighbours"][0] == want
    for names in (("num_neighbours",), ("planarity", "z_range"), ("curvature", "point_density")):
        a = compute_features(xyz, r, features=(*names, "num_neighbours"), core_points=q)
        assert a["num_neighbours"][0] == want
        f = compute_features(xyz, r, features=(*names, "num_neighbours"))
        assert f["num_neighbours"][0] == want  # the point itself: d = 0, inside either way




def test_query_index_equals_the_full_cloud_subset():
    """Features at some of the cloud's points (the pipeline's building points) equal the
    same points' features computed for the whole cloud, fast and reference."""
    rng = np.random.default_rng(4)
    xyz = np.column_stack([rng.uniform(0, 8, 6000), rng.uniform(0, 8, 6000), rng.normal(0, 0.05, 6000)])
    xyz[:2000, 2] += 3.0 * (xyz[:2000, 0] > 4)  # a step: some varied neighbourhoods
    xyz += [500000.0, 5000000.0, 10.0]
    pick = rng.choice(6000, 700, replace=False)
    names = ("planarity", "roughness", "z_rank", "point_density", "curvature", "num_neighbours")
    full = compute_features(xyz, 1.0, names)
    part = compute_features(xyz, 1.0, names, query_index=pick)
    ref = reference_features(xyz, 1.0, names, query_index=pick)
    for name in names:
        np.testing.assert_array_equal(part[name], full[name][pick])
        np.testing.assert_allclose(part[name], ref[name], rtol=1e-9, atol=1e-12, equal_nan=True)
    with pytest.raises(F.FeatureError, match="query_index"):
        compute_features(xyz, 1.0, names, query_index=[6000])


def test_feature_names_and_order_are_unchanged():
    """Models, cached training tables and the change descriptors name their columns in this
    order: the registry must keep it (new features go at the end)."""
    assert FEATURES == (
        "linearity", "planarity", "omnivariance", "surface_variation", "curvature", "point_density",
        "num_neighbours", "surface_density", "volume_density", "sphericity", "verticality",
        "eigenentropy", "anisotropy", "eigenvalue1", "eigenvalue2", "eigenvalue3", "eigenvalue_sum",
        "roughness", "z_rank", "z_range", "normal_x", "normal_y", "normal_z", "echo_ratio")
    # the result's order (compiled eigen ratios first, by code) is what feature_changes and
    # the change descriptors list
    got = list(compute_features(np.random.default_rng(0).uniform(0, 3, (60, 3)), 1.0))
    assert got[:8] == ["linearity", "planarity", "sphericity", "anisotropy", "surface_variation",
                       "omnivariance", "eigenentropy", "eigenvalue_sum"]
    assert got[8:] == [f for f in FEATURES if F.REGISTRY[f].compiled is None]


def test_registry_declarations_are_consistent():
    codes = [f.compiled for f in F.REGISTRY.values() if f.compiled is not None]
    assert sorted(codes) == list(range(8))  # one formula per branch of the compiled pass
    for f in F.REGISTRY.values():
        assert f.needs and f.needs <= set(F.MEASURES), f.name
        if f.category == "eigen":
            assert f.needs == {"eigen"}, f.name
        if f.compiled is not None:
            assert f.category == "eigen", f.name  # the compiled pass reads only eigenvalues
    assert F.kernel_switches(["eigenvalue1"]) == (True, False, False, False, False)
    assert F.kernel_switches(["normal_z", "echo_ratio", "z_rank"]) == (True, False, True, False, True)
    assert F.kernel_switches(["num_neighbours"]) == (False,) * 5


def test_a_feature_from_existing_measures_is_one_registry_entry(monkeypatch):
    """The documented way to add a feature: one `Feature`; kernel, reference, name check and
    NaN rule follow from its declaration."""
    flatness = F.Feature("flatness", "eigen", frozenset({"eigen"}), lambda q, r: q.lam[:, 2] / q.lam[:, 1])
    monkeypatch.setitem(F.REGISTRY, "flatness", flatness)
    rng = np.random.default_rng(11)
    xyz = np.vstack([rng.uniform(0, 4, (800, 3)) * [1, 1, 0.05], [[30.0, 30, 30]]])
    a = compute_features(xyz, 1.0, ("flatness", "eigenvalue2", "eigenvalue3"))
    b = reference_features(xyz, 1.0, ("flatness",))
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(a["flatness"], a["eigenvalue3"] / a["eigenvalue2"])
    assert np.isnan(a["flatness"][-1])  # an isolated point: undefined, as every eigen feature
    _assert_same(a, b, ["flatness"])


def test_compiled_eigen_features_match_their_definitions():
    """`_feature_kernels.eigen_features` against the registry's numpy formulas, with NaN
    rows (degenerate neighbourhoods), exact planes (l3 = 0) and lines (l2 = l3 = 0)."""
    rng = np.random.default_rng(12)
    lam = np.sort(rng.exponential(1.0, (2000, 3)), axis=1)[:, ::-1] * rng.uniform(1e-4, 10, (2000, 1))
    lam[:50] = np.nan
    lam[50:100, 2] = 0.0
    lam[100:150, 1:] = 0.0
    lam = np.ascontiguousarray(lam)
    codes = np.arange(8, dtype=np.int64)
    fast, ref = np.empty((8, len(lam))), np.empty((8, len(lam)))
    K.eigen_features(lam, codes, fast)
    R.eigen_features(lam, codes, ref)
    assert np.array_equal(np.isnan(fast), np.isnan(ref))
    assert not np.isinf(fast).any()
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-15)


def test_grid_keys_and_gather_match_the_reference():
    rng = np.random.default_rng(13)
    x, y, z = (np.ascontiguousarray(rng.uniform(0, 20, 5000) * s) for s in (1.0, 0.7, 0.3))
    s, q, nxc, nyc, zbits = 0.5, 0.5 / 64, 40, 28, 30
    a, b = np.empty(5000, np.int64), np.empty(5000, np.int64)
    K.grid_keys(x, y, z, 0.0, 0.0, s, q, nxc, nyc, zbits, a)
    R.grid_keys(x, y, z, 0.0, 0.0, s, q, nxc, nyc, zbits, b)
    np.testing.assert_array_equal(a, b)
    order = np.argsort(a)
    fast, ref = [np.empty(5000) for _ in range(3)], [np.empty(5000) for _ in range(3)]
    K.gather(x, y, z, order, *fast)
    R.gather(x, y, z, order, *ref)
    for u, v in zip(fast, ref):
        np.testing.assert_array_equal(u, v)
