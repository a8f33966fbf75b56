"""Robust change-feature selection: closed-form relative changes, ULS == DIM gives zero
difference, a small simulated ULS vs DIM collapse scene end to end, the comparison with the
paper's set, several demolition stages, voxel thinning, the CLI and bad input."""
import csv
import json
import math
import shutil

import numpy as np
import pytest

from quakescan.acquisition.dim_settings import preset_dim
from quakescan.acquisition.survey import preset
from quakescan.cli import main
from quakescan.formats.pointcloud import Epoch
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city
from quakescan.studies.robustness.report import write_report
from quakescan.studies.robustness.run import run_experiment
from quakescan.studies.robustness.selection import (
    NORMAL,
    PAPER_SET,
    REPORT_FEATURES,
    THRESHOLDS,
    RobustnessError,
    RobustnessResult,
    compare_with_paper,
    normal_change,
    quiet_features,
    relative_change,
    relative_changes,
    robustness,
    thin,
    thin_index,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _box_points(rng, spacing=0.25, noise=0.01):
    """Ground (id 0) and a 6 x 6 x 4 m box (id 1: roof and four walls), noisy."""
    g = np.arange(-6.0, 12.0 + 1e-9, spacing)
    gx, gy = np.meshgrid(g, g)
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    ground = ground[~((ground[:, 0] >= 0) & (ground[:, 0] <= 6) & (ground[:, 1] >= 0) & (ground[:, 1] <= 6))]
    s = np.arange(0.0, 6.0 + 1e-9, spacing)
    h = np.arange(0.0, 4.0 + 1e-9, spacing)
    rx, ry = np.meshgrid(s, s)
    roof = np.column_stack([rx.ravel(), ry.ravel(), np.full(rx.size, 4.0)])
    a, z = np.meshgrid(s, h)
    a, z = a.ravel(), z.ravel()
    walls = np.concatenate([np.column_stack([a, np.zeros_like(a), z]), np.column_stack([a, np.full_like(a, 6.0), z]),
                            np.column_stack([np.zeros_like(a), a, z]), np.column_stack([np.full_like(a, 6.0), a, z])])
    bld = np.concatenate([roof, walls])
    xyz = np.concatenate([ground, bld]) + rng.normal(0, noise, (len(ground) + len(bld), 3))
    ids = np.concatenate([np.zeros(len(ground), np.int64), np.ones(len(bld), np.int64)])
    return xyz, ids


def _epoch(xyz, ids, source):
    return Epoch(xyz=np.asarray(xyz, float), origin=np.zeros(3), classification=np.zeros(len(xyz), np.uint8),
                 building_id=np.asarray(ids, np.int64), source=source)


@pytest.fixture(scope="module")
def box_pair():
    rng = np.random.default_rng(0)
    xyz, ids = _box_points(rng)
    return _epoch(xyz, ids, "pre.las"), xyz, ids


# (1) closed form ------------------------------------------------------------------------------

def test_relative_change_definition():
    # |median| well above the IQR: scale = |median pre|
    assert relative_change([10.0, 10.0, 10.0], [15.0, 15.0, 15.0]) == pytest.approx(50.0)
    assert relative_change([-4.0, -4.0, -4.0], [-2.0, -2.0, -2.0]) == pytest.approx(50.0)  # |median| as scale
    # NaN pairs are dropped on both sides
    assert relative_change([10.0, np.nan, 10.0, 10.0], [12.0, 1e9, np.nan, 12.0]) == pytest.approx(20.0)
    assert math.isnan(relative_change([np.nan], [1.0]))
    # centred at 0: the IQR is the scale (median 0, IQR 1 -> a shift of 0.5 is 50 %)
    pre = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    q1, q3 = np.percentile(pre, [25, 75])
    assert relative_change(pre, pre + 0.5) == pytest.approx(100 * 0.5 / (q3 - q1))
    # constant zero feature: 0 % if unchanged, NaN (never robust) if changed
    assert relative_change([0.0, 0.0], [0.0, 0.0]) == 0.0
    assert math.isnan(relative_change([0.0, 0.0], [1.0, 1.0]))


def test_normal_change_angle_sign_free():
    n = np.array([[0.0, 0.0, 1.0]] * 5)
    assert normal_change(n, -n) == pytest.approx(0.0)
    assert normal_change(n, np.array([[1.0, 0.0, 0.0]] * 5)) == pytest.approx(100.0)
    c = math.cos(math.radians(45)), math.sin(math.radians(45))
    assert normal_change(n, np.array([[c[1], 0.0, c[0]]] * 5)) == pytest.approx(50.0)


def test_identical_epochs_change_nothing(box_pair):
    pre, xyz, ids = box_pair
    post = _epoch(xyz.copy(), ids, "post.las")
    ch = relative_changes(pre, post, 1.0, workers=2)
    assert set(ch) == set(REPORT_FEATURES) and NORMAL in ch and "normal_x" not in ch
    for f, v in ch.items():
        assert v == pytest.approx(0.0, abs=1e-9), f


def test_duplicated_points_double_the_counts(box_pair):
    pre, xyz, ids = box_pair
    post = _epoch(np.concatenate([xyz, xyz]), np.concatenate([ids, ids]), "post.las")
    ch = relative_changes(pre, post, 1.0, workers=2,
                          features=("num_neighbours", "surface_density", "volume_density", "point_density",
                                    "planarity", "linearity", "eigenvalue_sum", "normal_x"))
    for f in ("num_neighbours", "surface_density", "volume_density", "point_density"):
        assert ch[f] == pytest.approx(100.0), f
    for f in ("planarity", "linearity", "eigenvalue_sum", NORMAL):  # population covariance: unchanged
        assert ch[f] == pytest.approx(0.0, abs=1e-6), f


# (2) the same pair as ULS and DIM ----------------------------------------------------------------

def test_same_pair_is_robust_everywhere(box_pair):
    pre, xyz, ids = box_pair
    lower = xyz.copy()
    lower[(ids > 0) & (lower[:, 2] > 3.0), 2] -= 1.0  # the roof drops by a metre
    post = _epoch(lower, ids, "post.las")
    res = robustness(pre, post, pre, post, radii=(2.0, 1.0), workers=2)
    assert res.radii == [1.0, 2.0]
    for r in res.radii:
        for f in res.features:
            assert res.difference[r][f] == 0.0 or math.isnan(res.uls[r][f]), (r, f)
    finite_everywhere = [f for f in res.features if all(math.isfinite(res.uls[r][f]) for r in res.radii)]
    assert res.robust == [f for f in res.features if math.isfinite(res.difference[1.0][f])]
    assert len(finite_everywhere) >= len(res.features) - 1
    # tie in count and in mean difference (0): the smallest radius
    assert res.best_radius == 1.0
    assert all(c == len(res.robust) for c in res.counts_by_threshold.values())
    # something did change
    assert abs(res.uls[1.0]["z_range"]) > 1.0


def test_best_radius_rule():
    feats = ["a", "b", "c"]
    d = {1.0: {"a": 1.0, "b": 20.0, "c": 30.0},   # 1 robust
         2.0: {"a": 5.0, "b": 9.0, "c": 40.0},    # 2 robust, mean 18
         3.0: {"a": 2.0, "b": 8.0, "c": 35.0}}    # 2 robust, mean 15 -> best
    from quakescan.studies.robustness import selection as R

    def key(r):
        n = sum(R.within(d[r][f], 10.0) for f in feats)
        return (-n, float(np.mean(list(d[r].values()))), r)
    assert min(d, key=key) == 3.0


# (3) simulated ULS vs DIM of a small collapse scene --------------------------------------------

@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    root = tmp_path_factory.mktemp("rob")
    pre = box_city(rows=1, cols=2, footprint=10.0, street=8.0, height=9.0, margin=12.0)
    post = box_city(rows=1, cols=2, footprint=10.0, street=8.0, height=(9.0, 4.0), margin=12.0,
                    epoch="post", grades=[0, 5])
    write_scene(pre, root / "pre")
    write_scene(post, root / "post")
    uls = preset("paper").replace(pulse_rate_hz=50_000.0)
    dim = preset_dim("paper").replace(margin_m=40.0, point_step_px=16.0)
    calls = []
    res = run_experiment(root / "pre", root / "post", root / "out", radii=(1.0, 2.0), seed=1, workers=2,
                         survey=uls, photo_survey=dim, sample=3000, progress=lambda d, t: calls.append((d, t)))
    return root, res, calls, (uls, dim)


def test_simulated_experiment(experiment):
    root, res, calls, _ = experiment
    assert res.radii == [1.0, 2.0] and res.best_radius in res.radii
    assert calls[-1] == (8, 8)
    finite = [res.difference[r][f] for r in res.radii for f in res.features if math.isfinite(res.difference[r][f])]
    assert len(finite) >= 0.8 * len(res.radii) * len(res.features)
    # a lowered building: some features change clearly on both sources
    for r in res.radii:
        assert max(min(abs(res.uls[r][f]), abs(res.dim[r][f])) for f in res.features) > 5.0
    counts = [res.counts_by_threshold[t] for t in THRESHOLDS]
    assert counts == sorted(counts) and counts[int(res.threshold_pct)] == len(res.robust)
    assert set(res.robust) <= set(res.features)
    out = root / "out"
    for name in ("features_vs_threshold.png", "difference_heatmap.png"):
        assert (out / name).read_bytes()[:8] == PNG
    js = json.loads((out / "robustness.json").read_text())
    assert js["best_radius_m"] == res.best_radius and js["robust"] == res.robust
    rows = list(csv.DictReader((out / "robustness.csv").open()))
    assert len(rows) == len(res.radii) * len(res.features)
    assert "Comparison with the paper" in (out / "README.md").read_text()
    assert not list(out.rglob("*.part*"))
    assert sorted(p.name for p in (out / "clouds").glob("*.las")) == ["dim_post.las", "dim_pre.las",
                                                                       "uls_post.las", "uls_pre.las"]
    # each beside the record of what made it (quakescan.acquisition.acquire): what a rerun compares against
    assert sorted(p.name for p in (out / "clouds").iterdir() if not p.name.endswith(".las")) == sorted(
        f"{c}.las.acquisition.json" for c in ("dim_post", "dim_pre", "uls_post", "uls_pre"))


def test_experiment_resumes_from_existing_clouds(experiment, monkeypatch):
    root, res, _, (uls, dim) = experiment
    import quakescan.acquisition.dim
    import quakescan.acquisition.scan

    def boom(*a, **k):
        raise AssertionError("rescanned although the cloud exists")
    monkeypatch.setattr(quakescan.acquisition.scan, "scan", boom)
    monkeypatch.setattr(quakescan.acquisition.dim, "simulate_dim", boom)
    stamps = {p: p.stat().st_mtime_ns for p in (root / "out" / "clouds").glob("*.las")}
    # same out_dir: every cloud is kept, the numbers are reproduced
    again = run_experiment(root / "pre", root / "post", root / "out", radii=(1.0, 2.0), seed=1, workers=2,
                           survey=uls, photo_survey=dim, sample=3000)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # however the simulators are reached
    assert again.difference == res.difference or all(
        (math.isnan(a) and math.isnan(b)) or a == b
        for r in res.radii for a, b in zip(again.difference[r].values(), res.difference[r].values()))


def test_clouds_of_another_survey_are_made_again_never_reused(experiment, tmp_path):
    """The bug this guards against: a clouds/ folder of a run with another survey was reused
    because its files existed, mixing two experiments into one table."""
    root, _, _, (uls, dim) = experiment
    clouds = tmp_path / "out" / "clouds"
    shutil.copytree(root / "out" / "clouds", clouds)
    before = {p.name: p.read_bytes() for p in clouds.glob("*.las")}
    other = uls.replace(pulse_rate_hz=40_000.0)
    run_experiment(root / "pre", root / "post", tmp_path / "out", radii=(1.0,), seed=1, workers=2,
                   survey=other, photo_survey=dim, sample=1000)
    after = {p.name: p.read_bytes() for p in clouds.glob("*.las")}
    assert sorted(n for n in before if after[n] != before[n]) == ["uls_post.las", "uls_pre.las"]  # DIM: the same
    for name in ("uls_pre", "uls_post"):
        record = json.loads((clouds / f"{name}.las.acquisition.json").read_text())
        assert record["acquisition"]["settings"]["pulse_rate_hz"] == 40_000.0


# (4) comparison with the paper ---------------------------------------------------------------------

def _result(robust, features=REPORT_FEATURES):
    d = {1.0: {f: (0.0 if f in robust else 50.0) for f in features}}
    return RobustnessResult(radii=[1.0], features=list(features), uls=d, dim=d, difference=d, best_radius=1.0,
                            threshold_pct=10.0, robust=list(robust), counts_by_threshold={})


def test_compare_with_paper():
    cmp = compare_with_paper(_result(list(PAPER_SET)))
    assert cmp["both"] == sorted(PAPER_SET) and not cmp["only_ours"] and not cmp["only_paper"]
    assert cmp["agreement"] == 1.0 and len(PAPER_SET) == 10 and NORMAL in PAPER_SET
    cmp = compare_with_paper(_result(["planarity", "curvature", "echo_ratio"]))
    assert cmp["both"] == ["planarity"]
    assert cmp["only_ours"] == ["curvature", "echo_ratio"]
    assert set(cmp["only_paper"]) == set(PAPER_SET) - {"planarity"}
    assert cmp["agreement"] == pytest.approx(1 / 12, abs=1e-4)
    # features not looked at are not counted against us
    cmp = compare_with_paper(_result(["planarity"], features=("planarity", "curvature")))
    assert cmp["only_paper"] == [] and "roughness" in cmp["not_tested"]


def test_quiet_features_agree_on_no_change():
    res = _result(["planarity", "curvature"])
    assert quiet_features(res) == ["planarity", "curvature"]  # 0 % on both sources
    res.uls = {1.0: dict(res.uls[1.0], curvature=30.0)}
    res.dim = {1.0: dict(res.dim[1.0], curvature=25.0)}
    res.difference = {1.0: dict(res.difference[1.0], curvature=5.0)}
    assert quiet_features(res) == ["planarity"]  # curvature is robust and does change


def test_write_report_minimal(tmp_path):
    res = _result(["planarity"])
    res.counts_by_threshold = {t: 1 for t in THRESHOLDS}
    write_report(res, tmp_path / "rep")
    assert (tmp_path / "rep" / "features_vs_threshold.png").read_bytes()[:8] == PNG


# (5) bad input ---------------------------------------------------------------------------------------

def test_no_building_points_names_the_file(box_pair):
    pre, xyz, ids = box_pair
    ground_only = _epoch(xyz, np.zeros_like(ids), "/data/post_ground.las")
    with pytest.raises(RobustnessError, match="post_ground.las.*no building points"):
        relative_changes(pre, ground_only, 1.0)
    with pytest.raises(RobustnessError, match="post_ground.las"):
        robustness(pre, pre, ground_only, pre, radii=(1.0,))
    no_ids = Epoch(xyz=xyz, origin=np.zeros(3), classification=np.zeros(len(xyz), np.uint8), source="x.las")
    with pytest.raises(RobustnessError, match="x.las.*building_id"):
        relative_changes(no_ids, pre, 1.0)
    with pytest.raises(RobustnessError, match="radius"):
        relative_changes(pre, pre, -1.0)
    with pytest.raises(RobustnessError, match="unknown feature"):
        relative_changes(pre, pre, 1.0, features=("bogus",))


# (6) several stages ---------------------------------------------------------------------------------

def test_stages_robust_only_when_every_stage_agrees(box_pair):
    pre, xyz, ids = box_pair
    lower = xyz.copy()
    lower[(ids > 0) & (lower[:, 2] > 3.0), 2] -= 1.0
    stage1 = _epoch(lower, ids, "post1.las")  # the same change on both sources: all agree
    unchanged = _epoch(xyz.copy(), ids, "post2_uls.las")
    doubled = _epoch(np.concatenate([xyz, xyz]), np.concatenate([ids, ids]), "post2_dim.las")
    feats = ("num_neighbours", "planarity", "eigenvalue_sum", "normal_x")
    res = robustness(pre, [stage1, unchanged], pre, [stage1, doubled], radii=(1.0,), features=feats, workers=2)
    assert res.stages == ["post1", "post2"]
    # stage 1 agrees everywhere, stage 2 only on the shape features (duplicates change counts only)
    assert res.stage_robust_at("post1", 1.0) == list(res.features)
    assert "num_neighbours" not in res.stage_robust_at("post2", 1.0)
    assert res.stage_difference["post2"][1.0]["num_neighbours"] == pytest.approx(100.0)
    assert res.stage_difference["post1"][1.0]["num_neighbours"] == 0.0
    # robust = robust at every stage; the difference is the largest over the stages
    assert "num_neighbours" not in res.robust and {"planarity", "eigenvalue_sum", NORMAL} <= set(res.robust)
    assert res.difference[1.0]["num_neighbours"] == pytest.approx(100.0)
    assert res.deciding_stage[1.0]["num_neighbours"] == "post2"
    for f in res.features:  # uls/dim are the deciding stage's values: difference = |uls - dim|
        assert res.difference[1.0][f] == pytest.approx(abs(res.uls[1.0][f] - res.dim[1.0][f]))
        assert res.difference[1.0][f] == pytest.approx(max(res.stage_difference[s][1.0][f] for s in res.stages))
    js = res.to_json()
    assert set(js["per_stage"]) == {"post1", "post2"}
    assert "num_neighbours" in js["per_stage"]["post1"]["robust_by_radius"]["1"]
    assert "num_neighbours" not in js["per_stage"]["post2"]["robust_by_radius"]["1"]
    # one stage given as a list is the two-epoch design
    one = robustness(pre, [stage1], pre, stage1, radii=(1.0,), features=feats, workers=2)
    assert one.stages == ["post"] and one.robust == list(one.features)
    with pytest.raises(RobustnessError, match="2 ULS post-event epochs but 1 DIM"):
        robustness(pre, [stage1, unchanged], pre, [stage1], radii=(1.0,), features=feats)


# (7) thinning ------------------------------------------------------------------------------------------

def _grid(step, n, z=0.05):
    g = (np.arange(n) + 0.5) * step  # cell-centred: no point on a voxel boundary
    gx, gy = np.meshgrid(g, g)
    return np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])


