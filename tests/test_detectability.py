"""Say when it cannot see (core/change/detectability.py): the closed forms of Poisson sampling,
the lowest grade a building's data resolve, and how the result files and both maps carry it."""
import csv
import json
import math
import re

import numpy as np
import pytest
import shapely.geometry
from scipy import stats

from quakescan.change import detectability as D
from quakescan.results import png_map
from quakescan.results.building_result import BuildingResult
from quakescan.results.colours import colour_of, rgb8
from quakescan.results.csv_table import read_csv, write_csv
from quakescan.results.geojson import write_geojson
from quakescan.results.outlines import OUTLINE_FOOTPRINT, Outline
from quakescan.results.png_map import HATCH, HATCH_COLOUR, HEAVY_UNRESOLVED, write_map_png
from quakescan.results.webmap import legend_entries, write_map_html
from test_maps import _page_data

CLASSES = [0, 3, 4, 5]
E0, N0 = 367000.0, 4690000.0


# ------------------------------------------------------------------------------ closed forms

def test_the_chance_of_no_return_is_exp_minus_area_times_density():
    for area, d in ((0.5, 4.0), (2.0, 0.7), (10.0, 20.0), (0.0, 3.0)):
        assert D.chance_fewer_than(1, area, d) == pytest.approx(math.exp(-area * d), rel=1e-12, abs=1e-300)


@pytest.mark.parametrize("k", [1, 2, 3, 5, 12])
@pytest.mark.parametrize("mean", [0.1, 1.0, 2.5, 7.0, 30.0])
def test_fewer_than_k_returns_is_the_poisson_cdf(k, mean):
    assert D.chance_fewer_than(k, mean / 4.0, 4.0) == pytest.approx(stats.poisson.cdf(k - 1, mean), rel=1e-10)
    assert D.chance_fewer_than(0, mean, 1.0) == 0.0


def test_the_smallest_area_seen_once_at_95_percent_is_ln20_over_the_density():
    assert D.min_area_m2(4.0, 1, 0.05) == pytest.approx(math.log(20) / 4, rel=1e-12)
    assert D.min_area_m2(4.0, 1, 0.05) == pytest.approx(0.749, abs=5e-4)
    assert D.min_area_m2(10.0, 1, 0.01) == pytest.approx(math.log(100) / 10, rel=1e-12)
    assert D.min_area_m2(0.0) == math.inf and D.min_area_m2(3.0, 0) == 0.0


@pytest.mark.parametrize("k", [1, 2, 3, 6])
@pytest.mark.parametrize("alpha", [0.05, 0.025, 0.2])
def test_the_smallest_area_with_k_returns_solves_the_poisson_tail(k, alpha):
    d = 2.5
    a = D.min_area_m2(d, k, alpha)
    # exactly at confidence 1 - alpha there, and any smaller patch falls short of it
    assert stats.poisson.sf(k - 1, a * d) == pytest.approx(1 - alpha, rel=1e-10)
    assert stats.poisson.sf(k - 1, 0.999 * a * d) < 1 - alpha


def test_the_opening_needs_both_epochs_each_at_half_the_risk():
    got = D.min_opening_m2(4.0, 4.0)
    pre = math.log(1 / 0.025) / 4.0  # one return on the roof before, at 97.5 %
    post = D.min_area_m2(4.0, D.RETURNS_THROUGH_OPENING, 0.025)  # three through it after
    assert got == pytest.approx(max(pre, post), rel=1e-12) and got == pytest.approx(1.806, abs=1e-3)
    # the joint chance that both epochs resolve it is at least 1 - ALPHA
    both = (1 - D.chance_fewer_than(1, got, 4.0)) * (1 - D.chance_fewer_than(3, got, 4.0))
    assert both >= 1 - D.ALPHA
    # the sparser epoch decides: a dense drone after a sparse archive resolves what the archive does
    assert D.min_opening_m2(1.0, 100.0) == pytest.approx(math.log(40), rel=1e-12)
    assert D.min_opening_m2(100.0, 1.0) == pytest.approx(D.min_area_m2(1.0, 3, 0.025), rel=1e-12)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="density"):
        D.min_area_m2(-1.0)
    with pytest.raises(ValueError, match="alpha"):
        D.min_area_m2(4.0, 1, 1.5)
    with pytest.raises(ValueError, match="number of returns"):
        D.chance_fewer_than(1.5, 1.0, 1.0)
    with pytest.raises(ValueError, match="area"):
        D.chance_fewer_than(1, math.nan, 1.0)


