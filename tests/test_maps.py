"""The maps a responder opens: the offline HTML map (in headless Chromium) and the QGIS style."""
import json
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import shapely.geometry

from quakescan.grades import GRADE_NAMES, long_label
from quakescan.results.building_result import BuildingResult, NOT_ASSESSABLE
from quakescan.results.colours import NOT_ASSESSABLE_COLOUR, colour_of, rgb8
from quakescan.results.outlines import OUTLINE_FOOTPRINT, Outline
from quakescan.results.qgis_style import GRADE_FIELD, write_qml
from quakescan.results.webmap import write_map_html

CLASSES = [0, 3, 4, 5]
E0, N0 = 367000.0, 4690000.0
GRADES = (0, 3, 4, 5, None)  # None: not assessable


def _city(n=15):
    """n buildings in a row of 3, grades cycling through GRADES, at UTM 33N coordinates."""
    rows, outlines = [], {}
    for i in range(1, n + 1):
        g = GRADES[(i - 1) % len(GRADES)]
        if g is None:
            rows.append(BuildingResult(i, 12, 300, False, "12 pre-event points < 50"))
        else:
            probs = {c: (0.7 if c == g else 0.1) for c in CLASSES}
            rows.append(BuildingResult(i, 900, 800, True, grade=g, probabilities=probs, share_changed=0.4,
                                         decided_by="model", confidence=0.7))
        x, y = E0 + 25 * ((i - 1) % 5), N0 + 22 * ((i - 1) // 5)
        outlines[i] = Outline(shapely.geometry.box(x, y, x + 16, y + 12), OUTLINE_FOOTPRINT)
    return rows, outlines


def _page_data(path):
    text = path.read_text()
    m = re.search(r"var data = (\{.*?\});\n", text)
    return text, json.loads(m.group(1).replace("<\\/", "</"))


def test_html_map_is_self_contained_with_a_popup_per_building(tmp_path):
    rows, outlines = _city()
    rows.append(BuildingResult(99, 0, 0, False, "no point inside the footprint"))  # no outline: not drawn
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, "Damage grades: post.las", "EPSG:32633", CLASSES)
    text, data = _page_data(path)
    # nothing to fetch: no remote or relative script/style/image references outside the inlined Leaflet CSS
    assert not re.search(r"<(script|link|img)[^>]+(src|href)=", text)
    assert "Leaflet 1.9.4" in text and "BSD 2-Clause License" in text and "L.CRS.Simple" in text
    assert len(data["features"]) == 15 and data["buildings"] == 16
    assert data["crs"] == "CRS: EPSG:32633 (WGS 84 / UTM zone 33N)"
    # local coordinates: world minus the origin, which is the frame's lower-left corner (10 m margin)
    assert data["origin"] == [E0 - 10, N0 - 10]
    f1 = data["features"][0]
    xs = [c[0] for c in f1["geometry"]["coordinates"][0]]
    assert min(xs) == pytest.approx(10.0) and max(xs) == pytest.approx(26.0)
    by_id = {f["id"]: f["properties"] for f in data["features"]}
    assert by_id[2]["colour"] == colour_of(3) and by_id[2]["name"] == "substantial to heavy"
    assert by_id[5]["colour"] == NOT_ASSESSABLE_COLOUR and "12 pre-event points &lt; 50" in by_id[5]["popup"]
    popup = by_id[4]["popup"]
    for want in ("building ID</th><td>4", "5 destruction", "0: 10 %, 3: 10 %, 4: 10 %, 5: 70 %",
                 "confidence</th><td>70 %", "900 / 800"):
        assert want in popup, want
    legend = {e["text"]: e["count"] for e in data["legend"]}
    assert legend == {"0 no damage": 3, "3 substantial to heavy (heavy)": 3, "4 very heavy (extreme)": 3,
                      "5 destruction": 3, "not assessable": 4}
    _no_part(tmp_path)


def _no_part(tmp_path):
    assert not [p for p in tmp_path.rglob("*") if ".part" in p.name]


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _chromium(tmp_path, *args):
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", *args]
    return subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=120)


def test_html_map_renders_in_headless_chromium(tmp_path):
    """A real browser draws every building, in the grade colours, with nothing from the network."""
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (.ci/setup installs Debian's chromium): HTML map not opened")
    rows, outlines = _city(23)
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, "Damage grades", "EPSG:32633", CLASSES)
    url = path.resolve().as_uri()
    dom = _chromium(tmp_path, "--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    m = re.search(r'data-rendered-features="(\d+)"', dom.stdout)
    assert m, "the page's script did not run"
    assert int(m.group(1)) == 23
    assert len(re.findall(r'<path[^>]*class="qs-building', dom.stdout)) == 23  # one SVG path per building
    assert dom.stdout.count('class="leaflet-tooltip qs-id') == 23  # every ID labelled (few buildings)

    shot = tmp_path / "shot.png"
    run = _chromium(tmp_path, f"--screenshot={shot}", "--window-size=900,650", url)
    assert run.returncode == 0 and shot.is_file(), run.stderr[-2000:]
    import matplotlib.image

    img = (matplotlib.image.imread(shot)[:, :, :3] * 255).round().astype(int)
    assert img.shape[:2] == (650, 900)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 20  # not blank
    for g in (0, 3, 4, 5, None):
        want = np.array(rgb8(colour_of(g)))
        share = (np.abs(img - want).max(axis=2) <= 3).mean()  # fill at opacity 0.9 over the grey background
        blended = np.rint(0.9 * want + 0.1 * np.array([0xf4, 0xf4, 0xf4]))
        share = max(share, (np.abs(img - blended).max(axis=2) <= 3).mean())
        assert share > 0.002, (g, share)  # each grade's colour covers a visible area


def test_qml_has_one_category_per_grade_in_the_map_colours(tmp_path):
    path = tmp_path / "buildings.qml"
    write_qml(path)
    text = path.read_text()
    assert text.startswith("<!DOCTYPE qgis")
    root = ET.fromstring(text.split("\n", 1)[1])
    r = root.find("renderer-v2")
    assert r.get("type") == "categorizedSymbol" and r.get("attr") == GRADE_FIELD
    cats = r.findall("categories/category")
    symbols = {s.get("name"): s for s in r.findall("symbols/symbol")}
    assert [c.get("value") for c in cats] == [str(g) for g in GRADE_NAMES] + [""]
    for c in cats:
        g = int(c.get("value")) if c.get("value") else None
        assert c.get("label") == (long_label(g) if g is not None else NOT_ASSESSABLE)
        sym = symbols[c.get("symbol")]
        colour = {o.get("name"): o.get("value") for o in sym.iter("Option") if o.get("name")}["color"]
        assert colour == ",".join(str(v) for v in rgb8(colour_of(g))) + ",255"
        assert {p.get("k"): p.get("v") for p in sym.iter("prop")}["color"] == colour
    assert root.find("labeling/settings/text-style").get("fieldName") == "building_id"
    _no_part(tmp_path)
