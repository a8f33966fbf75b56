"""The generator's one job description: the add-on's GenerationSpec (addon/generation_spec.py),
the library's mirror (quakescan.generator.GenerationSpec) and the script's two forms of it,
its options and `--spec FILE.json`. No Blender needed."""
import dataclasses
import importlib.util
import json

import pytest

from addon import generation_spec
from addon.generation_spec import GenerationSpec, SpecError
from conftest import REPO
from quakescan import generator

SCRIPT = REPO / "blender_scripts" / "generate_scenes.py"

FULL = dict(set_name="bundle", dataset="mixed", buildings=7, seed=41, out="o/x", source="s/pre", grade_mix=None,
            grades="g.json", details="typical", streetscape="typical", origin=None, crs=None, damage="both",
            settle_steps=90, force=True, jobs=3)
CITY = dict(FULL, set_name="generic", source=None, grades=None, grade_mix={0: 3, 4: 4},
            origin=(367000.0, 4690000.0, 12.5), crs="EPSG:32633")


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("generate_scenes_spec_test", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _fields(cls):
    return [(f.name, f.default) for f in dataclasses.fields(cls)]


def test_the_librarys_spec_and_the_add_ons_agree_field_for_field():
    assert _fields(generator.GenerationSpec) == _fields(GenerationSpec)
    for values in (FULL, CITY, dict(set_name="region", dataset="paper", buildings=None, seed=0, out="o")):
        doc = generator.GenerationSpec(**values).to_json()
        assert doc == GenerationSpec(**values).to_json()
        assert sorted(doc) == sorted(generation_spec.FIELDS)
        json.dumps(doc)  # plain JSON, paths as text


def test_a_spec_round_trips_through_its_json_file(tmp_path):
    for values in (FULL, CITY):
        job = GenerationSpec(**values).checked()
        job.write(tmp_path / "job.json")
        assert GenerationSpec.read(tmp_path / "job.json") == job
        assert GenerationSpec.from_json(json.loads(json.dumps(job.to_json()))).checked() == job
    # the library's document is what the add-on reads
    lib = generator.GenerationSpec(**{**CITY, "out": tmp_path / "o"})
    (tmp_path / "lib.json").write_text(json.dumps(lib.to_json()))
    wanted = GenerationSpec(**{**CITY, "out": str(tmp_path / "o")}).checked()
    assert GenerationSpec.read(tmp_path / "lib.json") == wanted


def test_the_options_and_the_spec_file_give_the_same_job(script, tmp_path):
    argvs = (["--set", "generic", "--dataset", "mixed", "--grade-mix", "0:3,4:4", "--seed", "41", "--out", "o/x",
              "--details", "typical", "--streetscape", "typical", "--origin", "367000,4690000,12.5",
              "--crs", "EPSG:32633", "--damage", "both", "--settle-steps", "90", "--force", "--jobs", "3"],
             ["--set", "bundle", "--source", "s/pre", "--dataset", "mixed", "--buildings", "7", "--grades", "g.json",
              "--seed", "41", "--out", "o/x", "--details", "typical", "--streetscape", "typical", "--damage", "both",
              "--settle-steps", "90", "--force", "--jobs", "3"],
             ["--set", "region", "--dataset", "paper", "--out", "o"])
    wanted = (GenerationSpec(**{**CITY, "buildings": None}).checked(), GenerationSpec(**FULL).checked(),
              GenerationSpec("region", "paper", None, 0, "o").checked())
    for argv, want in zip(argvs, wanted):
        job, share = script.parse_args(argv)
        assert job == want and share == {"only_scenes": None, "collapse_claims": None}
        want.write(tmp_path / "job.json")
        assert script.parse_args(["--spec", str(tmp_path / "job.json")]) == (job, share)
    assert wanted[2].buildings == generation_spec.DEFAULT_BUILDINGS
    job, share = script.parse_args(["--spec", str(tmp_path / "job.json"), "--only-scenes", "pre,post"])
    assert share["only_scenes"] == "pre,post"


@pytest.mark.parametrize("change, words", [
    (dict(seed=2 ** 32), "seed must be in 0..2^32-1"),
    (dict(seed=True), "seed must be in"),
    (dict(buildings=0), "--buildings: must be at least 1"),
    (dict(set_name="town"), "invalid choice: 'town'"),
    (dict(dataset="paper", grade_mix={0: 2}), "--grade-mix is only used with --dataset mixed"),
    (dict(grade_mix={9: 1}), "grades must be 0, 1, 2, 3, 4, 5"),
    (dict(buildings=5, grade_mix={0: 3}), "disagrees with --grade-mix"),
    (dict(set_name="bundle", source=None), "--set bundle needs --source"),
    (dict(set_name="bundle", source="s", crs="EPSG:1"), "not used with --set bundle"),
    (dict(source="s"), "--source is only used with --set bundle"),
    (dict(grades="g.json"), "--grades is only used with --set bundle --dataset mixed"),
    (dict(origin=(1.0, 2.0, 3.0, 4.0)), "expected X,Y or X,Y,Z"),
    (dict(origin=(float("nan"), 0.0)), "expected X,Y or X,Y,Z"),
    (dict(force="yes"), "force: expected true or false"),
])
def test_both_forms_refuse_the_same_jobs_in_the_same_words(script, tmp_path, capsys, change, words):
    job = dataclasses.replace(GenerationSpec("generic", "mixed", None, 1, "o"), **change)
    with pytest.raises(SpecError, match=words.replace("(", r"\(").replace("^", r"\^").replace(".", r"\.")):
        job.checked()
    (tmp_path / "job.json").write_text(json.dumps(generator.GenerationSpec(**dataclasses.asdict(job)).to_json()))
    with pytest.raises(SystemExit) as e:
        script.parse_args(["--spec", str(tmp_path / "job.json")])
    assert e.value.code == 2 and words in capsys.readouterr().err


def test_a_bad_spec_file_is_refused_by_name(script, tmp_path, capsys):
    f = tmp_path / "job.json"
    for text, words in (("{", "cannot read it as JSON"), ("[]", "expected an object"),
                        ('{"set_name": "generic"}', "missing field(s) dataset, buildings, seed, out"),
                        (json.dumps({**GenerationSpec("generic", "mixed", 2, 1, "o").to_json(), "colour": 1}),
                         "unknown field(s) colour")):
        f.write_text(text)
        with pytest.raises(SystemExit):
            script.parse_args(["--spec", str(f)])
        err = capsys.readouterr().err
        assert f"--spec {f}: " in err and words in err, err
    GenerationSpec("generic", "mixed", 2, 1, "o").write(f)
    with pytest.raises(SystemExit):
        script.parse_args(["--spec", str(f), "--seed", "3"])
    assert "--seed cannot come with it" in capsys.readouterr().err


def test_the_library_reports_a_refused_spec_in_its_own_words(tmp_path):
    """Through the real script (its refusal comes before Blender's modules load)."""
    with pytest.raises(generator.GeneratorError, match=r"refused .*seed 1.*: --grade-mix is only used") as e:
        generator.generate(generator.GenerationSpec("generic", "paper", None, 1, tmp_path / "o", grade_mix={0: 2}))
    assert "--spec" not in str(e.value) and "usage" not in str(e.value)
    assert not (tmp_path / "o").exists()

