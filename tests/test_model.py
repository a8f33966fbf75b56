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
