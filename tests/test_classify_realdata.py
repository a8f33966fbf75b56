"""The real-world input path: AHN3 Delft (LAS 1.2 format 1, RD New) with BGT footprints."""
import csv
import json

import laspy
import numpy as np
import pytest

from quakescan.cli import main
from quakescan.assessment.run import classify
from quakescan.formats.pair import load_pair

pytestmark = pytest.mark.realdata


def _rows(path):
    with open(path, newline="") as f:
        return {int(r["building_id"]): r for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def ahn3(tmp_path_factory):
    from tests.conftest import SHARED_DATA

    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA / "ahn3_cropped_1.laz", SHARED_DATA / "ahn3_footprints_rd.geojson"


@pytest.fixture(scope="module")
def same_tile_result(ahn3, tmp_path_factory):
    las, fp = ahn3
    out = tmp_path_factory.mktemp("ahn3") / "res"
    summary = classify(las, las, out, footprints_path=fp)
    return summary, _rows(out / "buildings.csv"), out


def test_footprint_assignment_counts(ahn3):
    las, fp = ahn3
    data = load_pair(las, las, fp)
    ids = data.pre.building_id
    assert len(data.pre) == 640_510 and data.pre.crs == "EPSG:28992"
    assert len(np.unique(ids[ids > 0])) == 139  # of the 160 footprints; 21 lie off this tile
    assert len(data.footprint_ids_without_points) == 21
    assert (data.pre.classification[ids > 0] == 6).mean() > 0.9


def test_same_tile_as_both_epochs_is_undamaged_everywhere(same_tile_result):
    summary, rows, out = same_tile_result
    assert len(rows) == 160
    assessable = [r for r in rows.values() if r["assessable"] == "1"]
    assert len(assessable) > 100
    assert {r["label"] for r in assessable} == {"no damage"}
    assert all(float(r["share_changed"]) == 0.0 for r in assessable)
    off_tile = [r for r in rows.values() if r["assessable"] == "0"]
    assert all(r["predicted_grade"] == "" and r["reason"] for r in off_tile)
    gj = json.loads((out / "buildings.geojson").read_text())
    assert gj["crs"]["properties"]["name"].endswith("28992")
    assert {f["properties"]["outline"] for f in gj["features"]} == {"footprint"}


def test_shifted_post_epoch_is_aligned_and_a_real_collapse_is_found(ahn3, tmp_path):
    """Post = the same tile moved by (0.4, -0.3, 0.15) m, with the largest building
    pancaked: every non-ground point within 2 m of its footprint (eaves and walls overhang
    the BGT outline) squashed into a 0-2 m layer above the ground. ICP on the ground
    removes the shift, the collapsed building is found damaged, the rest stay undamaged."""
    import shapely

    from quakescan.formats.footprints import read_footprints

    las_path, fp = ahn3
    las = laspy.read(las_path)
    pre = load_pair(las_path, las_path, fp).pre
    ids, counts = np.unique(pre.building_id[pre.building_id > 0], return_counts=True)
    target = int(ids[np.argmax(counts)])
    footprints = read_footprints(fp)
    outline = footprints.polygons[int(np.flatnonzero(footprints.ids == target)[0])].buffer(2.0)
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z).copy()
    m = shapely.contains_xy(outline, x, y) & (pre.classification != 2)
    ground = np.median(z[shapely.contains_xy(outline.buffer(5.0), x, y) & (pre.classification == 2)])
    z[m] = ground + np.random.default_rng(0).uniform(0.0, 2.0, m.sum())
    las.x = np.asarray(las.x) + 0.4
    las.y = np.asarray(las.y) - 0.3
    las.z = z + 0.15
    post = tmp_path / "post.laz"
    las.write(post)
    assert main(["classify", "--pre", str(las_path), "--post", str(post), "--footprints", str(fp), "--align",
                 "--no-las", "-o", str(tmp_path / "res")]) == 0
    summary = json.loads((tmp_path / "res" / "summary.json").read_text())
    a = summary["alignment"]
    assert a["std_after_m"] < 0.1 and a["rmse_after_m"] < a["rmse_before_m"]
    rows = _rows(tmp_path / "res" / "buildings.csv")
    assert int(rows[target]["predicted_grade"]) >= 3 and float(rows[target]["share_changed"]) > 0.3
    others = [r for b, r in rows.items() if b != target and r["assessable"] == "1"]
    undamaged = sum(r["label"] == "no damage" for r in others) / len(others)
    assert undamaged > 0.95, undamaged