def test_the_signatures_are_the_catalogues_smallest():
    from quakescan.change.surface import SEE_THROUGH_M

    assert [s.grade for s in D.SIGNATURES] == [3, 4, 5]
    assert D.HEAVY.share == 0.05 and D.EXTREME.share == 0.20 and D.DESTRUCTION.share == 0.20
    assert D.HEAVY.drop_m == SEE_THROUGH_M and D.EXTREME.drop_m == 1.0
    # each grade's smallest signature is no easier to resolve than the one below it
    for a, b in zip(D.SIGNATURES, D.SIGNATURES[1:]):
        assert a.share <= b.share and a.drop_m <= b.drop_m


# ------------------------------------------------------------------------------ per building

def test_a_dense_building_resolves_heavy_and_a_sparse_tiny_one_nothing():
    dense = D.of_building({"density_pre": 8.0, "density_post": 8.0, "area_m2": 120.0, "lowering_lod_m": 0.2})
    assert dense.detectable_grade == 3 and dense.min_opening_m2 == pytest.approx(D.min_opening_m2(8, 8))
    assert dense.min_lowering_m == 0.2
    tiny = D.of_building({"density_pre": 0.5, "density_post": 0.5, "area_m2": 20.0})
    assert tiny.detectable_grade is None and tiny.min_lowering_m is None
    # AHN3-like 4 pts/m²: heavy from 36 m² of footprint, extreme or destruction from 9 m²
    opening = D.min_opening_m2(4.0, 4.0)
    assert D.detectable_grade(opening / 0.05 * 1.001, opening) == 3
    assert D.detectable_grade(opening / 0.05 * 0.999, opening) == 4
    assert D.detectable_grade(opening / 0.20 * 0.999, opening) is None
    # a lowering resolution coarser than a 1 m drop leaves only destruction's larger drop
    assert D.detectable_grade(500.0, opening, 1.5) == 5 and D.detectable_grade(500.0, opening, 2.5) is None
    # unknown without densities or area (a model without surface descriptors, an old checkpoint)
    assert D.of_building({}) is None and D.of_building({"density_pre": 4.0, "density_post": 4.0}) is None
    assert D.of_building({"density_pre": 0.0, "density_post": 4.0, "area_m2": 50.0}).detectable_grade is None


def test_detectable_grade_never_gets_worse_with_density_or_area():
    densities = np.geomspace(0.05, 200.0, 60)
    for area in (8.0, 30.0, 80.0, 400.0):
        grades = [D.of_building({"density_pre": d, "density_post": d, "area_m2": area}).detectable_grade
                  for d in densities]
        rank = [99 if g is None else g for g in grades]
        assert rank == sorted(rank, reverse=True), (area, grades)
        assert grades[0] is None and grades[-1] == 3
    openings = [D.min_opening_m2(d, 2 * d) for d in densities]
    assert openings == sorted(openings, reverse=True)
    for d in (0.3, 1.0, 4.0):
        rank = [99 if (g := D.detectable_grade(a, D.min_opening_m2(d, d))) is None else g
                for a in np.geomspace(1.0, 2000.0, 50)]
        assert rank == sorted(rank, reverse=True)


