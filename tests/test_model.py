"""Model persistence: round trip, tampered and incompatible files refused, grouped split."""
import fractions
import zipfile
from pathlib import Path

import numpy as np
import pytest

from quakescan.learning.model import DamageModel, ModelError, grouped_split, load_model, save_model, train_forest

pytestmark = pytest.mark.usefixtures("one_native_thread")  # tiny fits (tests/conftest.py)


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


def test_a_model_file_is_deflated_and_its_inflated_size_is_what_the_size_guard_reads(tmp_path, model):
    import zipfile

    m, _ = model
    save_model(m, tmp_path / "m.skops")
    with zipfile.ZipFile(tmp_path / "m.skops") as z:
        infos = z.infolist()
    assert {i.compress_type for i in infos} == {zipfile.ZIP_DEFLATED}
    assert sum(i.compress_size for i in infos) < sum(i.file_size for i in infos)


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


def test_rows_as_a_matrix_give_the_tables_probabilities(model):
    """The classify run's path (descriptor_matrix of the rows) and the table path are one."""
    from quakescan.change.pipeline import BuildingRow, descriptor_matrix

    m, x = model
    rows = [BuildingRow(i + 1, 10, 10, True, "", {"c": v[2], "a": v[0], "b": v[1]}) for i, v in enumerate(x)]
    np.testing.assert_array_equal(m.predict_proba_matrix(descriptor_matrix(rows, m.feature_names)),
                                  m.predict_proba({"a": x[:, 0], "b": x[:, 1], "c": x[:, 2]}))
    with pytest.raises(ModelError, match=r"reads 3 features a row, got a matrix of shape \(200, 2\)"):
        m.predict_proba_matrix(x[:, :2])


def test_tampered_file_is_refused_without_running_it(tmp_path, model):
    import skops.io as sio

    m, _ = model
    # A type no damage model contains and skops does not trust by itself (it trusts numpy's
    # masked arrays). The match names the message, not "refused": the test's own folder is
    # named so, and every message starts with the path.
    evil = {"meta": {"format": "quakescan-model", "version": 1}, "estimator": m.estimator,
            "payload": fractions.Fraction(1, 3)}
    sio.dump(evil, tmp_path / "evil.skops")
    with pytest.raises(ModelError, match=r"refused: the file asks to build types \['fractions.Fraction'\]"):
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
    from quakescan.learning.model import decided_by_rule, predict_grades, train_damage_forest

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


def test_training_and_classifying_read_no_change_from_one_column():
    """The rule reads share_changed where a row has it, else a surface model's m_changed: the
    rows training leaves out are the rows classifying decides without the model."""
    from quakescan.learning.model import changed_share, changed_share_column, decided_by_rule

    assert changed_share_column(["m_changed", "share_changed"]) == "share_changed"
    assert changed_share_column(["s_raised", "m_changed"]) == "m_changed"
    assert changed_share_column(["s_raised"]) is None
    names = ["s_raised", "m_changed"]
    x = np.array([[0.3, 0.0], [0.0, 0.2], [0.0, 0.0]])
    assert decided_by_rule(x, names).tolist() == [True, False, True]
    assert [changed_share(dict(zip(names, row))) == 0.0 for row in x] == decided_by_rule(x, names).tolist()
    assert changed_share({"share_changed": 0.1, "m_changed": 0.0}) == 0.1 and changed_share({"s_raised": 1.0}) == 0.0