def test_thinning_gives_the_spacing_on_a_grid():
    # a 4 x 4 m plane sampled every 0.025 m (1600 pts/m^2) inside one voxel layer: exactly one
    # point per 0.1 m cell stays, 100 pts/m^2, i.e. spacing sqrt(area / n) = 0.1 m
    xyz = _grid(0.025, 160)
    idx = thin_index(xyz, 0.1, seed=3)
    assert len(idx) == 40 * 40 and np.all(np.diff(idx) > 0)
    cells = np.floor(xyz[idx] / 0.1).astype(int)
    assert len(np.unique(cells, axis=0)) == len(idx)  # one per cell, every cell kept
    assert math.sqrt(16.0 / len(idx)) == pytest.approx(0.1)
    # deterministic for a seed, another seed draws other points of the same cells
    assert np.array_equal(idx, thin_index(xyz, 0.1, seed=3))
    other = thin_index(xyz, 0.1, seed=4)
    assert len(other) == len(idx) and not np.array_equal(other, idx)
    # a sparser input (0.2 m grid) is left alone; 0.05 m keeps 2 x 2 of the 0.025 m grid's 4 x 4 per cell
    sparse = _grid(0.2, 20)
    assert len(thin_index(sparse, 0.1)) == len(sparse)
    assert len(thin_index(xyz, 0.05)) == 80 * 80