def test_walls_resolve_heavy_damage_where_two_percent_of_the_facade_holds_the_smallest_hole():
    """A 40 m x 6 m facade band (240 m²): its 2 % (4.8 m²) must hold the smallest wall opening
    both epochs resolve. An airborne archive's 0.3 returns per m² of wall (AHN3-like) needs
    ln(40) / 0.3 = 12.3 m² for one return before: not resolvable; a drone's 20 resolve."""
    assert D.WALL_HEAVY_SHARE == 0.02
    sparse = D.min_opening_m2(0.3, 20.0)
    assert sparse == pytest.approx(math.log(40) / 0.3)
    assert not D.walls_resolved(240.0, sparse)
    assert D.walls_resolved(240.0, D.min_opening_m2(20.0, 20.0))
    assert not D.walls_resolved(0.0, 0.1) and not D.walls_resolved(240.0, math.inf)
    q = {"density_pre": 30.0, "density_post": 30.0, "area_m2": 100.0}
    assert D.of_building(q).walls_resolved is None  # no facade record: unknown
    q.update(wall_density_pre=0.3, wall_density_post=20.0, facade_m2=240.0)
    seen = D.of_building(q)
    assert seen.walls_resolved is False and seen.min_wall_opening_m2 == pytest.approx(sparse)
    assert seen.detectable_grade == 3  # the roofs resolve heavy damage all the same



def test_walls_are_resolved_only_where_every_open_facing_resolves_its_own_heavy_share():
    """Facades resolved together (40 returns per m² on 240 m²) but one 60 m² facing sampled at
    0.3: heavy damage confined to that facade (2 % of it, 1.2 m²) needs ln(40) / 0.3 = 12.3 m²
    for one return: the walls are not resolved; with that facing at 40 too, they are."""
    q = {"density_pre": 30.0, "density_post": 30.0, "area_m2": 100.0, "wall_density_pre": 40.0,
         "wall_density_post": 40.0, "facade_m2": 240.0}
    assert D.of_building(q).walls_resolved is True  # no facing recorded: the facades together
    q["wall_facings"] = [[60.0, 40.0, 40.0], [60.0, 40.0, 40.0], [60.0, 40.0, 40.0], [60.0, 0.3, 40.0]]
    assert D.facings_resolve(q["wall_facings"]) is False and D.of_building(q).walls_resolved is False
    q["wall_facings"][3] = [60.0, 40.0, 40.0]
    assert D.facings_resolve(q["wall_facings"]) is True and D.of_building(q).walls_resolved is True
    # a table's record of the rule (`realset.SAMPLING_FIELDS`) stands for the facings
    assert D.of_building({**q, "wall_facings": [], "wall_facings_resolved": 0.0}).walls_resolved is False
    assert D.facings_resolve([]) is None and D.facings_resolve([[60.0, float("nan"), 1.0]]) is None


def test_heavy_unresolved_is_a_building_graded_0_that_cannot_resolve_3():
    assert D.heavy_unresolved(0, None, 5.0) and D.heavy_unresolved(0, 4, 5.0)
    assert not D.heavy_unresolved(0, 3, 1.0)
    assert not D.heavy_unresolved(4, None, 5.0)  # a damaged building was seen damaged
    assert not D.heavy_unresolved(0, None, None) and not D.heavy_unresolved(None, None, 5.0)  # unknown


def test_the_pipeline_measures_each_buildings_area_and_lowering_resolution():
    from test_surface import epoch, scene

    from quakescan.change.pipeline import describe_pair
    from quakescan.change.settings import PipelineSettings
    from quakescan.change.surface import SurfaceSettings
    from quakescan.assessment.record import detectability_counts

    rng = np.random.default_rng(6)
    pre, post = scene(rng, 30, False), scene(rng, 30, False)
    s = PipelineSettings(surface=SurfaceSettings(), paper_descriptors=False)
    (row,) = describe_pair(epoch(pre), epoch(post), s, workers=1)
    q = row.quality
    # a 10 x 10 m footprint on 0.5 m cells, 21 or 22 a side where the walls' noise reaches the next cell
    assert q["area_m2"] == pytest.approx(q["cells"] * 0.25) and 100.0 <= q["area_m2"] <= 22 * 22 * 0.25
    assert s.surface.lod_floor_m <= q["lowering_lod_m"] < 1.0
    seen = D.of_building(q)
    assert seen.detectable_grade == 3 and seen.min_opening_m2 < 0.5  # ~30 pts/m²: a fraction of a m²

    class Model:  # every building asked: the result takes the row's detectability
        no_change_rule = True
        classes = [0, 3, 4, 5]
        feature_names = []

    from quakescan.learning.prediction import predict_rows

    (res,) = predict_rows([row], Model(), rule=True)
    assert (res.detectable_grade, res.min_opening_m2, res.min_lowering_m) == \
        (seen.detectable_grade, seen.min_opening_m2, seen.min_lowering_m)
    # its walls: 15 pts/m² (half the roof's, test_surface.sample_box) on a 40 m outline, 6 m high
    assert q["facade_m2"] == pytest.approx(40 * (6.0 - 0.5 - 1.0), rel=0.12)
    assert q["wall_density_pre"] == pytest.approx(15.0, rel=0.2) and q["wall_density_post"] == pytest.approx(15.0, rel=0.2)
    assert seen.walls_resolved and seen.min_wall_opening_m2 == pytest.approx(
        D.min_opening_m2(q["wall_density_pre"], q["wall_density_post"]))
    assert (res.walls_resolved, res.min_wall_opening_m2) == (seen.walls_resolved, seen.min_wall_opening_m2)
    assert detectability_counts([res]) == {"no_damage_heavy_unresolved": 0, "by_detectable_grade": {"3": 1},
                                           "walls_resolve_heavy": {"resolved": 1, "not_resolved": 0, "unknown": 0},
                                           "no_damage_walls_unresolved": 0}


