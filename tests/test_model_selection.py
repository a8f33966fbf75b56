"""Choosing the classifier by grouped cross-validation: known answers on synthetic tables."""
import numpy as np
import pytest

from quakescan.learning.model import ModelError
from quakescan.learning.model_selection import candidate_name, compare_classifiers, comparison_table, grouped_folds

NAMES = ["share_changed", "height_median", "noise"]
GRADES = (0, 3, 4, 5)
FAST = {"rf": {"n_estimators": 5}, "hgb": {"n_estimators": 10}}  # seconds, not minutes

pytestmark = pytest.mark.usefixtures("one_native_thread")


def _buildings(n_buildings=40, seed=0):
    """Each building (group) seen once per grade, as one pre-event city in four post-event
    scenes; grade 0 unchanged (share_changed 0), the others separable by construction."""
    rng = np.random.default_rng(seed)
    y = np.tile(GRADES, n_buildings)
    groups = np.repeat(np.arange(n_buildings), len(GRADES))
    share = np.select([y == 3, y == 4, y == 5], [0.2, 0.5, 0.8], 0.0) + (y > 0) * rng.uniform(0, 0.05, len(y))
    height = -np.asarray(y, float) + rng.normal(0, 0.1, len(y))
    return np.column_stack([share, height, rng.normal(size=len(y))]), y, groups


def test_folds_keep_each_building_in_one_fold_and_repeat_with_the_seed():
    _, y, groups = _buildings()
    folds = grouped_folds(y, groups, 5, seed=1)
    assert sorted(np.concatenate([te for _, te in folds]).tolist()) == list(range(len(y)))
    for tr, te in folds:
        assert not set(groups[tr]) & set(groups[te])
        assert sorted(set(y[te].tolist())) == list(GRADES)
    again = grouped_folds(y, groups, 5, seed=1)
    assert all((a == b).all() for (_, a), (_, b) in zip(folds, again))
    with pytest.raises(ModelError, match="4 groups .* too few for 5-fold"):
        grouped_folds(y[:16], groups[:16], 5)


def test_separable_buildings_are_all_right_for_every_kind():
    x, y, groups = _buildings()
    candidates = [{"kind": "rf", **FAST["rf"]}, {"kind": "hgb", **FAST["hgb"]},
                  {"kind": "rf", "calibration": "sigmoid", **FAST["rf"]}, {"kind": "rf", "rule": True, **FAST["rf"]}]
    scores = compare_classifiers(x, y, groups, NAMES, candidates, seed=0, n_splits=5)
    assert [s.name for s in scores] == ["rf", "hgb", "rf+sigmoid", "rf+rule"]
    for s in scores:
        assert s.accuracy == 1.0 and s.macro_f1 == 1.0 and s.damaged_f1 == 1.0, s.name
        assert s.f1_per_grade == {0: 1.0, 3: 1.0, 4: 1.0, 5: 1.0} and s.fold_accuracy == [1.0] * 5
        assert s.log_loss < 0.5 and s.brier < 0.25 and s.fit_seconds > 0
    rule = scores[-1]
    assert rule.log_loss < scores[0].log_loss  # p(0) = 1 for every unchanged building


def test_permuted_grades_score_at_chance():
    x, y, groups = _buildings(50)
    y = np.random.default_rng(7).permutation(y)
    scores = compare_classifiers(x, y, groups, NAMES, [{"kind": "rf", **FAST["rf"]}, {"kind": "hgb", **FAST["hgb"]}])
    for s in scores:
        assert 0.1 < s.accuracy < 0.4, (s.name, s.accuracy)  # chance: 1/4
        assert s.log_loss > np.log(4) - 0.1 and s.brier > 0.7, s.name  # no better than p = 1/4 each


def test_same_seed_same_scores_and_a_table():
    x, y, groups = _buildings(12)
    cand = [{"kind": "hgb", "calibration": "isotonic", **FAST["hgb"]}, {"name": "small forest", **FAST["rf"]}]
    a = compare_classifiers(x, y, groups, NAMES, cand, seed=3, n_splits=3)
    b = compare_classifiers(x, y, groups, NAMES, cand, seed=3, n_splits=3)
    strip = [dict(s.to_json(), fit_seconds=None) for s in a]
    assert strip == [dict(s.to_json(), fit_seconds=None) for s in b]
    table = comparison_table(a).splitlines()
    assert table[0].startswith("| candidate | OA (folds) | macro F1 | F1 no damage | F1 heavy |")
    lo, hi = min(a[0].fold_accuracy), max(a[0].fold_accuracy)
    assert len(table) == 4 and table[1] == "|" + "---|" * 11
    assert table[2].startswith(f"| hgb+isotonic | {100 * a[0].accuracy:.1f} % ({100 * lo:.1f}–{100 * hi:.1f}) |")
    assert table[3].startswith("| small forest | 100.0 % (100.0–100.0) | 100.0 % | 100.0 % |")
    assert table[3].endswith(f" | {a[1].log_loss:.3f} | {a[1].brier:.3f} | {a[1].fit_seconds:.2f} |")


def test_bad_candidates_and_tables_are_named():
    x, y, groups = _buildings(10)
    assert candidate_name({"kind": "hgb", "calibration": "sigmoid", "rule": True}) == "hgb+sigmoid+rule"
    with pytest.raises(ModelError, match="x has 40 rows, y 39 and groups 40"):
        compare_classifiers(x, y[1:], groups, NAMES, [{}])
    with pytest.raises(ModelError, match="candidate rf\\+sigmoid: groups and calibration splits"):
        compare_classifiers(x, y, groups, NAMES, [{"calibration": "sigmoid", "groups": groups}])
    with pytest.raises(ModelError, match="classifier kind 'svm'"):
        compare_classifiers(x, y, groups, NAMES, [{"kind": "svm"}])