def test_a_forest_that_never_saw_grade_0_still_reports_it_by_rule():
    """Only destroyed buildings changed in training: the forest knows one grade; a building
    without changes is still "no damage" with p_0 = 1 in the results."""
    from quakescan.change.pipeline import BuildingRow
    from quakescan.learning.prediction import predict_rows
    from quakescan.learning.model import train_damage_forest

    names = ["share_changed", "height_median"]
    x = np.array([[0.0, 0.0], [0.0, 0.0], [0.6, -4.0], [0.7, -5.0]])
    rf = train_damage_forest(x, np.array([0, 0, 5, 5]), names, n_estimators=5)
    m = DamageModel(rf, names, 1.5)
    assert m.classes == [5] and m.grades == [0, 5]
    rows = [BuildingRow(1, 100, 100, True, "", {"share_changed": 0.0, "height_median": 0.0}),
            BuildingRow(2, 100, 100, True, "", {"share_changed": 0.5, "height_median": -3.0})]
    a, b = predict_rows(rows, m)
    assert (a.grade, a.decided_by, a.probabilities, a.confidence) == (0, "no change", {0: 1.0, 5: 0.0}, 1.0)
    assert (b.grade, b.decided_by, b.probabilities, b.confidence) == (5, "model", {0: 0.0, 5: 1.0}, 1.0)


def test_training_rows_without_any_change_are_refused():
    from quakescan.learning.model import train_damage_forest

    with pytest.raises(ModelError, match="none of the 3 training buildings has changed points"):
        train_damage_forest(np.zeros((3, 2)), np.array([0, 3, 5]), ["share_changed", "h"])


# ------------------------------------------------------------------ classifier kinds and their files

KINDS = [("rf", None), ("hgb", None), ("rf", "sigmoid"), ("hgb", "sigmoid"), ("rf", "isotonic"),
         ("hgb", "isotonic")]
SMALL = {"rf": {"n_estimators": 10}, "hgb": {"n_estimators": 15}}  # fast; the defaults are bigger