# ------------------------------------------------------------------------------ result files

def _rows():
    """Graded 0 and blind to heavy damage (1, 2), graded 0 and seeing (3), damaged (4), not
    assessable (5), graded 0 without detectability (6: an older file, a paper model)."""
    p0 = {0: 0.91, 3: 0.03, 4: 0.03, 5: 0.03}
    return [
        BuildingResult(1, 300, 280, True, grade=0, probabilities=p0, share_changed=0.0, decided_by="model",
                         confidence=0.91, detectable_grade=4, min_opening_m2=3.25, min_lowering_m=0.31,
                         walls_resolved=False, min_wall_opening_m2=22.5),
        BuildingResult(2, 90, 80, True, grade=0, probabilities=p0, share_changed=0.0, decided_by="model",
                         confidence=0.91, detectable_grade=None, min_opening_m2=14.4),
        BuildingResult(3, 900, 850, True, grade=0, probabilities=p0, share_changed=0.0, decided_by="model",
                         confidence=0.91, detectable_grade=3, min_opening_m2=0.9, min_lowering_m=0.22,
                         walls_resolved=True, min_wall_opening_m2=0.6),
        BuildingResult(4, 900, 400, True, grade=5, probabilities={0: 0.1, 3: 0.1, 4: 0.1, 5: 0.7},
                         share_changed=0.6, decided_by="model", confidence=0.7, detectable_grade=3,
                         min_opening_m2=1.2, min_lowering_m=0.25),
        BuildingResult(5, 12, 300, False, "12 pre-event points < 50"),
        BuildingResult(6, 500, 510, True, grade=0, probabilities={0: 1.0, 3: 0.0, 4: 0.0, 5: 0.0},
                         share_changed=0.0, decided_by="no change", confidence=1.0),
    ]


