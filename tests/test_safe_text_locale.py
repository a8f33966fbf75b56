"""Every text output is UTF-8 whatever the locale, and lone surrogates never crash a writer (issue 45).

A real locale whose encoding is not UTF-8: `LC_ALL=C PYTHONUTF8=0` in a subprocess (Python
then writes ASCII unless told otherwise); the audit's UnicodeEncodeError came from the
"pts/m²" of a reason, with no odd ID at all.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPT = r'''
import locale, sys
assert locale.getpreferredencoding(False).lower() in ("ansi_x3.4-1968", "ascii", "us-ascii"), locale.getpreferredencoding(False)
import shapely.geometry
from quakescan.assessment.record import write_building_results
from quakescan.results.building_result import BuildingResult
from quakescan.results.csv_table import read_footprint_ids
from quakescan.results.outlines import building_outlines
from quakescan.results.evaluation import evaluate_files
from quakescan.formats.footprints import Footprints
import numpy as np
from pathlib import Path

out = Path(sys.argv[1])
rows = [BuildingResult(1, 900, 800, True, grade=3, probabilities={0: 0.2, 3: 0.8, 4: 0.0, 5: 0.0},
                         decided_by="model", confidence=0.8),
        BuildingResult(2, 900, 800, False, "density 1.23 pts/m\u00b2 < 1.9"),
        BuildingResult(3, 900, 800, True, grade=0, probabilities={0: 1.0, 3: 0.0, 4: 0.0, 5: 0.0},
                         decided_by="no change", confidence=1.0)]
polys = [shapely.geometry.box(10 * i, 0, 10 * i + 8, 8) for i in range(3)]
props = [{"ref": "Stra\u00dfe 7 \u00e9\u00e8"}, {"ref": "\ud800 lone"}, {"ref": "\u5efa\u7269"}]
fp = Footprints(np.array([1, 2, 3]), polys, "EPSG:2056", "test", props, "ref")
outlines = building_outlines(rows, fp)
write_building_results(out, rows, [0, 3, 4, 5], fp, outlines, "EPSG:2056", None,
                       "Damage grades: nach-\u00e9v\u00e9nement \udcff.las")
(out / "truth.csv").write_bytes("\ufeffbuilding_id,grade\n1,3\n3,0\n".encode("utf-8"))
ev = evaluate_files(out / "buildings.csv", out / "truth.csv")
assert ev.n == 2 and ev.overall_accuracy == 1.0
print(read_footprint_ids(out / "buildings.csv"))
'''


def test_results_are_written_as_utf8_under_the_c_locale(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("LC_") and k not in ("LANG", "LANGUAGE")}
    env.update(LC_ALL="C", PYTHONUTF8="0", PYTHONIOENCODING="utf-8", MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1]), *sys.path])
    run = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], env=env, capture_output=True, text=True,
                         encoding="utf-8", timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    csv_text = (tmp_path / "buildings.csv").read_bytes().decode("utf-8")
    assert "pts/m\u00b2 < 1.9" in csv_text and "Stra\u00dfe 7 \u00e9\u00e8" in csv_text and "\u5efa\u7269" in csv_text
    assert "\\ud800 lone" in csv_text  # a lone surrogate as its escape
    doc = json.loads((tmp_path / "buildings.geojson").read_bytes())
    assert doc["features"][0]["properties"]["footprint"]["ref"] == "Stra\u00dfe 7 \u00e9\u00e8"
    page = (tmp_path / "damage_map.html").read_bytes().decode("utf-8")
    assert "nach-\u00e9v\u00e9nement \\udcff.las" in page
    assert (tmp_path / "damage_map.png").is_file() and (tmp_path / "buildings.qml").is_file()
    assert "'Stra\u00dfe 7 \u00e9\u00e8'" in run.stdout and "'\\\\ud800 lone'" in run.stdout