def _grades_data(n=150, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    y = np.where(x[:, 0] > 0.5, 5, np.where(x[:, 1] > 0, 3, 0))
    return x, y


def test_train_forest_is_the_rf_kind_and_the_forest_it_always_was():
    """train_forest goes through fit_classifier("rf") and still fits the same forest."""
    from sklearn.ensemble import RandomForestClassifier

    from quakescan.learning.model import fit_classifier

    x, y = _grades_data()
    old = RandomForestClassifier(n_estimators=20, max_depth=5, random_state=3, n_jobs=None,
                                 class_weight="balanced").fit(x, y)
    np.testing.assert_array_equal(train_forest(x, y, n_estimators=20, seed=3).predict_proba(x), old.predict_proba(x))
    np.testing.assert_array_equal(fit_classifier(x, y, n_estimators=20, seed=3).predict_proba(x), old.predict_proba(x))
    assert fit_classifier(x, y, "rf").n_estimators == 100


@pytest.mark.parametrize("kind,calibration", KINDS)
def test_same_rows_same_seed_same_predictions(kind, calibration):
    from quakescan.learning.model import fit_classifier

    x, y = _grades_data()
    a = fit_classifier(x, y, kind, calibration=calibration, seed=4, **SMALL[kind])
    b = fit_classifier(x, y, kind, calibration=calibration, seed=4, **SMALL[kind])
    np.testing.assert_array_equal(a.predict_proba(x), b.predict_proba(x))
    assert [int(c) for c in a.classes_] == [0, 3, 5]
    assert (a.predict(x) == y).mean() > 0.85


def test_hgb_defaults_and_arguments():
    from quakescan.learning.model import HGB_DEFAULTS, fit_classifier

    x, y = _grades_data()
    h = fit_classifier(x, y, "hgb", seed=2, learning_rate=0.2)
    assert h.max_iter == HGB_DEFAULTS["max_iter"] and h.early_stopping is False and h.learning_rate == 0.2
    assert h.random_state == 2 and h.class_weight == "balanced" and h.max_depth == 5
    assert fit_classifier(x, y, "hgb", n_estimators=7).max_iter == 7
    assert fit_classifier(x, y, "hgb", n_estimators=7, n_jobs=1).n_iter_ == 7
    with pytest.raises(ModelError, match="n_estimators=7 and max_iter=9"):
        fit_classifier(x, y, "hgb", n_estimators=7, max_iter=9)
    with pytest.raises(ModelError, match="classifier kind 'svm' is not one of"):
        fit_classifier(x, y, "svm")
    with pytest.raises(ModelError, match="calibration 'platt' is not one of"):
        fit_classifier(x, y, "rf", calibration="platt")
    with pytest.raises(ModelError, match="classifier kind 'rf'.*learning_rate"):
        fit_classifier(x, y, "rf", learning_rate=0.1)


def test_calibration_folds_keep_groups_apart_and_are_fixed():
    from quakescan.learning.model import calibration_folds, fit_classifier

    x, y = _grades_data(120)
    groups = np.arange(120) // 4  # 30 buildings, 4 rows each
    assert calibration_folds(x, y) == 3
    folds = calibration_folds(x, y, groups=groups)
    assert len(folds) == 3
    for tr, te in folds:
        assert not set(groups[tr]) & set(groups[te])
    again = calibration_folds(x, y, groups=groups)
    assert all((a == c).all() and (b == d).all() for (a, b), (c, d) in zip(folds, again))
    m = fit_classifier(x, y, "rf", calibration="sigmoid", groups=groups, n_estimators=10)
    assert len(m.calibrated_classifiers_) == 3
    with pytest.raises(ModelError, match="119 groups for 120 rows"):
        calibration_folds(x, y, groups=groups[1:])
    with pytest.raises(ModelError, match=r"cannot fit a rf classifier \(calibration isotonic\) on 4 rows"):
        fit_classifier(x[:4], np.array([0, 0, 5, 5]), "rf", calibration="isotonic")


@pytest.mark.parametrize("kind,calibration", KINDS)
def test_every_kind_round_trips_through_a_file_of_trusted_types(tmp_path, kind, calibration):
    import skops.io as sio

    from quakescan.learning.model import TRUSTED_TYPES, fit_classifier

    x, y = _grades_data()
    est = fit_classifier(x, y, kind, calibration=calibration, groups=np.arange(len(y)) // 3, seed=1,
                         **SMALL[kind])
    m = DamageModel(est, ["a", "b", "c"], 1.5)
    save_model(m, tmp_path / "m.skops")
    assert set(sio.get_untrusted_types(file=tmp_path / "m.skops")) <= set(TRUSTED_TYPES)
    back = load_model(tmp_path / "m.skops")
    table = {"a": x[:, 0], "b": x[:, 1], "c": x[:, 2]}
    np.testing.assert_array_equal(back.predict_proba(table), m.predict_proba(table))
    c = back.classifier
    assert (c["kind"], c["calibration"]) == (kind, calibration) and c["params"]["random_state"] == 1
    assert c == m.classifier
    if calibration:
        assert c["params"]["calibration_cv"] == "3 given splits"
    meta = sio.load(tmp_path / "m.skops", trusted=TRUSTED_TYPES)["meta"]
    assert meta["classifier"] == c and meta["no_change_rule"] is True and meta["version"] == 1


def test_trusted_types_are_exactly_what_the_kinds_need(tmp_path):
    """No type on the allow-list that no classifier kind needs (and none missing)."""
    import skops.io as sio

    from quakescan.learning.model import TRUSTED_TYPES, fit_classifier

    x, y = _grades_data(60)
    needed = set()
    for k, (kind, calibration) in enumerate(KINDS):
        sio.dump(fit_classifier(x, y, kind, calibration=calibration, n_estimators=3), tmp_path / f"{k}.skops")
        needed |= set(sio.get_untrusted_types(file=tmp_path / f"{k}.skops"))
    assert needed == set(TRUSTED_TYPES)


def test_metadata_naming_another_classifier_is_refused(tmp_path, model):
    import skops.io as sio

    m, _ = model
    meta = {"format": "quakescan-model", "version": 1, "feature_names": ["a", "b", "c"],
            "classifier": {"kind": "hgb", "calibration": None, "params": {}}}
    sio.dump({"meta": meta, "estimator": m.estimator}, tmp_path / "liar.skops")
    with pytest.raises(ModelError, match="metadata says kind 'hgb'.*holds kind 'rf'"):
        load_model(tmp_path / "liar.skops")
    meta = dict(meta, classifier={"kind": "rf", "calibration": None}, no_change_rule="yes")
    sio.dump({"meta": meta, "estimator": m.estimator}, tmp_path / "rule.skops")
    with pytest.raises(ModelError, match="no_change_rule must be true or false, got 'yes'"):
        load_model(tmp_path / "rule.skops")


def test_a_model_file_of_the_first_format_loads_and_predicts_as_before(tmp_path):
    """Files written before the classifier and no_change_rule keys (the model QuakeScan shipped
    until the transfer model, commit 14370f2): a forest without calibration that decides
    unchanged buildings by rule, and predict_rows gives what the rule plus the forest's own
    predict_proba give."""
    import skops.io as sio

    from quakescan.change.pipeline import BuildingRow
    from quakescan.change.settings import PipelineSettings
    from quakescan.learning.prediction import predict_rows

    settings = PipelineSettings()
    names = settings.descriptor_names()
    rng = np.random.default_rng(4)
    xt = np.abs(rng.normal(size=(60, len(names))))
    yt = np.repeat([3, 4, 5], 20)
    forest = train_forest(xt, yt, n_estimators=100, seed=0)
    meta = {"format": "quakescan-model", "version": 1, "quakescan": "0.1.0", "sklearn": "1.4",
            "feature_names": names, "radius_m": 1.5, "split": settings.to_json(), "provenance": {},
            "created": "2026-11-01"}
    sio.dump({"meta": meta, "estimator": forest}, tmp_path / "old.skops")
    m = load_model(tmp_path / "old.skops")
    assert m.no_change_rule is True and m.grades == [0, 3, 4, 5]
    assert (m.classifier["kind"], m.classifier["calibration"]) == ("rf", None)
    assert m.classifier["params"]["n_estimators"] == 100
    x = np.abs(rng.normal(size=(40, len(m.feature_names))))
    x[::4, 0] = 0.0  # share_changed (the first column) zero: by rule
    rows = [BuildingRow(i + 1, 100, 100, True, "", dict(zip(m.feature_names, r.tolist()))) for i, r in enumerate(x)]
    got = predict_rows(rows, m)
    want = m.estimator.predict_proba(x)
    for r, row, p in zip(got, x, want):
        if row[0] == 0:
            assert (r.grade, r.decided_by, r.probabilities) == (0, "no change", {0: 1.0, 3: 0.0, 4: 0.0, 5: 0.0})
        else:
            assert r.decided_by == "model" and r.grade == m.classes[int(np.argmax(p))]
            assert r.probabilities == {**{g: 0.0 for g in m.grades}, **dict(zip(m.classes, p.tolist()))}


def _recorded_modules(path) -> set:
    """The modules whose types a skops file asks to rebuild (its schema's `__module__`s)."""
    import re

    with zipfile.ZipFile(path) as z:
        return set(re.findall(r'"__module__": "([^"]+)"', z.read("schema.json").decode()))


def test_a_model_file_saved_before_the_rename_to_quakescan_loads_and_predicts(tmp_path, model):
    """The shipped model was written by save_model when the library's import name was `core`
    (commit 1dc0058 and before). skops records only numpy, sklearn and builtins types, never
    the library's, so such a file loads without any `core` package; a file saved now records
    the same kinds of types, which is what keeps every older file loadable."""
    from quakescan.learning.default_model import DEFAULT_MODEL

    m = load_model(DEFAULT_MODEL)
    probe = np.random.default_rng(0).random((3, len(m.feature_names)))
    got = m.predict_proba({n: probe[:, i] for i, n in enumerate(m.feature_names)})
    assert got.shape == (3, len(m.classes)) and np.allclose(got.sum(axis=1), 1.0)
    save_model(model[0], tmp_path / "now.skops")
    for path in (DEFAULT_MODEL, tmp_path / "now.skops"):
        mods = _recorded_modules(path)
        assert mods and all(mod.split(".")[0] in ("builtins", "numpy", "sklearn") for mod in mods), (path, mods)


def test_the_shipped_model_is_the_transfer_model_with_its_limits_and_provenance():
    from quakescan.learning.default_model import DEFAULT_MODEL
    from quakescan.learning.prediction import model_settings
    from quakescan.learning.default_model import MODEL_DESCRIPTORS

    m = load_model(DEFAULT_MODEL)
    assert m.no_change_rule is False and m.grades == [0, 3, 4, 5]
    assert list(m.feature_names) == list(MODEL_DESCRIPTORS)
    s = model_settings(m)
    assert s.surface is not None and not s.paper_descriptors
    assert 0 < s.min_density_pts_m2 < 4 and 0 < s.min_coverage < 1
    prov = m.provenance
    assert prov["classifier_selection"]["chosen"] and prov["n_rows"] > 2500
    assert "make_default_model.py" in prov["command"] and prov["descriptor_version"] >= 1
    # probabilities calibrated on real points, out of fold (quakescan.learning.real_calibration)
    cal = prov["real_calibration"]
    assert m.temperature == cal["temperature"] and cal["rows"] > 100
    assert cal["log_loss_after"] <= cal["log_loss_before"]


# ------------------------------------------------------------------ the no-change rule as a model property

def _rows_with_unchanged_heavy():
    """_descriptor_rows plus unchanged rows (share_changed 0) of two kinds: 40 undamaged and
    40 'heavy' ones that sank without a changed point (height -0.5): only a model asked
    about unchanged rows can tell them apart."""
    x, y = _descriptor_rows()
    flat = np.column_stack([np.zeros(80), np.repeat([0.0, -0.5], 40)])
    return np.vstack([x, flat]), np.concatenate([y, np.repeat([0, 3], 40)])


def test_rule_off_fits_and_asks_every_row():
    from quakescan.learning.model import fit_classifier, predict_grades, train_damage_forest

    names = ["share_changed", "height_median"]
    x, y = _rows_with_unchanged_heavy()
    all_rows = train_damage_forest(x, y, names, rule=False, n_estimators=20, seed=1)
    np.testing.assert_array_equal(all_rows.predict_proba(x),
                                  fit_classifier(x, y, n_estimators=20, seed=1).predict_proba(x))
    changed = train_damage_forest(x, y, names, n_estimators=20, seed=1)
    flat = x[-80:]
    assert (predict_grades(changed, flat, names) == 0).all()  # the rule: unchanged is undamaged
    off = predict_grades(all_rows, flat, names, rule=False)
    assert (off == y[-80:]).all()  # the model sees the sunk ones
    assert predict_grades(all_rows, np.zeros((0, 2)), names, rule=False).shape == (0,)


def test_rule_off_keeps_calibration_groups_row_for_row():
    from quakescan.learning.model import train_damage_forest

    names = ["share_changed", "height_median"]
    x, y = _rows_with_unchanged_heavy()
    groups = np.arange(len(y)) // 2
    est = train_damage_forest(x, y, names, calibration="sigmoid", groups=groups, n_estimators=10)
    assert est.n_features_in_ == 2 and len(est.calibrated_classifiers_) == 3
    folds = [(np.arange(len(y))[k::3], np.arange(len(y))[(k + 1) % 3::3]) for k in range(3)]
    with pytest.raises(ModelError, match="cannot follow the rule's removal of 80 unchanged rows"):
        train_damage_forest(x, y, names, calibration="sigmoid", cv=folds)


def test_a_model_without_the_rule_is_asked_about_unchanged_buildings(tmp_path):
    import skops.io as sio

    from quakescan.change.pipeline import BuildingRow
    from quakescan.learning.prediction import predict_rows
    from quakescan.learning.model import TRUSTED_TYPES, VERSION_ALL_ROWS, train_damage_forest

    names = ["share_changed", "height_median"]
    x, y = _rows_with_unchanged_heavy()
    m = DamageModel(train_damage_forest(x, y, names, rule=False, n_estimators=20, seed=1), names, 1.5,
                    no_change_rule=False)
    rows = [BuildingRow(1, 100, 100, True, "", {"share_changed": 0.0, "height_median": -0.5}),
            BuildingRow(2, 100, 100, True, "", {"share_changed": 0.0, "height_median": 0.0}),
            BuildingRow(3, 100, 100, True, "", {"share_changed": 0.6, "height_median": -4.0}),
            BuildingRow(4, 3, 0, False, "3 pre-event points < 50")]
    sunk, flat, destroyed, na = predict_rows(rows, m)
    assert (sunk.grade, sunk.decided_by) == (3, "model") and (flat.grade, flat.decided_by) == (0, "model")
    assert (destroyed.grade, na.grade, na.assessable) == (5, None, False)
    assert sunk.probabilities[3] > 0.5 and set(sunk.probabilities) == {0, 3, 5}
    forced = predict_rows(rows, m, rule=True)[0]
    assert (forced.grade, forced.decided_by) == (0, "no change")
    save_model(m, tmp_path / "all.skops")
    assert sio.load(tmp_path / "all.skops", trusted=TRUSTED_TYPES)["meta"]["version"] == VERSION_ALL_ROWS
    back = load_model(tmp_path / "all.skops")
    assert back.no_change_rule is False
    assert [(r.grade, r.decided_by) for r in predict_rows(rows, back)] == \
           [(r.grade, r.decided_by) for r in (sunk, flat, destroyed, na)]


def test_grades_of_a_model_without_the_rule_are_its_classes():
    from quakescan.learning.model import train_damage_forest

    names = ["share_changed", "height_median"]
    x = np.array([[0.0, 0.0], [0.1, -1.0], [0.6, -4.0], [0.7, -5.0]])
    est = train_damage_forest(x, np.array([3, 3, 5, 5]), names, rule=False, n_estimators=5)
    assert DamageModel(est, names, 1.5, no_change_rule=False).grades == [3, 5]
    assert DamageModel(est, names, 1.5).grades == [0, 3, 5]


# ------------------------------------------------------------------ confidence


def test_confidence_is_the_predicted_class_probability_and_margin_its_lead():
    p = np.array([[0.7, 0.2, 0.1], [0.4, 0.4, 0.2], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(DamageModel.confidence(p), [0.7, 0.4, 1.0])
    np.testing.assert_allclose(DamageModel.margin(p), [0.5, 0.0, 1.0])
    np.testing.assert_array_equal(DamageModel.margin(np.ones((2, 1))), [1.0, 1.0])
    assert DamageModel.confidence(np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ModelError, match=r"\(n, n_classes\) array, got shape \(3,\)"):
        DamageModel.confidence([0.2, 0.3, 0.5])


def test_predict_rows_puts_the_confidence_on_each_building(model):
    from quakescan.change.pipeline import BuildingRow
    from quakescan.learning.prediction import predict_rows

    m, x = model
    names = ["share_changed", "b", "c"]
    m.feature_names = names
    rows = [BuildingRow(k + 1, 100, 100, True, "", dict(zip(names, r.tolist()))) for k, r in enumerate(x[:20])]
    rows[0].descriptors["share_changed"] = 0.0
    rows.append(BuildingRow(99, 2, 0, False, "2 pre-event points < 50"))
    res = predict_rows(rows, m)
    proba = m.predict_proba({n: np.array([r.descriptors[n] for r in rows[1:20]]) for n in names})
    assert res[0].confidence == 1.0 and res[0].decided_by == "no change"
    np.testing.assert_allclose([r.confidence for r in res[1:20]], proba.max(axis=1))
    assert all(r.confidence == r.probabilities[r.grade] for r in res[:20])
    assert res[-1].confidence is None
