"""bench/bench_real_damage.py turns Rotterdam's buildings by quarter turns before packing them,
so each stands alone in every orientation: exact integer rotations, every object once per turn."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
bench = pytest.importorskip("bench_real_damage")
ROTTERDAM = bench.SHARED / "rotterdam_subset.json"


@pytest.mark.skipif(not ROTTERDAM.is_file(), reason=f"{ROTTERDAM} missing (the shared data folder)")
def test_rotated_copies_turn_every_vertex_exactly_and_keep_every_object_once_per_turn(tmp_path):
    src = json.loads(ROTTERDAM.read_text())
    n = bench.rotated_copies(ROTTERDAM, tmp_path / "r.json", turns=(0, 1, 2))
    dst = json.loads((tmp_path / "r.json").read_text())
    assert n == 3 * len(src["CityObjects"]) == len(dst["CityObjects"])
    v = np.asarray(src["vertices"], np.int64)
    w = np.asarray(dst["vertices"], np.int64).reshape(3, len(v), 3)
    np.testing.assert_array_equal(w[0], v)
    np.testing.assert_array_equal(w[1], np.column_stack([-v[:, 1], v[:, 0], v[:, 2]]))
    np.testing.assert_array_equal(w[2], np.column_stack([-v[:, 0], -v[:, 1], v[:, 2]]))
    key = next(iter(src["CityObjects"]))
    a = src["CityObjects"][key]["geometry"][0]["boundaries"]
    b = dst["CityObjects"][f"{key}-r2"]["geometry"][0]["boundaries"]

    def flat(x):
        return [i for y in x for i in flat(y)] if isinstance(x, list) else [x]
    assert np.array_equal(np.array(flat(b)), np.array(flat(a)) + 2 * len(v))
    for k, o in dst["CityObjects"].items():  # parents and children stay within their own copy
        for c in o.get("parents", []) + o.get("children", []):
            assert c.endswith(k[k.rindex("-r"):]) and c in dst["CityObjects"]


def _scored(quiet, ece):
    grades = {str(g): {"recall": 0.5, "precision": 0.5, "f1": 0.5, "n": 10} for g in (0, 3, 4, 5)}
    return {"per_grade": grades, "undamaged_called_damaged": 0.0, "damaged_found": 0.7, "quiet_misses": quiet,
            "quiet_misses_no_return_moved": quiet[:1], "ece": ece, "heavy_seen": {"roof": [1, 2], "walls only": [0, 2]},
            "confusion": {str(t): {str(c): 0 for c in (0, 3, 4, 5, "n/a")} for t in (0, 3, 4, 5)}}


def test_the_report_shows_the_unseen_damage_knob_every_way_in_one_table():
    case = {**_scored([], 0.12), "case": "15/15/15, patterns", "split": 5, "seed": 101, "damage": "patterns",
            "moved": 10, "assumed_visible": _scored([7, 8, 9], 0.15), "own_prior": _scored([], 0.05)}
    text = bench.report({"machine": "m", "model": "x.skops", "seconds": 1, "peak_mib": 1, "cases": [case]})
    rows = [line for line in text.splitlines() if line.startswith("| 15/15/15, patterns | ")]
    assert [r.split(" | ")[1] for r in rows[1:]] == ["counted (default)", "assumed visible",
                                                     "counted, the case's own mix as prior"]
    assert rows[2].endswith("| 3 (1) | 0.150 |") and rows[3].endswith("| 0 (0) | 0.050 |")


def test_heavy_damage_is_scored_apart_for_roof_openings_and_for_walls_only(tmp_path):
    """The independent benchmark's heavy damage is roof openings; the catalogue's heavy damage
    also lies in walls alone, which a nadir survey cannot see: both are counted apart, as graded
    damaged and as graded heavy."""
    import csv

    truth, result = tmp_path / "truth.csv", tmp_path / "buildings.csv"
    cases = [(1, 3, "roof_holes", 3), (2, 3, "roof_holes wall_holes", 4), (3, 3, "wall_holes", 0),
             (4, 3, "infill_blowout", 3), (5, 0, "", 0)]
    with open(truth, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["building_id", "grade", "injected", "n_points", "patterns", "moved"])
        for b, g, pat, _ in cases:
            w.writerow([b, g, int(g > 0), 500, pat, 10])
    with open(result, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["building_id", "assessable", "predicted_grade", "confidence"])
        for b, _, _, p in cases:
            w.writerow([b, 1, p, 0.7])
    s = bench.score(result, truth)
    assert s["heavy_seen"] == {"roof": [2, 2], "walls only": [1, 2]}
    assert s["heavy_graded_heavy"] == {"roof": 1, "walls only": 1}
    case = {**s, "case": "c", "split": 5, "seed": 1, "damage": "patterns", "moved": 1}
    text = bench.report({"machine": "m", "model": "x.skops", "seconds": 1, "peak_mib": 1, "cases": [case]})
    row = next(line for line in text.splitlines() if line.startswith("| c | "))
    assert row.endswith("| 2 of 2 / 1 of 2 | 1 of 2 / 1 of 2 |")
