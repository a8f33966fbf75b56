"""One table of grade names: core's and the add-on's copy agree, and every output uses it."""
import sys
from pathlib import Path

from quakescan import grades
from quakescan.learning.model import GRADE_LABELS
from quakescan.results.evaluation import TARGET_SHORT_NAMES as EVALUATION_NAMES

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def test_the_add_on_copy_is_identical():
    from addon import ems98  # pure Python: no bpy needed

    assert ems98.GRADE_NAMES == grades.GRADE_NAMES
    assert ems98.GRADE_SHORT_NAMES == grades.GRADE_SHORT_NAMES
    assert {g: v[0] for g, v in ems98.GRADES.items()} == grades.GRADE_NAMES
    assert all(ems98.grade_label(g) == grades.grade_name(g) for g in range(6))


def test_ems98_names_and_the_papers_short_names():
    assert [grades.grade_name(g) for g in range(6)] == [
        "no damage", "negligible to slight", "moderate", "substantial to heavy", "very heavy", "destruction"]
    assert [grades.short_name(g) for g in (3, 4, 5)] == ["heavy", "extreme", "destruction"]
    assert grades.long_label(3) == "3 substantial to heavy (heavy)" and grades.long_label(5) == "5 destruction"
    assert grades.grade_name(7) == "grade 7"
    # the CSV's `label` (a file contract) and the evaluation tables keep the short names, from the same table
    assert GRADE_LABELS == grades.GRADE_SHORT_NAMES
    assert EVALUATION_NAMES == {g: grades.GRADE_SHORT_NAMES[g] for g in (0, 3, 4, 5)}


def test_the_docs_document_the_table_once():
    """Once across README.md and the docs pages (it lives in docs/formats.md), so no copy drifts."""
    text = "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))])
    rows = [f"| {g} | {grades.GRADE_NAMES[g]} | {grades.GRADE_SHORT_NAMES[g]} |" for g in range(6)]
    for row in rows:
        assert text.count(row) == 1, row
