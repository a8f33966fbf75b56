"""blender_scripts/generate_scenes.py through the bpy module (in-process and as a script),
and through a `blender` binary when one is on PATH."""
import hashlib
import importlib.util
import subprocess
import sys

import pytest

from addon import generation
from addon.generation_jobs import job_shares
from conftest import BLENDER, HAVE_BPY, REPO

SCRIPT = REPO / "blender_scripts" / "generate_scenes.py"
needs_bpy = pytest.mark.skipif(not HAVE_BPY, reason="bpy module not installed")


def _load():
    spec = importlib.util.spec_from_file_location("generate_scenes", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def gen():
    return _load()


def test_bad_arguments_exit_2(gen, capsys):
    for argv in (["--set", "town", "--dataset", "paper", "--out", "x"],
                 ["--set", "generic", "--dataset", "paper", "--buildings", "0", "--out", "x"],
                 ["--set", "generic", "--dataset", "paper", "--buildings", "many", "--out", "x"],
                 ["--set", "generic", "--dataset", "paper"]):
        with pytest.raises(SystemExit) as e:
            gen.main(argv)
        assert e.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'town'" in err and "must be at least 1" in err and "--out" in err


def test_a_grades_file_fixes_each_listed_building_and_names_what_is_wrong(gen, tmp_path, capsys):
    f = tmp_path / "g.json"
    f.write_text('{"3": 4, "5": 0}')
    assert generation.read_grades(f, [3, 5, 9]) == {3: 4, 5: 0, 9: 0}
    for text, wanted in (('{"7": 3}', "building 7 is not in the --source bundle"),
                         ('{"3": 6}', "grade must be an integer 0-5, got 6"), ('{"3": true}', "got True"),
                         ('[1, 2]', "expected an object"), ('{"x": 1}', "'x' is not a building ID"), ("{", "cannot read")):
        f.write_text(text)
        with pytest.raises(ValueError, match=wanted):
            generation.read_grades(f, [3, 5, 9])
    for argv in (["--set", "generic", "--dataset", "mixed", "--grades", str(f), "--out", "x"],
                 ["--set", "bundle", "--source", "s", "--dataset", "mixed", "--grades", str(f), "--grade-mix", "0:1",
                  "--out", "x"]):
        with pytest.raises(SystemExit):
            gen.parse_args(argv)
    err = capsys.readouterr().err
    assert "--grades is only used with --set bundle --dataset mixed" in err and "give one" in err


def test_blender_style_arguments(gen):
    a, _ = gen.parse_args(gen._script_argv(["blender", "-b", "-P", "x.py", "--", "--set", "region", "--dataset",
                                            "mixed", "--out", "o"]))
    assert (a.set_name, a.dataset, a.buildings, a.seed) == ("region", "mixed", 112, 0)


def test_out_is_a_file(gen, tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "2", "--out", str(f)]) == 2


@needs_bpy
def test_paper_dataset_reads_back_and_resumes(gen, bpy_registered, tmp_path, capsys):
    from quakescan.formats.scene import read_scene
    out = tmp_path / "paper"
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "8", "--seed", "3",
                     "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["post_destruction", "post_extreme", "post_heavy", "pre"]
    scenes = {n: read_scene(out / n) for n in names}
    ids = [b.id for b in scenes["pre"].buildings]
    assert ids == list(range(1, 9))
    for n, g in (("post_heavy", 3), ("post_extreme", 4), ("post_destruction", 5)):
        sc = scenes[n]
        assert sc.epoch == "post" and [b.id for b in sc.buildings] == ids
        assert {b.grade for b in sc.buildings} == {g}
        assert all(b.patterns for b in sc.buildings)
    assert scenes["pre"].epoch == "pre" and {b.grade for b in scenes["pre"].buildings} == {0}
    assert (scenes["pre"].face_building == 0).any()  # terrain
    err = capsys.readouterr().err
    assert "pre: wrote" in err and "post_destruction: wrote" in err
    # resume: finished bundles are skipped and left byte-identical
    before = _digest(out)
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.ply")}
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "8", "--seed", "3",
                     "--out", str(out)]) == 0
    assert "skipped" in capsys.readouterr().err
    assert _digest(out) == before and {p: p.stat().st_mtime_ns for p in out.rglob("*.ply")} == mtimes
    # an interrupted run leaves a missing bundle: only that one is made again
    import shutil
    shutil.rmtree(out / "post_extreme")
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "8", "--seed", "3",
                     "--out", str(out)]) == 0
    assert _digest(out) == before
    # other settings into the same folder: refused unless --force
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "8", "--seed", "4",
                     "--out", str(out)]) == 1
    assert "other settings" in capsys.readouterr().err
    assert gen.main(["--set", "generic", "--dataset", "paper", "--buildings", "8", "--seed", "4",
                     "--out", str(out), "--force"]) == 0
    assert _digest(out) != before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@needs_bpy
