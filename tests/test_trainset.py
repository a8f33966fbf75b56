"""The transfer training set (core/learning/trainset.py) and the shipped model's recipe (core/learning/default_model.py)."""
import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

from quakescan.learning.default_model import (TABLE_SETTINGS, TRANSFER_SETTINGS, data_limits, fit_default_model,
                                              model_columns, select_classifier, size_limit)
from quakescan.learning.trainset import SENSOR_PAIRS, TrainingPlan, TrainingSetError, build, default_plan


def test_the_full_plan_varies_buildings_sensors_and_damage_context():
    plan = default_plan(0, "full", small=True)
    planned = 0
    sizes = {c.name: (c.buildings or 15) for c in plan.cities}
    for p in plan.pairs:
        planned += sizes[p.city]
    assert planned >= 2500  # "thousands of buildings"
    combos = {(p.pre["kind"], p.post["kind"]) for p in plan.pairs}
    assert combos == set(SENSOR_PAIRS)  # every same-source and cross-source combination
    assert {c.source for c in plan.cities} == {"generic", "region", "rotterdam", "small"}
    assert any(p.post_scene == "pre" for p in plan.pairs)  # no-change pairs of the paper design
    mixed = [c for c in plan.cities if c.dataset == "mixed"]
    assert all(c.grade_mix[0] > 0 and c.grade_mix[5] > 0 for c in mixed)  # undamaged beside collapses
    # every acquisition drawn at random: no two ULS acquisitions alike
    uls = [json.dumps(a, sort_keys=True) for p in plan.pairs for a in (p.pre, p.post) if a["kind"] == "uls"]
    assert len(set(uls)) == len(uls)
    text = json.dumps(plan.to_json()).lower()
    assert "zurich" not in text  # reserved for evaluation
    assert json.dumps(default_plan(0, "full", small=True).to_json()) == json.dumps(plan.to_json())
    assert json.dumps(default_plan(1, "full", small=True).to_json()) != json.dumps(plan.to_json())


def test_plan_sizes_nest_and_name_each_city_once():
    quick, full, large = (default_plan(0, z, small=True) for z in ("quick", "full", "large"))
    for plan in (quick, full, large):
        names = [c.name for c in plan.cities]
        assert len(names) == len(set(names))
    assert len(quick.cities) == 2 and len(full.cities) == 18 and len(large.cities) == 32
    # large = full's cities and pairs (same draws, so a built full set is reused) and more
    assert [asdict(c) for c in large.cities[:18]] == [asdict(c) for c in full.cities]
    assert [asdict(p) for p in large.pairs[:56]] == [asdict(p) for p in full.pairs]


def test_small_building_cities_are_added_after_the_others_and_acquired_from_the_air_first():
    without, full = default_plan(0, "full"), default_plan(0, "full", small=True)
    # the plan without them is the one the earlier models were trained on (same draws)
    assert [asdict(p) for p in full.pairs[:len(without.pairs)]] == [asdict(p) for p in without.pairs]
    extra = [c for c in full.cities if c.source == "small"]
    assert [c.name for c in extra] == ["small_m0", "small_m1"] and all(c.buildings == 64 for c in extra)
    pairs = [p for p in full.pairs if p.city.startswith("small_")]
    assert len(pairs) == 6 and all(p.pre["kind"] == "als" for p in pairs)
    assert {p.post["kind"] for p in pairs} == {"als", "uls", "dim"}
    assert not any(c.source == "small" for c in default_plan(0, "quick", small=True).cities)


