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