def test_thin_keeps_attributes(box_pair):
    pre, _, _ = box_pair
    t = thin(pre, 0.5, seed=1)
    assert 0 < len(t) < len(pre) and t.source == pre.source
    idx = thin_index(pre.xyz, 0.5, seed=1)
    assert np.array_equal(t.xyz, pre.xyz[idx]) and np.array_equal(t.building_id, pre.building_id[idx])
    assert thin(pre, None) is pre
    for bad in (0, -0.1, float("nan"), "x"):
        with pytest.raises(RobustnessError, match="spacing"):
            thin(pre, bad)
    res = robustness(pre, pre, pre, pre, radii=(1.0,), features=("planarity",), spacing=0.5, workers=2)
    assert res.spacing_m == 0.5 and res.clouds["uls_pre"]["points"] == len(t)
    assert res.clouds["uls_pre"]["points_in"] == len(pre)


# (8) command line ----------------------------------------------------------------------------------------

def test_cli_two_stages_and_bad_spacing(experiment, tmp_path, capsys):
    root, _, _, _ = experiment
    out = tmp_path / "cli"  # stage 2 = an unchanged rescan of the pre-event scene
    args = ["robustness", "--pre", str(root / "pre"), "--post", str(root / "post"), str(root / "pre"), "-o", str(out),
            "--radii", "1,2", "--threads", "2", "--sample", "2000"]
    assert main(args + ["--spacing", "0.2"]) == 0
    assert "over 2 stages" in capsys.readouterr().out
    js = json.loads((out / "robustness.json").read_text())
    assert js["stages"] == ["post1", "post2"] and js["spacing_m"] == 0.2
    assert set(js["per_stage"]) == {"post1", "post2"}
    rows = list(csv.DictReader((out / "robustness_stages.csv").open()))
    assert {r["stage"] for r in rows} == {"post1", "post2"} and len(rows) == 2 * 2 * len(REPORT_FEATURES)
    assert "robust at post2" in (out / "README.md").read_text()
    for bad in ("-0.5", "abc", "0"):
        assert main(args + ["--spacing", bad]) == 2
        err = capsys.readouterr().err
        assert f"--spacing {bad}" in err and "spacing must be" in err
