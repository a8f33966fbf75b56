"""One temperature fitted on real-point rows out of fold (`quakescan.learning.real_calibration`),
and the model file that carries it."""
from __future__ import annotations

import numpy as np
import pytest

from quakescan.learning.model import DamageModel, ModelError, load_model, save_model, train_forest
from quakescan.learning.real_calibration import out_of_fold_real, real_calibration
from quakescan.learning.reliability import MAX_TEMPERATURE, expected_calibration_error, fit_temperature, log_loss, temper
from quakescan.learning.trainset import TransferTable


def _softmax(z):
    e = np.exp(z - z.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def test_tempering_keeps_every_argmax_and_sums_to_one():
    rng = np.random.default_rng(0)
    p = _softmax(rng.normal(0, 3, (500, 4)))
    p[0] = [1.0, 0.0, 0.0, 0.0]  # certainty and zeros stay finite
    for t in (0.5, 1.0, 2.0, MAX_TEMPERATURE):
        q = temper(p, t)
        assert np.all(np.isfinite(q))
        np.testing.assert_allclose(q.sum(axis=1), 1.0)
        np.testing.assert_array_equal(q.argmax(axis=1), p.argmax(axis=1))
    np.testing.assert_array_equal(temper(p, 1.0), p)
    assert temper(p, 4.0).max(axis=1).mean() < p.max(axis=1).mean()  # softer
    # closed form: two classes at logits 0 and ln 9 (p = 0.9) at T = 2 give 3 : 1
    np.testing.assert_allclose(temper(np.array([[0.1, 0.9]]), 2.0), [[0.25, 0.75]])
    with pytest.raises(ValueError, match="temperature must be"):
        temper(p, 0.0)


@pytest.mark.parametrize("true_t", [0.5, 2.5])
def test_the_fitted_temperature_is_the_one_that_made_the_data(true_t):
    """Classes drawn from softmax(z / T0) while the model says softmax(z): the fit finds T0, and
    the calibration error falls."""
    rng = np.random.default_rng(int(true_t * 10))
    z = rng.normal(0, 3, (6000, 4))
    truth = np.array([rng.choice(4, p=row) for row in _softmax(z / true_t)])
    said = _softmax(z)
    t = fit_temperature(said, truth)
    assert t == pytest.approx(true_t, rel=0.08)
    assert log_loss(temper(said, t), truth) < log_loss(said, truth)
    assert expected_calibration_error(temper(said, t), truth) < 0.03 < expected_calibration_error(said, truth)


def _table(pairs=("sim_a", "sim_b", "real_1", "real_2"), per=60, repeat_real=3, seed=0):
    """A table whose first column is the pair index (so a fit can be checked for what it saw);
    real pairs' rows repeated `repeat_real` times, as the training set repeats them."""
    rng = np.random.default_rng(seed)
    xs, ys, city, pair, bid = [], [], [], [], []
    for k, name in enumerate(pairs):
        n = per
        x = np.c_[np.full(n, k), rng.normal(size=(n, 2))]
        y = np.where(x[:, 1] > 0.3, 5, np.where(x[:, 2] > 0, 3, 0))
        reps = repeat_real if name.startswith("real") else 1
        xs += [x] * reps
        ys += [y] * reps
        city += [np.full(n, k % 2)] * reps
        pair += [np.full(n, k)] * reps
        bid += [np.arange(n)] * reps
    cat = np.concatenate
    return TransferTable(x=cat(xs), y=cat(ys), names=["pair", "a", "b"], city=cat(city), pair=cat(pair),
                         building_id=cat(bid), density=np.ones((len(cat(ys)), 2)), cities=["c0", "c1"],
                         pairs=list(pairs), sensors=["uls-uls"] * len(pairs))


def test_each_real_pair_is_predicted_by_a_fit_that_never_saw_it_once_per_building():
    table = _table()
    seen = []

    def fit(x, y, **kw):
        seen.append(set(np.unique(x[:, 0]).astype(int).tolist()))
        return train_forest(x, y, n_estimators=10, max_depth=4, seed=0)

    proba, truth, classes, where = out_of_fold_real(table, table, {"kind": "rf"}, ["real_1", "real_2"], fit=fit)
    assert seen == [{0, 1, 3}, {0, 1, 2}]  # pair indices 2 and 3 are real_1 and real_2
    assert len(truth) == 2 * 60 and list(np.unique(where)) == ["real_1", "real_2"]  # repeats counted once
    assert list(classes) == [0, 3, 5] and proba.shape == (120, 3)


def test_real_calibration_records_its_measurements():
    table = _table()
    rec = real_calibration(table, table, {"kind": "rf", "n_estimators": 20, "max_depth": None}, ["real_1", "real_2"])
    assert rec["rows"] == 120 and rec["pairs"] == ["real_1", "real_2"]
    assert 1 / MAX_TEMPERATURE <= rec["temperature"] <= MAX_TEMPERATURE
    assert rec["log_loss_after"] <= rec["log_loss_before"] + 1e-9


@pytest.fixture
def model():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    y = np.where(x[:, 0] > 0.5, 5, np.where(x[:, 1] > 0, 3, 0))
    return DamageModel(train_forest(x, y, n_estimators=20, max_depth=5, seed=1), ["a", "b", "c"], 1.5), x


def test_a_model_file_carries_its_temperature_and_grades_do_not_change(tmp_path, model):
    m, x = model
    table = {"a": x[:, 0], "b": x[:, 1], "c": x[:, 2]}
    plain = m.predict_proba(table)
    m.temperature = 2.0
    save_model(m, tmp_path / "t.skops")
    back = load_model(tmp_path / "t.skops")
    assert back.temperature == 2.0
    np.testing.assert_allclose(back.predict_proba(table), temper(plain, 2.0))
    np.testing.assert_array_equal(back.predict(table), np.asarray(m.classes)[plain.argmax(axis=1)])
    m.temperature = 1.0
    save_model(m, tmp_path / "plain.skops")
    assert load_model(tmp_path / "plain.skops").temperature == 1.0


@pytest.mark.parametrize("bad", [0.0, -1.0, "2", float("nan"), 1e9, True])
def test_a_model_file_with_a_bad_temperature_is_refused(tmp_path, model, bad):
    import skops.io as sio

    m, _ = model
    meta = {"format": "quakescan-model", "version": 1, "feature_names": ["a", "b", "c"], "radius_m": 1.5,
            "classifier": {"kind": "rf", "calibration": None}, "temperature": bad}
    sio.dump({"meta": meta, "estimator": m.estimator}, tmp_path / "bad.skops")
    with pytest.raises(ModelError, match="temperature must be"):
        load_model(tmp_path / "bad.skops")


def test_the_temperature_is_fitted_to_the_probabilities_classify_reports():
    """Rows whose data could not show damage carry unseen shares: the temperature is fitted
    after they are counted (`unseen_damage`), the one a user's probabilities get."""
    import dataclasses

    from quakescan.learning.real_calibration import _out_of_fold
    from quakescan.learning.unseen_damage import with_unseen_damage

    table = _table()
    q = np.zeros((len(table.y), 3))
    q[table.pair == 2] = [0.5, 0.1, 0.0]  # real_1: an airborne pair, walls unresolved
    with_q = dataclasses.replace(table, unseen=q)
    config = {"kind": "rf", "n_estimators": 20, "max_depth": None}
    rec = real_calibration(with_q, with_q, config, ["real_1", "real_2"])
    plain = real_calibration(table, table, config, ["real_1", "real_2"])
    assert rec["unseen_damage"] and not plain["unseen_damage"]
    proba, truth, classes, _, rows = _out_of_fold(with_q, with_q, config, ["real_1", "real_2"])
    shares = [dict(zip((3, 4, 5), r)) for r in q[rows]]
    index = np.searchsorted(classes, truth)
    expected = fit_temperature(proba, index, lambda p: with_unseen_damage(p, classes, shares))
    assert rec["temperature"] == pytest.approx(round(expected, 4))
    assert plain["temperature"] == pytest.approx(round(fit_temperature(proba, index), 4))
    assert rec["temperature"] != plain["temperature"]


def test_recalibrating_a_model_refits_its_temperature_and_keeps_its_estimator(tmp_path, monkeypatch):
    from quakescan.learning import default_model as dm

    table = _table()
    config = dm.CANDIDATES[0]
    fit_args = {k: v for k, v in config.items() if k not in ("name", "rule")}
    from quakescan.learning.model import fit_classifier

    m = DamageModel(fit_classifier(table.x, table.y, seed=0, **fit_args), list(table.names), 1.5, temperature=3.0)
    m.provenance["classifier_selection"] = {"chosen": config["name"]}
    save_model(m, tmp_path / "m.skops")
    monkeypatch.setattr(dm, "default_tables", lambda work, **kw: (None, table, table, ["real_1", "real_2"]))
    rec = dm.recalibrate_default_model(tmp_path / "m.skops", tmp_path / "work", tmp_path / "out.skops",
                                       real_data=tmp_path)
    expected = real_calibration(table, table, config, ["real_1", "real_2"])
    back = load_model(tmp_path / "out.skops")
    assert back.temperature == rec["temperature"] == expected["temperature"]
    assert "before: T 3)" in back.provenance["real_calibration"]["refit"]
    np.testing.assert_array_equal(back.estimator.predict_proba(table.x), m.estimator.predict_proba(table.x))
    with pytest.raises(ValueError, match="needs the real archives"):
        dm.recalibrate_default_model(tmp_path / "m.skops", tmp_path / "work", tmp_path / "o2.skops")