def test_physics_twins_copy_their_cities_and_acquisitions_and_change_nothing_else():
    from quakescan.learning.trainset import PHYSICS_TWINS, city_job

    full, both = default_plan(0, "full"), default_plan(0, "full", damage="both")
    # the patterns plan is what it was (no damage key in its records: old manifests read the same)
    assert "damage" not in json.dumps(full.to_json())
    assert both.to_json()["cities"][:len(full.cities)] == full.to_json()["cities"]
    assert [asdict(p) for p in both.pairs[:len(full.pairs)]] == [asdict(p) for p in full.pairs]
    twins = both.cities[len(full.cities):]
    assert sorted(c.name for c in twins) == sorted(f"{n}-physics" for n in PHYSICS_TWINS["full"])
    base = {c.name: c for c in full.cities}
    for t in twins:
        b = base[t.name.removesuffix("-physics")]
        assert asdict(t) == {**asdict(b), "name": t.name, "damage": "physics"}
        folder = Path("scenes") / "city"
        assert city_job(t, folder) == replace(city_job(b, folder), damage="physics")
        assert (city_job(b, folder).damage, city_job(b, folder).details) == ("patterns", "none")
        # acquired exactly as the twin: same acquisitions and seeds, pair for pair
        strip = [(p.post_scene, p.pre, p.post, p.pre_seed, p.post_seed) for p in both.pairs]
        assert ([s for p, s in zip(both.pairs, strip) if p.city == t.name]
                == [s for p, s in zip(both.pairs, strip) if p.city == b.name])
    assert both.name == "default-full+physics"
    assert default_plan(0, "full", "realistic", "both").to_json() == default_plan(0, "full", "realistic").to_json()
    with pytest.raises(TrainingSetError, match="damage must be one of"):
        default_plan(0, "full", damage="physics")


def test_a_physics_twin_is_held_out_with_its_city(tmp_path, monkeypatch):
    """Rows of a twin take its city's index, so city-held-out cross-validation keeps both
    versions of a building on one side (as a realistic twin's do)."""
    from tests.trainset_fakes import finished_tables

    plan = finished_tables(tmp_path, monkeypatch, default_plan(0, "quick", damage="both"), TABLE_SETTINGS)
    table = build(tmp_path, plan, TABLE_SETTINGS)
    names = [plan.cities[i].name for i in table.city]
    physics = np.array([table.pairs[i].startswith("generic_m0-physics.") for i in table.pair])
    assert physics.sum() == 4 and set(np.array(names)[physics]) == {"generic_m0"}


def test_data_limits_count_a_physics_twin_s_acquisitions_once():
    """A twin repeats its city's acquisitions: the density limit is that of the table without
    them (here the twins' dense rows would move the 1st percentile)."""
    from quakescan.learning.default_model import without_twins
    from quakescan.learning.trainset import TransferTable

    n = 200
    density = np.column_stack([np.linspace(1.0, 50.0, n), np.full(n, 60.0)])
    names = list(TABLE_SETTINGS.descriptor_names())
    x = np.zeros((n + 100, len(names)))
    table = TransferTable(x=x, y=np.zeros(n + 100, np.int64), names=names, city=np.zeros(n + 100, np.int64),
                          pair=np.r_[np.zeros(n, np.int64), np.ones(100, np.int64)],
                          building_id=np.arange(n + 100), density=np.vstack([density, np.full((100, 2), 80.0)]),
                          cities=["generic_m0", "generic_m0-physics"],
                          pairs=["generic_m0.post.uls-uls.1-2", "generic_m0-physics.post.uls-uls.1-2"],
                          sensors=["uls-uls", "uls-uls"])
    own = without_twins(table)
    assert len(own.y) == n and own.density.max() == 60.0
    assert data_limits(own)[0] == np.floor(np.quantile(density[:, 0], 0.01) * 10) / 10 == 1.4
    assert data_limits(table)[0] > data_limits(own)[0]  # what counting the twins would have done


def test_a_plan_naming_a_city_it_lacks_is_refused(tmp_path):
    plan = default_plan(0, "quick")
    bad = TrainingPlan(plan.cities[:1], plan.pairs, 0, "broken")
    with pytest.raises(TrainingSetError, match="region_m0"):
        build(tmp_path, bad, TRANSFER_SETTINGS)
    with pytest.raises(TrainingSetError, match="'full', 'large' or 'quick'"):
        default_plan(0, "huge")