def test_csv_round_trip_of_the_new_columns_and_old_files(tmp_path):
    path = tmp_path / "buildings.csv"
    write_csv(_rows(), path, CLASSES)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        cols, lines = reader.fieldnames, {int(r["building_id"]): r for r in reader}
    assert cols[-5:] == ["detectable_grade", "min_opening_m2", "min_lowering_m", "walls_resolved",
                         "min_wall_opening_m2"]
    assert (lines[1]["walls_resolved"], lines[1]["min_wall_opening_m2"]) == ("0", "22.5")
    assert (lines[3]["walls_resolved"], lines[3]["min_wall_opening_m2"]) == ("1", "0.6")
    assert lines[2]["walls_resolved"] == lines[5]["walls_resolved"] == ""
    assert (lines[1]["detectable_grade"], lines[1]["min_opening_m2"], lines[1]["min_lowering_m"]) == \
        ("4", "3.25", "0.31")
    assert (lines[2]["detectable_grade"], lines[2]["min_opening_m2"], lines[2]["min_lowering_m"]) == \
        ("", "14.4", "")  # resolves nothing: grade empty, opening given
    for unknown in (5, 6):
        assert lines[unknown]["detectable_grade"] == lines[unknown]["min_opening_m2"] == ""
    back = {r.building_id: r for r in read_csv(path)}
    for w in _rows():
        r = back[w.building_id]
        assert (r.detectable_grade, r.min_opening_m2, r.min_lowering_m, r.walls_resolved, r.min_wall_opening_m2) == \
            (w.detectable_grade, w.min_opening_m2, w.min_lowering_m, w.walls_resolved, w.min_wall_opening_m2)
        assert r.heavy_unresolved == w.heavy_unresolved
    assert [b for b, r in sorted(back.items()) if r.heavy_unresolved] == [1, 2]
    # a file written before the columns existed reads with them empty
    old = tmp_path / "old.csv"
    with open(path, newline="") as f, open(old, "w", newline="") as g:
        w = csv.writer(g, lineterminator="\n")
        for line in csv.reader(f):
            w.writerow(line[:-5])
    before = read_csv(old)
    assert [r.grade for r in before] == [0, 0, 0, 5, None, 0]
    assert all(r.detectable_grade is None and r.min_opening_m2 is None and not r.heavy_unresolved for r in before)
    # an opening no size resolves (an epoch without points over the building)
    blind = [BuildingResult(9, 60, 10, True, grade=0, probabilities={0: 1.0}, confidence=1.0,
                              min_opening_m2=math.inf)]
    write_csv(blind, path, CLASSES)
    (r,) = read_csv(path)
    assert r.min_opening_m2 == math.inf and r.detectable_grade is None and r.heavy_unresolved


def test_geojson_has_the_new_properties(tmp_path):
    rows = _rows()
    rows.append(BuildingResult(9, 60, 10, True, grade=0, probabilities={0: 1.0}, confidence=1.0,
                                 min_opening_m2=math.inf))
    outlines = {r.building_id: Outline(shapely.geometry.box(E0 + 20 * i, N0, E0 + 20 * i + 12, N0 + 10),
                                         OUTLINE_FOOTPRINT) for i, r in enumerate(rows)}
    path = tmp_path / "buildings.geojson"
    write_geojson(rows, outlines, path, "EPSG:32633", CLASSES)
    props = {f["id"]: f["properties"] for f in json.loads(path.read_text())["features"]}
    assert (props[1]["detectable_grade"], props[1]["min_opening_m2"], props[1]["min_lowering_m"]) == (4, 3.25, 0.31)
    assert props[2]["detectable_grade"] is None and props[2]["min_opening_m2"] == 14.4
    assert props[5]["detectable_grade"] is None and props[5]["min_opening_m2"] is None  # not assessable
    assert props[9]["min_opening_m2"] is None  # JSON has no infinity


# ------------------------------------------------------------------------------ maps

def _map_rows():
    rows = _rows()
    outlines = {r.building_id: Outline(shapely.geometry.box(E0 + 25 * i, N0, E0 + 25 * i + 16, N0 + 12),
                                         OUTLINE_FOOTPRINT) for i, r in enumerate(rows)}
    return rows, outlines


def test_png_map_hatches_the_buildings_graded_0_that_cannot_resolve_heavy(tmp_path):
    rows, outlines = _map_rows()
    fig, ax = png_map._draw_map(rows, outlines, "hatched", None, "EPSG:32633")
    (hatched,) = [c for c in ax.collections if c.get_gid() == "heavy-unresolved"]
    assert hatched.get_hatch() == HATCH and len(hatched.get_paths()) == 2
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[:2] == ["0 no damage: 4", HEAVY_UNRESOLVED.replace("; ", ";\n") + ": 2"]
    assert ax.get_legend().get_patches()[1].get_hatch() == HATCH
    # in the pixels: dark stripes over the green of buildings 1 and 2, plain green on 3 and 6
    path = tmp_path / "damage_map.png"
    write_map_png(rows, outlines, path, "hatched", crs="EPSG:32633")
    import matplotlib.image

    img = matplotlib.image.imread(path)[:, :, :3]
    fig.canvas.draw()
    h_px = img.shape[0]

    def dark_share(bid):
        x0, y0, x1, y1 = outlines[bid].geometry.bounds  # the lower left quarter: the ID label sits in the middle
        (ax0, ay0), (ax1, ay1) = ax.transData.transform([(x0 + 1, y0 + 1), (x0 + 0.4 * (x1 - x0), y0 + 0.4 * (y1 - y0))])
        patch = img[int(h_px - ay1):int(h_px - ay0), int(ax0):int(ax1)]
        green = np.abs(patch - np.array(rgb8(colour_of(0))) / 255).max(axis=2) < 2 / 255
        assert green.mean() > 0.3, bid  # the fill is still the grade's
        return (patch.max(axis=2) < 0.35).mean()

    assert dark_share(1) > 0.05 and dark_share(2) > 0.05
    assert dark_share(3) == 0.0 and dark_share(6) == 0.0
    # without such buildings the map has neither hatch nor legend entry
    fig, ax = png_map._draw_map(rows[2:], outlines, "plain", None, None)
    assert not [c for c in ax.collections if c.get_gid() == "heavy-unresolved"]
    assert not any(HEAVY_UNRESOLVED in t.get_text() for t in ax.get_legend().get_texts())


