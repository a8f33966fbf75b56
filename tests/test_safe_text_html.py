"""Escaped HTML, plain-text PNG titles and IDs JavaScript cannot round (issue 45)."""
import json
import re

import pytest
import shapely.geometry

from quakescan.results import png_map
from quakescan.results.building_result import BuildingResult
from quakescan.results.outlines import OUTLINE_FOOTPRINT, Outline
from quakescan.results.png_map import write_map_png
from quakescan.results.webmap import write_map_html
from quakescan.runtime.text_safety import js_safe_id, script_json
from test_maps import CHROMIUM, _chromium

CLASSES = [0, 3, 4, 5]
E0, N0 = 367000.0, 4690000.0
BIG = 2 ** 60 + 1  # a double rounds it to 2^60
HOSTILE = '<!--<script>x</script><img src=x onerror="document.title=1">'


def _rows_and_outlines(ids):
    rows, outlines = [], {}
    for k, bid in enumerate(ids):
        rows.append(BuildingResult(bid, 900, 800, True, grade=3, probabilities={0: 0.2, 3: 0.8, 4: 0.0, 5: 0.0},
                                     share_changed=0.4, decided_by="model", confidence=0.8,
                                     min_opening_m2=float("inf"), detectable_grade=None))
        x = E0 + 25 * k
        outlines[bid] = Outline(shapely.geometry.box(x, N0, x + 16, N0 + 12), OUTLINE_FOOTPRINT)
    return rows, outlines


def test_script_json_cannot_end_or_stall_the_script_element():
    text = script_json({"t": "</script><!--<script>&amp;\u2028"})
    assert "<" not in text and ">" not in text and "&" not in text and "\u2028" not in text
    assert json.loads(text) == {"t": "</script><!--<script>&amp;\u2028"}


def test_ids_beyond_2_53_are_text_for_javascript():
    assert js_safe_id(2 ** 53 - 1) == 2 ** 53 - 1 and js_safe_id(503100000018603) == 503100000018603
    assert js_safe_id(2 ** 53 + 1) == str(2 ** 53 + 1) and js_safe_id(BIG) == str(BIG)


def _page_data(path):
    text = path.read_text(encoding="utf-8")
    m = re.search(r"var data = (\{.*?\});\n", text)
    return text, json.loads(m.group(1))


def test_html_map_escapes_file_names_crs_names_and_ids(tmp_path):
    rows, outlines = _rows_and_outlines([7, BIG])
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, f"Damage grades: {HOSTILE}.las", HOSTILE, CLASSES,
                   own_ids={7: HOSTILE, BIG: "\ud800 lone"})
    text, data = _page_data(path)
    script = text.split("var data = ", 1)[1].split("</script>", 1)[0]
    assert "<" not in script.split(";\n", 1)[0]  # the data hold no "<" the HTML parser could take
    assert HOSTILE not in text  # never raw, in the <title> nor in the script
    assert "<title>Damage grades: &lt;!--&lt;script&gt;" in text
    assert data["title"] == f"Damage grades: {HOSTILE}.las" and data["crs"].startswith("CRS: <!--<script>x")
    by_id = {f["properties"]["id"]: f for f in data["features"]}
    assert set(by_id) == {7, str(BIG)}  # the big ID exact, as text
    assert by_id[str(BIG)]["id"] == str(BIG)
    popup = by_id[7]["properties"]["popup"]
    assert "&lt;!--&lt;script&gt;x&lt;/script&gt;&lt;img src=x onerror=&quot;" in popup
    assert "\\ud800 lone" in by_id[str(BIG)]["properties"]["popup"]  # a lone surrogate escaped, not a crash


def test_html_map_with_hostile_names_draws_every_building_in_chromium(tmp_path):
    if CHROMIUM is None:
        pytest.skip("chromium is not installed: HTML map not opened")
    rows, outlines = _rows_and_outlines([7, 8, BIG])
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, f"Damage grades: {HOSTILE}.las", HOSTILE, CLASSES, own_ids={8: HOSTILE})
    dom = _chromium(tmp_path, "--dump-dom", path.resolve().as_uri())
    assert dom.returncode == 0, dom.stderr[-2000:]
    m = re.search(r'data-rendered-features="(\d+)"', dom.stdout)
    assert m and int(m.group(1)) == 3, "the page's script did not run to its end"
    assert "<title>Damage grades: &lt;!--&lt;script&gt;" in dom.stdout  # the page's own title, not a number
    labels = re.findall(r'class="leaflet-tooltip qs-id[^"]*"[^>]*>([^<]*)<', dom.stdout)
    assert sorted(labels) == sorted(["7", "8", str(BIG)])  # exact, not 1152921504606846976


def test_png_title_and_crs_are_plain_text_not_mathtext(tmp_path):
    rows, outlines = _rows_and_outlines([1])
    title = "Damage grades: post$\\foo{$.las \udcff"  # mathtext and a file name that is not UTF-8
    fig, ax = png_map._draw_map(rows, outlines, title, None, "EPSG:99999 $\\frac{$")
    assert ax.get_title() == "Damage grades: post$\\foo{$.las \\udcff"
    write_map_png(rows, outlines, tmp_path / "damage_map.png", title, crs="EPSG:99999 $\\frac{$")
    assert (tmp_path / "damage_map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