def _split(las_path, tmp_path, pre_mask, post_mask):
    las = laspy.read(las_path)
    paths = []
    for name, mask in (("pre", pre_mask(len(las.points))), ("post", post_mask(len(las.points)))):
        sub = laspy.LasData(las.header)
        sub.points = las.points[mask]
        sub.write(tmp_path / f"{name}.las")
        paths.append(tmp_path / f"{name}.las")
    return paths


@pytest.mark.slow
def test_two_random_halves_of_a_real_tile_are_a_no_change_pair(ahn3, tmp_path):
    """The issue's real no-change rescan: AHN3 tile 1 split into two random halves
    (default_rng(5).random(n) < 0.5, ~3.7 pts/m² each), real footprints, the shipped model.
    At most 1 of the ~116 assessable buildings is called damaged (the issue's target, 1 %;
    measured: 1, since the model also learns from realistic scenes; the model trained on
    bare scenes alone called 2, the paper's forest all 118: BENCHMARKS.md "transfer"); the
    rest are not assessable with a stated reason (too sparse for the model, too few points),
    never guessed."""
    las, fp = ahn3
    pre, post = _split(las, tmp_path, lambda n: np.random.default_rng(5).random(n) < 0.5,
                       lambda n: ~(np.random.default_rng(5).random(n) < 0.5))
    classify(pre, post, tmp_path / "res", footprints_path=fp, write_las=False)
    rows = _rows(tmp_path / "res" / "buildings.csv")
    ok = [r for r in rows.values() if r["assessable"] == "1"]
    damaged = [b for b, r in rows.items() if r["assessable"] == "1" and r["label"] != "no damage"]
    assert len(ok) >= 100
    assert len(damaged) <= 0.01 * len(ok), damaged
    assert all(r["reason"] for r in rows.values() if r["assessable"] == "0")
    assert all(0.0 <= float(r["confidence"]) <= 1.0 for r in ok)


def test_calibrate_lod_takes_footprints_for_real_clouds(ahn3, tmp_path, capsys):
    las, fp = ahn3
    pre, post = _split(las, tmp_path, lambda n: np.random.default_rng(5).random(n) < 0.5,
                       lambda n: ~(np.random.default_rng(5).random(n) < 0.5))
    assert main(["calibrate-lod", "--pre", str(pre), "--post", str(post), "--footprints", str(fp),
                 "-o", str(tmp_path / "lod.json")]) == 0
    lod = json.loads((tmp_path / "lod.json").read_text())
    assert lod["points"] > 10_000 and lod["lod_height_m"] >= 0.3 and lod["lod_curvature"] >= 0.2
    assert "--lod-height" in capsys.readouterr().out


