"""No result replaces an input, and an output path must name something (issue 45): an input in
the output folder under a result's name is refused before anything is written, naming both."""
import shutil

import pytest

from quakescan.cli import main
from quakescan.formats.footprints import footprints_from_scene, write_footprints
from quakescan.formats.scene import read_scene, write_scene
from quakescan.formats.synthetic import box_city
from quakescan.assessment.run import classify
from quakescan.errors import ClassifyError
from tests.safe_folder_pair import names, pair  # noqa: F401  (a fixture)
from tests.scenes import HEIGHTS, UTM


def test_footprints_named_as_the_results_geojson_are_refused(pair, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    out.mkdir()
    fp = out / "buildings.geojson"
    write_footprints(footprints_from_scene(read_scene_of_pair()), fp)
    before = fp.read_bytes()
    with pytest.raises(ClassifyError, match=r"buildings\.geojson: the footprint file is .*buildings\.geojson, "
                                            r"which classify would replace"):
        classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops", footprints_path=fp)
    assert fp.read_bytes() == before and names(out) == ["buildings.geojson"]


def read_scene_of_pair():
    return box_city(rows=2, cols=3, height=HEIGHTS, origin=UTM)


@pytest.mark.parametrize("name", ["post_grades.las", "post_grades.laz", "summary.json"])
def test_a_post_event_cloud_under_a_result_name_is_refused_with_or_without_las(pair, tmp_path, name):  # noqa: F811
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(pair / "post.las", out / name)
    before = (out / name).read_bytes()
    for write_las in (True, False):
        with pytest.raises(ClassifyError, match=rf"the post-event point cloud is .*{name}, which classify would "
                                                "replace with its results; move it out of the output folder"):
            classify(pair / "pre.las", out / name, out, model_path=pair / "model.skops", write_las=write_las)
    assert (out / name).read_bytes() == before and names(out) == [name]


def test_a_hard_link_of_an_input_is_the_input(pair, tmp_path):  # noqa: F811
    import os

    out = tmp_path / "out"
    out.mkdir()
    os.link(pair / "model.skops", out / "damage_map.png")
    with pytest.raises(ClassifyError, match="the model file is"):
        classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")


def test_the_cli_names_both_and_writes_nothing(pair, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(pair / "post.las", out / "post_grades.las")
    assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(out / "post_grades.las"),
                 "--model", str(pair / "model.skops"), "-o", str(out), "--no-las"]) == 2
    err = capsys.readouterr().err
    assert f"quakescan: error: {out / 'post_grades.las'}: the post-event point cloud is" in err
    assert names(out) == ["post_grades.las"]


def test_footprints_of_a_scene_never_replace_the_scenes_own_files(tmp_path, capsys):
    scene = tmp_path / "scene"
    write_scene(box_city(rows=1, cols=2), scene)
    before = {p.name: p.read_bytes() for p in scene.iterdir()}
    for target in ("scene.json", "mesh.ply"):
        assert main(["footprints", str(scene), "-o", str(scene / target)]) == 2
        err = capsys.readouterr().err
        assert f"{scene / target}: the scene {'manifest' if target == 'scene.json' else 'mesh'} is" in err
        assert "which footprints would replace" in err
    assert {p.name: p.read_bytes() for p in scene.iterdir()} == before
    assert main(["footprints", str(scene), "-o", str(scene / "footprints.geojson")]) == 0  # a new file beside: fine
    assert read_scene(scene).buildings


def test_scan_never_writes_its_summary_or_trajectory_over_the_survey_or_scene(tmp_path, capsys):
    from quakescan.acquisition.survey import preset, write_survey_template

    scene = tmp_path / "scene"
    write_scene(box_city(rows=1, cols=1), scene)
    survey = tmp_path / "survey.json"
    write_survey_template(survey, preset("paper"))
    before = survey.read_bytes()
    assert main(["scan", str(scene), "--survey", str(survey), "-o", str(tmp_path / "x.las"),
                 "--summary", str(survey)]) == 2
    assert "the survey file is" in capsys.readouterr().err and survey.read_bytes() == before
    assert main(["scan", str(scene), "--survey", str(survey), "-o", str(tmp_path / "x.las"),
                 "--trajectory", str(scene / "scene.json")]) == 2
    assert "the scene manifest is" in capsys.readouterr().err
    assert names(tmp_path) == ["scene", "survey.json"]


@pytest.mark.parametrize("odd", ["", "   ", "a\nb", "x\0y"])
def test_an_empty_or_odd_output_path_is_an_error(pair, tmp_path, capsys, monkeypatch, odd):  # noqa: F811
    monkeypatch.chdir(tmp_path)  # where `-o ''` wrote every result before
    assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"),
                 "--model", str(pair / "model.skops"), "-o", odd]) == 2
    err = capsys.readouterr().err
    assert "quakescan: error: -o " in err and ("an empty output path" in err or "cannot hold" in err)
    assert main(["footprints", str(pair), "-o", odd]) == 2
    with pytest.raises(ClassifyError, match="-o"):
        classify(pair / "pre.las", pair / "post.las", odd, model_path=pair / "model.skops")
    assert names(tmp_path) == []


def test_evaluate_never_writes_its_metrics_over_the_truth(tmp_path, capsys):
    truth = tmp_path / "evaluation.json"
    truth.write_text("building_id,grade\n1,0\n")
    result = tmp_path / "buildings.csv"
    result.write_text("building_id,assessable,predicted_grade\n1,1,0\n")
    assert main(["evaluate", str(result), "--truth", str(truth)]) == 2
    assert f"{truth}: the truth is {truth}, which evaluate would replace" in capsys.readouterr().err
    assert truth.read_text() == "building_id,grade\n1,0\n"
