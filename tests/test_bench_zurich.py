"""bench/bench_zurich.py packs the scattered Zurich LoD2 buildings into a compact city: every
building moves as a whole (its parts with it), shapes unchanged, streets between them."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
bench_zurich = pytest.importorskip("bench_zurich")

needs_zurich = pytest.mark.skipif(not bench_zurich.ZURICH.is_file(),
                                  reason=f"{bench_zurich.ZURICH} missing (the shared data folder)")


def test_the_paper_mix_scaled_to_any_count_sums_to_it():
    assert bench_zurich.scaled_mix(121) == {0: 35, 3: 19, 4: 32, 5: 35}
    assert bench_zurich.scaled_mix(49) == {0: 14, 3: 8, 4: 13, 5: 14}
    for n in (1, 4, 7, 50, 333):
        assert sum(bench_zurich.scaled_mix(n).values()) == n


@needs_zurich
def test_packing_moves_whole_buildings_apart_by_a_street_and_keeps_their_shapes(tmp_path):
    src = json.loads(bench_zurich.ZURICH.read_text())
    n = bench_zurich.packed_cityjson(bench_zurich.ZURICH, tmp_path / "p.json")
    dst = json.loads((tmp_path / "p.json").read_text())
    assert n == 49 and set(dst["CityObjects"]) == set(src["CityObjects"])
    scale = np.asarray(src["transform"]["scale"])

    def world(doc, key):  # the building's vertices (with its parts'), in metres
        objs = doc["CityObjects"]
        keys = [key] + objs[key].get("children", [])
        idx = []
        for k in keys:
            for g in objs[k].get("geometry", []):
                idx += _ints(g["boundaries"])
        v = np.asarray(doc["vertices"], dtype=np.float64)[idx] * scale + np.asarray(doc["transform"]["translate"])
        return v

    boxes = []
    for key, obj in src["CityObjects"].items():
        if obj.get("parents"):
            continue
        a, b = world(src, key), world(dst, key)
        if not len(a):
            continue
        # the same shape, moved: every vertex by one and the same vector (to the millimetre)
        shift = b - a
        np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-6)
        assert b[:, 2].min() == pytest.approx(0.0, abs=1e-9)
        boxes.append((b[:, :2].min(axis=0), b[:, :2].max(axis=0)))
    for i, (lo1, hi1) in enumerate(boxes):
        for lo2, hi2 in boxes[i + 1:]:
            gap = np.maximum(lo2 - hi1, lo1 - hi2).max()  # separation along the axis that separates them
            assert gap >= bench_zurich.STREET_M - 1e-3


def _ints(x):
    if isinstance(x, list):
        return [i for y in x for i in _ints(y)]
    return [x] if isinstance(x, int) else []


def test_pooled_metrics_are_those_of_the_evaluation_of_every_building_at_once():
    from quakescan.results.evaluation import evaluate_grades

    rng = np.random.default_rng(0)
    grades = np.array([0, 3, 4, 5])
    runs = [(grades[rng.integers(0, 4, 49)], grades[rng.integers(0, 4, 49)]) for _ in range(3)]
    pooled = sum(np.asarray(evaluate_grades(t, p).confusion) for t, p in runs)
    m = bench_zurich.confusion_metrics(pooled)
    whole = evaluate_grades(np.concatenate([t for t, _ in runs]), np.concatenate([p for _, p in runs]))
    assert m["n"] == whole.n == 147
    assert m["overall_accuracy"] == pytest.approx(whole.overall_accuracy)
    assert m["f1"] == pytest.approx([whole.per_grade[g]["f1"] for g in (0, 3, 4, 5)])
    assert m["damaged_f1"] == pytest.approx(whole.damaged["f1"])