def test_an_unregistered_post_epoch_is_aligned_without_being_asked_and_says_so(ahn3, tmp_path, capsys):
    """The same tile moved by (0.4, 0, 0.15) m as the post epoch, no --align: the epochs'
    stable ground disagrees by more than the model tolerates, so classify aligns them and
    says so; every building stays undamaged. --no-align takes them as they are (and the
    offset reads as damage on some buildings, which is why it is not the default: 21 of 133
    with the model shipped on 2026-11-27, more than half with the one before)."""
    las_path, fp = ahn3
    las = laspy.read(las_path)
    las.x = np.asarray(las.x) + 0.4
    las.z = np.asarray(las.z) + 0.15
    post = tmp_path / "post.laz"
    las.write(post)
    assert main(["classify", "--pre", str(las_path), "--post", str(post), "--footprints", str(fp), "--no-las",
                 "-o", str(tmp_path / "auto")]) == 0
    assert "disagreed by up to 0.4" in capsys.readouterr().out
    summary = json.loads((tmp_path / "auto" / "summary.json").read_text())
    reg = summary["registration"]
    assert reg["mode"] == "auto" and reg["applied"] and 0.38 < reg["offset_m"] < 0.5
    assert np.allclose(summary["alignment"]["translation_m"], [-0.4, 0.0, -0.15], atol=0.03)
    rows = [r for r in _rows(tmp_path / "auto" / "buildings.csv").values() if r["assessable"] == "1"]
    assert len(rows) > 100 and {r["label"] for r in rows} == {"no damage"}

    assert main(["classify", "--pre", str(las_path), "--post", str(post), "--footprints", str(fp), "--no-las",
                 "--no-align", "-o", str(tmp_path / "off")]) == 0
    summary = json.loads((tmp_path / "off" / "summary.json").read_text())
    assert summary["registration"] == {"mode": "off", "checked": False} and "alignment" not in summary
    rows = [r for r in _rows(tmp_path / "off" / "buildings.csv").values() if r["assessable"] == "1"]
    assert sum(r["label"] != "no damage" for r in rows) > 0.05 * len(rows)


def test_registered_epochs_are_checked_and_left_as_they_are(same_tile_result):
    summary, rows, out = same_tile_result
    reg = summary["registration"]
    assert reg["mode"] == "auto" and reg["checked"] and not reg["applied"]
    assert reg["offset_m"] < 0.01 and reg["tolerance_m"] == pytest.approx(0.2)
    assert "alignment" not in summary


def test_the_graded_cloud_keeps_every_input_attribute_and_stays_compressed(ahn3, same_tile_result):
    """AHN3 is LAZ with classes 1/2/6/9/26, GPS time, scan angle and point source IDs: the
    graded cloud is LAZ too (not a tenfold larger LAS) and keeps all of them."""
    las_path, fp = ahn3
    summary, rows, out = same_tile_result
    graded = out / "post_grades.laz"
    assert summary["post_grades"] == str(graded) and not (out / "post_grades.las").exists()
    assert graded.stat().st_size < 2 * las_path.stat().st_size
    src, got = laspy.read(las_path), laspy.read(graded)
    assert got.point_format.id == 7 and len(got.points) == len(src.points)
    assert np.array_equal(np.asarray(got.classification), np.asarray(src.classification))
    assert set(np.unique(np.asarray(got.classification)).tolist()) >= {2, 6}
    for name in ("gps_time", "intensity", "point_source_id", "return_number", "number_of_returns"):
        assert np.array_equal(np.asarray(got[name]), np.asarray(src[name])), name
    # format 1 keeps whole degrees; format 7 stores 0.006° steps (laspy's conversion)
    assert np.allclose(np.asarray(got.scan_angle) * 0.006, np.asarray(src.scan_angle_rank), atol=0.006)
    assert np.allclose(np.asarray(got.x), np.asarray(src.x), atol=0.001)
    ids = np.asarray(got.building_id)
    assert set(np.unique(ids[ids > 0]).tolist()) <= set(rows)