@pytest.mark.slow
def test_quick_training_set_builds_resumes_and_trains_a_model_that_classifies_cross_source_pairs(tmp_path):
    from quakescan.assessment.run import classify
    from quakescan.learning.model import load_model, save_model

    from quakescan.cli import main

    plan = default_plan(0, "quick")
    assert main(["training-set", "-o", str(tmp_path / "ts"), "--size", "quick", "--threads", "2"]) == 0
    table = build(tmp_path / "ts", plan, TABLE_SETTINGS, workers=2)
    assert table.x.shape == (len(table.y), len(TABLE_SETTINGS.descriptor_names()))
    assert len(table.y) >= 40 and set(np.unique(table.y)) <= {0, 3, 4, 5}
    assert np.all(np.isfinite(table.x))
    manifest = json.loads((tmp_path / "ts" / "manifest.json").read_text())
    assert manifest["rows"] == len(table.y) and manifest["plan"]["name"] == "default-quick"
    clouds = sorted((tmp_path / "ts" / "clouds").rglob("*.las"))
    assert len(clouds) == 8  # two clouds per pair
    stamps = {p: p.stat().st_mtime_ns for p in clouds}
    tables = {p: p.stat().st_mtime_ns for p in (tmp_path / "ts" / "tables").glob("*.npz")}
    again = build(tmp_path / "ts", plan, TABLE_SETTINGS, workers=2)
    np.testing.assert_array_equal(again.x, table.x)  # resumed: same rows, nothing acquired or described again
    assert {p: p.stat().st_mtime_ns for p in clouds} == stamps
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "ts" / "tables").glob("*.npz")} == tables
    cut = sorted(tables)[0]  # a table cut by a crash or a full disk: discarded and described again
    cut.write_bytes(cut.read_bytes()[:50])
    again = build(tmp_path / "ts", plan, TABLE_SETTINGS, workers=2)
    np.testing.assert_array_equal(again.x, table.x)

    table = model_columns(table)
    assert table.names == TRANSFER_SETTINGS.descriptor_names()
    scores, config = select_classifier(table, seed=0, n_splits=2)
    model = fit_default_model(table, plan, config, scores, command="test")
    dens, cov = data_limits(table)
    assert model.split["min_density_pts_m2"] == dens and 0 < dens
    assert 0 <= cov <= 1 and model.no_change_rule is False
    # every row records its footprint's raster cells; a size limit is available, not shipped
    assert table.cells is not None and len(table.cells) == len(table.y) and table.cells.min() > 0
    assert size_limit(table, 0.01) == int(np.quantile(table.cells, 0.01)) > 0
    assert model.split.get("min_cells", 0) == size_limit(table) == 0
    path = tmp_path / "model.skops"
    save_model(model, path)
    loaded = load_model(path)
    assert loaded.provenance["classifier_selection"]["chosen"] == config["name"]

    # a cross-source pair (ALS-like archive before, DIM after) end to end through classify
    pair = next(p for p in plan.pairs if p.pre["kind"] == "als" and p.post["kind"] == "dim")
    pre = next((tmp_path / "ts" / "clouds" / pair.city).glob(f"pre.als.{pair.pre_seed}.las"))
    post = next((tmp_path / "ts" / "clouds" / pair.city).glob(f"post.dim.{pair.post_seed}.las"))
    summary = classify(pre, post, tmp_path / "out", model_path=path, write_las=False)
    assert summary["buildings"] == 12
    header = (tmp_path / "out" / "buildings.csv").read_text().splitlines()[0].split(",")
    assert "confidence" in header and "decided_by" in header


def test_densest_cluster_drops_the_outlier_and_the_empty_terrain_between():
    from quakescan.formats.cityjson import import_cityjson
    from quakescan.learning.trainset import ROTTERDAM, densest_cluster

    if not ROTTERDAM.is_file():
        pytest.skip(f"{ROTTERDAM} not available")
    scene = import_cityjson(ROTTERDAM)
    cropped = densest_cluster(scene)
    assert len(scene.buildings) == 16 and len(cropped.buildings) == 15
    span = cropped.bounds()[1, :2] - cropped.bounds()[0, :2]
    assert np.all(span < 150) and np.all(scene.bounds()[1, :2] - scene.bounds()[0, :2] > 400)
    assert set(np.unique(cropped.face_building)) == set(cropped.building_ids.tolist()) | {0}