def test_html_map_stripes_them_and_says_why_in_the_popup(tmp_path):
    rows, outlines = _map_rows()
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, "Damage <grades>", "EPSG:32633", CLASSES)
    text, data = _page_data(path)
    assert '<pattern id="qs-hatch"' in text and 'url(#qs-hatch)' in text
    assert "Damage &lt;grades&gt;" in text
    by_id = {f["id"]: f["properties"] for f in data["features"]}
    assert [b for b, p in sorted(by_id.items()) if p["hatched"]] == [1, 2]
    p1, p2, p3 = by_id[1]["popup"], by_id[2]["popup"], by_id[3]["popup"]
    for want in ("lowest grade resolvable</th><td>4 very heavy (extreme)", "smallest opening resolvable</th><td>3.2 m²",
                 "smallest lowering resolvable</th><td>0.31 m", f"note</th><td>{HEAVY_UNRESOLVED}"):
        assert want in p1, want
    assert "lowest grade resolvable</th><td>none of grades 3-5" in p2 and "smallest lowering" not in p2
    assert "lowest grade resolvable</th><td>3 substantial to heavy (heavy)" in p3 and "note" not in p3
    assert "resolvable" not in by_id[5]["popup"] and "resolvable" not in by_id[6]["popup"]  # unknown
    legend = [(e["text"], e["count"], e.get("hatched", False)) for e in data["legend"]]
    assert legend[:2] == [("0 no damage", 4, False), (HEAVY_UNRESOLVED, 2, True)]
    assert not any(e.get("hatched") for e in legend_entries(rows[2:]))


def test_html_map_hatch_renders_in_headless_chromium(tmp_path):
    """A real browser fills the buildings blind to heavy damage with the stripes."""
    from test_maps import CHROMIUM, _chromium

    if CHROMIUM is None:
        pytest.skip("chromium is not installed (.ci/setup installs Debian's chromium): HTML map not opened")
    rows, outlines = _map_rows()
    path = tmp_path / "damage_map.html"
    write_map_html(rows, outlines, path, "Damage grades", "EPSG:32633", CLASSES)
    url = path.resolve().as_uri()
    dom = _chromium(tmp_path, "--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert len(re.findall(r'<path[^>]*class="qs-building qs-heavy-unresolved', dom.stdout)) == 2
    assert len(re.findall(r'<path[^>]*fill="url\(#qs-hatch\)"', dom.stdout)) == 2
    shot = tmp_path / "shot.png"
    run = _chromium(tmp_path, f"--screenshot={shot}", "--window-size=900,650", url)
    assert run.returncode == 0 and shot.is_file(), run.stderr[-2000:]
    import matplotlib.image

    img = (matplotlib.image.imread(shot)[:, :, :3] * 255).round().astype(int)
    stripe = np.rint(0.9 * np.array(rgb8(HATCH_COLOUR)) + 0.1 * np.array([0xf4, 0xf4, 0xf4]))
    assert (np.abs(img - stripe).max(axis=2) <= 3).mean() > 0.002  # the stripes cover a visible area