def test_text_footprint_ids_and_attributes_reach_the_results(ahn3, tmp_path):
    """BGT's gml_id is text: buildings are numbered, the CSV keeps each one's gml_id and the
    GeoJSON every footprint attribute (the 15-digit BAG ID among them)."""
    las_path, fp = ahn3
    assert main(["classify", "--pre", str(las_path), "--post", str(las_path), "--footprints", str(fp),
                 "--id-field", "gml_id", "--no-las", "--no-align", "-o", str(tmp_path / "res")]) == 0
    with open(tmp_path / "res" / "buildings.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 160 and all(r["footprint_id"].startswith("b") for r in rows)
    assert len({r["footprint_id"] for r in rows}) == 160
    gj = json.loads((tmp_path / "res" / "buildings.geojson").read_text())
    first = gj["features"][0]["properties"]
    assert first["footprint"]["gml_id"] == rows[0]["footprint_id"]
    assert len(str(first["footprint"]["identificatiebagpnd"])) >= 15


@pytest.mark.slow
def test_a_sparse_rescan_of_a_real_tile_shows_no_displaced_surface_by_chance(ahn3, tmp_path):
    """AHN3 tile 1 against itself thinned to 25 % (~2 pts/m² after): nothing changed, so a
    surface is 'displaced' only by chance. With the binomial test on the few post-event points
    near a core point (M3C2Settings.displaced_alpha) no core point of any building is; the
    share rule alone let chance patches through (a 3-point patch on one roof step read as a
    1.2 m sag)."""
    import dataclasses

    from quakescan.change.pipeline import describe_pair
    from quakescan.change.settings import settings_for_descriptors
    from quakescan.change.surface import SURFACE_DESCRIPTORS

    las, fp = ahn3
    pre, post = _split(las, tmp_path, lambda n: np.ones(n, bool),
                       lambda n: np.random.default_rng(5).random(n) < 0.25)
    pair = load_pair(pre, post, fp)
    settings = settings_for_descriptors(SURFACE_DESCRIPTORS, 1.5)
    assert settings.surface.m3c2.displaced_alpha == 0.01
    legacy = dataclasses.replace(settings, surface=dataclasses.replace(
        settings.surface, m3c2=dataclasses.replace(settings.surface.m3c2, displaced_alpha=0.0)))
    inward = {}
    for name, s in (("chance test", settings), ("share rule", legacy)):
        rows = [r for r in describe_pair(pair.pre, pair.post, s, workers=2) if r.assessable]
        inward[name] = sum(r.descriptors["m_inward"] + r.descriptors["m_outward"] > 0 for r in rows)
    assert inward["chance test"] == 0 < inward["share rule"], inward


@pytest.mark.slow
def test_random_halves_of_a_real_tile_see_no_interior_by_chance(ahn3, tmp_path, monkeypatch):
    """AHN3 tile 1 cut into two random halves of ~3.5 pts/m² by three permutation draws (seeds 0,
    2, 5): nothing changed, yet each half misses small low surfaces (a recess, a light well)
    the other hit a few times. Without the chance test (`MISSED_CHANCE` off) a 3-4-cell patch
    of them read as `s_interior_seen` 1.3-1.8 % on a building of every draw, and the shipped
    model of descriptors version 15 called that building heavily damaged; with it, no building
    of any draw sees an interior: at 3.5 pts/m² a patch needs about 2 m²."""
    import quakescan.change.surface as surface
    from quakescan.change.pipeline import describe_pair
    from quakescan.change.settings import settings_for_descriptors

    las, fp = ahn3
    settings = settings_for_descriptors(surface.SURFACE_DESCRIPTORS, 1.5)
    seen = {}
    n = laspy.open(las).header.point_count
    for seed in (0, 2, 5):
        first = np.zeros(n, bool)
        first[np.random.default_rng(seed).permutation(n)[: n // 2]] = True
        (tmp_path / str(seed)).mkdir()
        pre, post = _split(las, tmp_path / str(seed), lambda n: first, lambda n: ~first)
        pair = load_pair(pre, post, fp)
        for test_on in (True, False):
            monkeypatch.setattr(surface, "MISSED_CHANCE", 1e-3 if test_on else float("inf"))
            rows = [r for r in describe_pair(pair.pre, pair.post, settings, workers=2) if r.assessable]
            seen[seed, test_on] = sorted(r.building_id for r in rows if r.descriptors["s_interior_seen"] > 0)
    assert all(not seen[seed, True] for seed in (0, 2, 5)), seen
    assert all(seen[seed, False] for seed in (0, 2, 5)), seen
