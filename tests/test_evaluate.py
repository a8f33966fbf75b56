"""Metrics against hand-computed values; CSV join; confusion matrix picture."""
import numpy as np
import pytest

from quakescan.results.evaluation import (EvaluationError, binary_metrics, evaluate_files, evaluate_grades,
                                          plot_confusion)


def test_binary_metrics_by_hand():
    truth = np.array([1, 1, 1, 0, 0, 0, 0, 0], bool)
    pred = np.array([1, 1, 0, 1, 0, 0, 0, 0], bool)
    m = binary_metrics(truth, pred)  # tp 2, fn 1, fp 1, tn 4
    assert (m["tp"], m["fn"], m["fp"], m["tn"]) == (2, 1, 1, 4)
    assert m["oa"] == pytest.approx(6 / 8)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(2 / 3)
    assert m["f1"] == pytest.approx(2 / 3)
    assert binary_metrics([0, 0], [0, 0])["f1"] == 0.0  # no positives: defined as 0, not NaN


def test_grades_one_vs_rest_and_damaged():
    truth = np.array([0, 0, 3, 4, 5, 5, 2])  # grade 2 counts as no damage
    pred = np.array([0, 3, 3, 5, 5, 5, 0])
    ev = evaluate_grades(truth, pred)
    assert ev.n == 7
    assert ev.per_grade[5]["precision"] == pytest.approx(2 / 3) and ev.per_grade[5]["recall"] == 1.0
    assert ev.per_grade[4]["recall"] == 0.0
    # damaged vs undamaged: truth damaged {2,3,4,5}, predicted damaged {1,2,3,4,5}
    assert ev.damaged["tp"] == 4 and ev.damaged["fp"] == 1 and ev.damaged["tn"] == 2
    assert ev.confusion.sum() == 7 and ev.confusion[0, 0] == 2 and ev.confusion[2, 3] == 1
    assert "| destruction |" in ev.table()


def test_files_join_and_skip_not_assessable(tmp_path):
    (tmp_path / "r.csv").write_text("building_id,predicted_grade,assessable\n1,0,1\n2,5,1\n3,3,0\n9,4,1\n")
    (tmp_path / "t.csv").write_text("building_id,grade\n1,0\n2,5\n3,4\n4,3\n")
    ev = evaluate_files(tmp_path / "r.csv", tmp_path / "t.csv")
    assert ev.n == 2 and ev.not_assessable == 1 and ev.missing == [4]
    assert ev.per_grade[5]["f1"] == 1.0
    plot_confusion(ev, tmp_path / "c.png")
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the two buildings (truth 0 -> 0, 5 -> 5) are the matrix's only dark blue cells: top left and
    # bottom right, so the dark pixels lie on the falling diagonal of the picture
    from matplotlib.image import imread

    rgb = imread(tmp_path / "c.png")[..., :3]
    y, x = np.nonzero((rgb[..., 2] > rgb[..., 0] + 0.2) & (rgb[..., 2] < 0.6))
    assert len(x) > 500 and np.corrcoef(x, y)[0, 1] > 0.9


def test_bad_tables(tmp_path):
    (tmp_path / "r.csv").write_text("id,grade\n1,0\n")
    (tmp_path / "t.csv").write_text("building_id,grade\n1,0\n")
    with pytest.raises(EvaluationError, match="missing columns"):
        evaluate_files(tmp_path / "r.csv", tmp_path / "t.csv")
    with pytest.raises(EvaluationError, match="does not exist"):
        evaluate_files(tmp_path / "nope.csv", tmp_path / "t.csv")


def test_metrics_of_a_class_absent_from_the_truth_are_na_not_zero():
    """No truth building is extreme (4), one is predicted extreme: its recall and F1 have no
    cases ("n/a"), its precision is a real 0 % (the one prediction is wrong); destruction is
    neither in the truth nor predicted: precision, recall and F1 are all "n/a"."""
    import json

    from quakescan.results.evaluation import evaluate_grades, metric_text

    ev = evaluate_grades(np.array([0, 0, 3, 3]), np.array([0, 4, 3, 3]))
    lines = {line.split(" | ")[0].strip("| "): line for line in ev.table().splitlines()[2:]}
    assert lines["extreme"] == "| extreme | 75.0 % | 0.0 % | n/a | n/a |"
    assert lines["destruction"] == "| destruction | 100.0 % | n/a | n/a | n/a |"
    assert lines["heavy"] == "| heavy | 100.0 % | 100.0 % | 100.0 % | 100.0 % |"
    doc = json.loads(json.dumps(ev.to_json()))
    assert doc["per_grade"]["4"]["undefined"] == ["recall", "f1"] and doc["per_grade"]["3"]["undefined"] == []
    old = {k: v for k, v in doc["per_grade"]["5"].items() if k != "undefined"}  # a dict from before the field
    assert metric_text(old, "recall") == "n/a" and metric_text(old, "oa") == "100.0 %"
