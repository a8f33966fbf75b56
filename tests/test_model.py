"""Model persistence: round trip, tampered and incompatible files refused, grouped split."""
import zipfile

import numpy as np
import pytest

from core.model import DamageModel, ModelError, grouped_split, load_model, save_model, train_forest


@pytest.fixture
def model():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    y = np.where(x[:, 0] > 0.5, 5, np.where(x[:, 1] > 0, 3, 0))
    rf = train_forest(x, y, n_estimators=20, max_depth=5, seed=1)
    return DamageModel(rf, ["a", "b", "c"], 1.5, {"lod_height_m": 0.3}, {"trained_on": "synthetic", "seed": 1}), x


def test_round_trip_predicts_the_same(tmp_path, model):
    m, x = model
    save_model(m, tmp_path / "m.skops")
    back = load_model(tmp_path / "m.skops")
    table = {"a": x[:, 0], "b": x[:, 1], "c": x[:, 2]}
    np.testing.assert_array_equal(back.predict_proba(table), m.predict_proba(table))
    assert back.feature_names == ["a", "b", "c"] and back.radius_m == 1.5 and back.classes == [0, 3, 5]
    assert back.provenance["trained_on"] == "synthetic" and back.provenance["versions"]["quakescan"]


def test_same_seed_same_forest(model):
    m, x = model
    y = m.estimator.predict(x)
    again = train_forest(x, y, n_estimators=20, max_depth=5, seed=1)
    other = train_forest(x, y, n_estimators=20, max_depth=5, seed=1)
    np.testing.assert_array_equal(again.predict_proba(x), other.predict_proba(x))


def test_missing_features_are_named(model):
    m, x = model
    with pytest.raises(ModelError, match=r"needs features \['c'\]"):
        m.predict_proba({"a": x[:, 0], "b": x[:, 1]})


def test_tampered_file_is_refused_without_running_it(tmp_path, model):
    import skops.io as sio

    m, _ = model
    evil = {"meta": {"format": "quakescan-model", "version": 1}, "estimator": m.estimator,
            "payload": np.ma.MaskedArray([1, 2])}  # a type no damage model contains
    sio.dump(evil, tmp_path / "evil.skops")
    with pytest.raises(ModelError, match="refused"):
        load_model(tmp_path / "evil.skops")
    (tmp_path / "junk.skops").write_bytes(b"PK not really a zip")
    with pytest.raises(ModelError, match="not a QuakeScan model file"):
        load_model(tmp_path / "junk.skops")
    with pytest.raises(ModelError, match="does not exist"):
        load_model(tmp_path / "none.skops")


def test_incompatible_version_is_refused(tmp_path, model):
    import skops.io as sio

    m, _ = model
    sio.dump({"meta": {"format": "quakescan-model", "version": 99, "feature_names": ["a", "b", "c"]},
              "estimator": m.estimator}, tmp_path / "v99.skops")
    with pytest.raises(ModelError, match="version 99 is not supported"):
        load_model(tmp_path / "v99.skops")
    assert zipfile.is_zipfile(tmp_path / "v99.skops")


def test_grouped_split_keeps_buildings_together():
    groups = np.repeat(np.arange(50), 3)
    train, test = grouped_split(groups, 0.3, seed=0)
    assert not set(groups[train]) & set(groups[test])
    assert len(set(groups[test])) == 15


def _descriptor_rows():
    """Rows whose first column is share_changed: heavy (3) and destroyed (5) buildings with
    changes, undamaged ones with a few changed points (0), and many rows without changes."""
    rng = np.random.default_rng(3)
    share = np.concatenate([rng.uniform(0.001, 0.01, 30), rng.uniform(0.01, 0.05, 30), rng.uniform(0.3, 0.9, 30)])
    dz = np.concatenate([rng.normal(0, 0.05, 30), rng.normal(-0.5, 0.1, 30), rng.normal(-4, 0.5, 30)])
    y = np.repeat([0, 3, 5], 30)
    x = np.column_stack([share, dz])
    return x, y


def test_the_forest_learns_only_from_buildings_with_changed_points():
    """Rows without changed points are decided by rule: adding 500 of them changes nothing."""
    from core.model import decided_by_rule, predict_grades, train_damage_forest

    names = ["share_changed", "height_median"]
    x, y = _descriptor_rows()
    unchanged = np.zeros((500, 2))
    rf = train_damage_forest(x, y, names, n_estimators=20, seed=1)
    rf_more = train_damage_forest(np.vstack([x, unchanged]), np.concatenate([y, np.zeros(500, int)]), names,
                                  n_estimators=20, seed=1)
    np.testing.assert_array_equal(rf.predict_proba(x), rf_more.predict_proba(x))
    assert decided_by_rule(unchanged, names).all() and not decided_by_rule(x, names).any()
    both = np.vstack([x, unchanged])
    grades = predict_grades(rf, both, names)
    assert (grades[len(x):] == 0).all()
    np.testing.assert_array_equal(grades[:len(x)], rf.predict(x))
    assert (grades[:len(x)] == y).mean() > 0.9  # separable by construction


def test_a_forest_that_never_saw_grade_0_still_reports_it_by_rule():
    """Only destroyed buildings changed in training: the forest knows one grade; a building
    without changes is still "no damage" with p_0 = 1 in the results."""
    from core.classify import predict_rows
    from core.model import train_damage_forest
    from core.pipeline import BuildingRow

    names = ["share_changed", "height_median"]
    x = np.array([[0.0, 0.0], [0.0, 0.0], [0.6, -4.0], [0.7, -5.0]])
    rf = train_damage_forest(x, np.array([0, 0, 5, 5]), names, n_estimators=5)
    m = DamageModel(rf, names, 1.5)
    assert m.classes == [5] and m.grades == [0, 5]
    rows = [BuildingRow(1, 100, 100, True, "", {"share_changed": 0.0, "height_median": 0.0}),
            BuildingRow(2, 100, 100, True, "", {"share_changed": 0.5, "height_median": -3.0})]
    a, b = predict_rows(rows, m)
    assert (a.grade, a.decided_by, a.probabilities) == (0, "no change", {0: 1.0, 5: 0.0})
    assert (b.grade, b.decided_by, b.probabilities) == (5, "model", {0: 0.0, 5: 1.0})


def test_training_rows_without_any_change_are_refused():
    from core.model import train_damage_forest

    with pytest.raises(ModelError, match="none of the 3 training buildings has changed points"):
        train_damage_forest(np.zeros((3, 2)), np.array([0, 3, 5]), ["share_changed", "h"])