def test_damage_the_acquisition_did_not_see_is_left_out_of_training():
    from quakescan.learning.default_model import EVIDENCE, training_rows, visible_damage
    from quakescan.learning.trainset import TransferTable

    names = list(EVIDENCE) + ["s_post_gap"]
    x = np.zeros((4, len(names)))
    x[1, names.index("m_holes")] = 0.1  # heavy, seen
    x[3, names.index("s_post_gap")] = 0.5  # heavy, nothing changed that shows damage
    y = np.array([0, 3, 0, 3])
    t = TransferTable(x, y, names, np.zeros(4, int), np.zeros(4, int), np.arange(4), np.ones((4, 2)), ["c"], ["p"],
                      ["uls-uls"])
    assert visible_damage(t).tolist() == [True, True, True, False]
    assert training_rows(t).y.tolist() == [0, 3, 0]


def test_the_realistic_plan_is_the_clean_plan_with_scene_detail_and_footprint_labels():
    clean, real = default_plan(0, "full"), default_plan(0, "full", "realistic")
    assert real.labels == "footprints" and clean.labels == "simulator"
    assert len(real.cities) == len(clean.cities) and len(real.pairs) == len(clean.pairs)
    for a, b in zip(clean.cities, real.cities):
        assert b.name == f"{a.name}-real" and (b.details, b.streetscape) == ("typical", "typical")
        assert (a.source, a.dataset, a.seed, a.grade_mix) == (b.source, b.dataset, b.seed, b.grade_mix)
    for a, b in zip(clean.pairs, real.pairs):  # the same acquisitions and seeds: like for like
        assert (a.pre, a.post, a.pre_seed, a.post_seed, a.post_scene) == (b.pre, b.post, b.pre_seed, b.post_seed,
                                                                         b.post_scene)
    with pytest.raises(TrainingSetError, match="scenes must be"):
        default_plan(0, "full", "photoreal")
    with pytest.raises(TrainingSetError, match="labels must be"):
        TrainingPlan(labels="guess")


def test_combined_tables_keep_both_versions_of_a_city_in_one_cross_validation_group():
    from quakescan.learning.trainset import TransferTable, combine_tables

    def tab(cities, city, pairs):
        n = len(city)
        return TransferTable(x=np.arange(2 * n, dtype=float).reshape(n, 2), y=np.zeros(n, np.int64), names=["a", "b"],
                             city=np.array(city), pair=np.zeros(n, np.int64), building_id=np.arange(1, n + 1),
                             density=np.ones((n, 2)), cities=cities, pairs=pairs, sensors=["uls-uls"] * len(pairs))

    clean = tab(["g0", "r0"], [0, 1, 1], ["p0"])
    real = tab(["r0-real", "g0-real"], [0, 0, 1], ["q0"])  # another order: matched by name
    both = combine_tables(clean, real)
    assert both.city.tolist() == [0, 1, 1, 1, 1, 0]
    assert both.pair.tolist() == [0, 0, 0, 1, 1, 1] and both.pairs == ["p0", "q0"]
    assert len(both.y) == 6 and both.x.shape == (6, 2)
    with pytest.raises(TrainingSetError, match="no clean counterpart"):
        combine_tables(clean, tab(["z9-real"], [0], ["q0"]))


def test_a_city_made_by_another_generator_is_made_again_not_refused(monkeypatch, tmp_path):
    """The training set's scenes are its own cache: a bundle of an older generator version (or
    other settings) must be regenerated, which the generator does only with --force (without
    it, it stops: right for a user's folder, a dead end for a cache)."""
    import quakescan.generator as generator
    from quakescan.learning import trainset as T

    calls = []
    monkeypatch.setattr(generator, "generate", calls.append)
    T.generate_city(T.CitySpec("generic_m0", "generic", "mixed", 100, None, {0: 2, 5: 1}), tmp_path / "generic_m0")
    assert calls and all(job.force is True for job in calls)