def test_same_seed_same_bytes_mixed_region(gen, bpy_registered, tmp_path):
    from quakescan.formats.scene import read_scene
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for out, seed in ((a, 5), (b, 5), (c, 6)):
        assert gen.main(["--set", "region", "--dataset", "mixed", "--buildings", "12", "--seed", str(seed),
                         "--out", str(out)]) == 0
    assert sorted(p.name for p in a.iterdir()) == ["post", "pre"]
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)
    post = read_scene(a / "post")
    grades = [x.grade for x in post.buildings]
    assert all(0 <= g <= 5 for g in grades)
    for x in post.buildings:
        if x.grade <= 1:
            assert x.patterns == []
    assert all(x.material in ("masonry", "reinforced_concrete") for x in post.buildings)


@needs_bpy
def test_script_runs_with_python_and_bpy_module(gen, bpy_registered, tmp_path):
    args = ["--set", "region", "--dataset", "mixed", "--buildings", "5", "--seed", "1"]
    r = subprocess.run([sys.executable, str(SCRIPT), *args, "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "done in" in r.stderr
    assert (tmp_path / "o" / "post" / "scene.json").is_file()
    # same bytes in another process (no hash-order or session dependence)
    assert gen.main([*args, "--out", str(tmp_path / "i")]) == 0
    assert _digest(tmp_path / "o") == _digest(tmp_path / "i")
    r = subprocess.run([sys.executable, str(SCRIPT), "--set", "region", "--dataset", "bogus", "--out", "x"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "invalid choice" in r.stderr


@needs_bpy
def test_jobs_make_the_same_bytes_in_several_processes(gen, bpy_registered, tmp_path, capsys):
    args = ["--set", "generic", "--dataset", "paper", "--buildings", "4", "--seed", "2"]
    assert gen.main([*args, "--out", str(tmp_path / "one")]) == 0
    r = subprocess.run([sys.executable, str(SCRIPT), *args, "--jobs", "3", "--out", str(tmp_path / "three")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "4 scenes in 3 processes" in r.stderr
    assert _digest(tmp_path / "one") == _digest(tmp_path / "three")
    # a finished run resumes to nothing in the parent: no child is started
    r = subprocess.run([sys.executable, str(SCRIPT), *args, "--jobs", "3", "--out", str(tmp_path / "three")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "nothing to do" in r.stderr and "processes" not in r.stderr


def _tree(folder):
    """Digest of every file by its path under `folder` (hidden leftovers included)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@needs_bpy
@pytest.mark.slow
def test_jobs_share_out_the_collapses_of_a_scene_with_the_same_bytes_and_resume(tmp_path):
    import json
    args = ["--set", "small", "--dataset", "mixed", "--grade-mix", "0:1,4:2,5:2", "--seed", "2", "--damage", "physics"]

    def gen_run(*extra):
        r = subprocess.run([sys.executable, str(SCRIPT), *args, *extra], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stderr

    def simulated(err):
        return err.count("collapsed in") + err.count("did not come to rest")

    gen_run("--out", str(tmp_path / "one"))
    err = gen_run("--jobs", "2", "--out", str(tmp_path / "two"))
    assert "collapses in 2 processes" in err and simulated(err) == 4  # every grade-4/5 building, once
    post = json.loads((tmp_path / "two" / "post" / "scene.json").read_text())
    assert any(p["name"] == "physics_collapse" for b in post["buildings"] for p in b["patterns"])
    assert _tree(tmp_path / "one") == _tree(tmp_path / "two")  # no part file is left behind either
    # an interrupted run keeps the collapses it finished: only the missing one is simulated again
    out = tmp_path / "two"
    (out / "post" / "scene.json").unlink()
    claims = tmp_path / "claims"
    claims.mkdir()
    gen_run("--out", str(out), "--collapse-claims", str(claims))  # what a --jobs child does, alone
    parts = sorted((out / ".post.collapses").glob("*.npz"))
    assert len(parts) == 4
    parts[1].unlink()
    err = gen_run("--jobs", "2", "--out", str(out))
    assert simulated(err) == 1
    assert _tree(tmp_path / "one") == _tree(out)


def test_job_shares_balance_collapses_by_physics(gen):
    todo = [("pre", None, {}), ("post_heavy", {1: 3, 2: 3}, {}), ("post_extreme", {1: 4, 2: 4}, {}),
            ("post_destruction", {1: 5, 2: 5}, {})]
    # with physics the two collapse scenes go to different processes, one cheap scene beside each
    shares = job_shares(todo, 2, "physics")
    assert len(shares) == 2 and all(len(s) == 2 for s in shares)
    assert {"post_extreme", "post_destruction"} == {n for s in shares for n in s if n.endswith(("extreme", "destruction"))}
    assert not any({"post_extreme", "post_destruction"} <= set(s) for s in shares)
    # paper scenes: one grade for every building
    paper = [("pre", None, {}), ("post_heavy", 3, {}), ("post_extreme", 4, {}), ("post_destruction", 5, {})]
    shares = job_shares(paper, 2, "physics", buildings=112)
    assert not any({"post_extreme", "post_destruction"} <= set(s) for s in shares) and len(shares) == 2
    assert sorted(sum(job_shares(todo, 8, "patterns"), [])) == sorted(t[0] for t in todo)
    assert len(job_shares(todo, 8, "patterns")) == 4 and len(job_shares(todo, 1, "physics")) == 1


@pytest.mark.skipif(BLENDER is None, reason="no blender binary on PATH")
@pytest.mark.slow
def test_script_runs_inside_blender(tmp_path):
    cmd = [BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "-P", str(SCRIPT), "--",
           "--set", "generic", "--dataset", "paper", "--buildings", "3", "--seed", "1", "--out", str(tmp_path / "o")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "o" / "post_destruction" / "scene.json").is_file()
    bad = subprocess.run(cmd[:-2] + ["--buildings", "0"], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0


def test_grade_mix_gives_exact_counts(gen, bpy_registered, tmp_path):
    """--grade-mix: the paper's evaluation set has exact class counts, not random draws."""
    import collections
    import json

    out = tmp_path / "mix"
    assert gen.main(["--set", "region", "--dataset", "mixed", "--grade-mix", "0:3,3:2,4:2,5:3", "--seed", "4",
                     "--out", str(out)]) == 0
    doc = json.loads((out / "post" / "scene.json").read_text())
    assert collections.Counter(b["grade"] for b in doc["buildings"]) == {0: 3, 3: 2, 4: 2, 5: 3}
    assert doc["generator"]["grade_mix"] == {"0": 3, "3": 2, "4": 2, "5": 3}


@pytest.mark.parametrize("argv", [["--dataset", "paper", "--grade-mix", "0:3"],
                                  ["--dataset", "mixed", "--grade-mix", "0:3,9:1"],
                                  ["--dataset", "mixed", "--grade-mix", "0:3", "--buildings", "5"]])
def test_bad_grade_mix_exits_2(gen, argv, tmp_path):
    with pytest.raises(SystemExit) as e:
        gen.main(["--set", "region", *argv, "--out", str(tmp_path / "x")])
    assert e.value.code == 2


def test_origin_and_crs_arguments(gen, capsys):
    a, _ = gen.parse_args(["--set", "generic", "--dataset", "mixed", "--out", "o", "--origin", "367000,4690000",
                           "--crs", "EPSG:32633"])
    assert a.origin == (367000.0, 4690000.0, 0.0) and a.crs == "EPSG:32633"
    info = generation.generator_info(a, "pre")
    assert info["origin"] == [367000.0, 4690000.0, 0.0] and info["crs"] == "EPSG:32633"
    plain, _ = gen.parse_args(["--set", "generic", "--dataset", "mixed", "--out", "o"])
    assert not {"origin", "crs"} & set(generation.generator_info(plain, "pre"))
    for argv in (["--origin", "1,2,3,4"], ["--origin", "east"], ["--origin", "nan,0"], ["--origin", "1e300,0"],
                 ["--set", "bundle", "--source", "s", "--crs", "EPSG:32633"]):
        base = ["--set", "generic", "--dataset", "mixed", "--out", "o"]
        if argv[0] == "--set":
            base = ["--dataset", "mixed", "--out", "o"]
        with pytest.raises(SystemExit) as e:
            gen.parse_args(base + argv)
        assert e.value.code == 2, argv
    err = capsys.readouterr().err
    assert "expected X,Y or X,Y,Z" in err and "not used with --set bundle" in err


@needs_bpy
def test_origin_and_crs_reach_the_bundles(gen, bpy_registered, tmp_path):
    from quakescan.formats.scene import read_scene
    base = ["--set", "generic", "--dataset", "mixed", "--buildings", "2", "--seed", "4"]
    assert gen.main([*base, "--out", str(tmp_path / "local")]) == 0
    assert gen.main([*base, "--origin", "367000,4690000,12.5", "--crs", "EPSG:32633",
                     "--out", str(tmp_path / "utm")]) == 0
    local, utm = read_scene(tmp_path / "local" / "post"), read_scene(tmp_path / "utm" / "post")
    assert local.crs is None and list(local.origin) == [0.0, 0.0, 0.0]
    assert utm.crs == "EPSG:32633" and list(utm.origin) == [367000.0, 4690000.0, 12.5]
    assert (utm.vertices == local.vertices).all()  # the mesh stays in local metres around the origin
