"""Temporary files are QuakeScan's own: made exclusively under names nobody can plant in
advance, never a symbolic link followed; a final name that is a link is refused (issue 45)."""
import os
import socket

import pytest

from quakescan.cli import main
from quakescan.errors import PointCloudError, ResultsError
from quakescan.assessment.run import classify
from quakescan.errors import ClassifyError
from quakescan.runtime.atomic import (
    TEMP_MARKER,
    Temporary,
    open_replacing,
    remove_stale_temporaries,
    replacing,
    write_text,
)
from tests.safe_folder_pair import RESULTS, names, pair  # noqa: F401  (a fixture)

PLANTED = RESULTS + ["buildings.csv.part", ".checkpoint.jsonl"]


def _plant_links(out, victims):
    """A symbolic link at OUT/<name>.part for every output, each to a file of its own outside OUT."""
    out.mkdir()
    victims.mkdir()
    for name in PLANTED:
        victim = victims / name
        victim.write_text("the user's own file\n")
        os.symlink(victim, out / f"{name}.part")


def test_links_planted_at_the_old_temporary_names_are_never_followed(pair, tmp_path):  # noqa: F811
    out, victims = tmp_path / "out", tmp_path / "victims"
    _plant_links(out, victims)
    classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")
    for name in PLANTED:
        assert (victims / name).read_text() == "the user's own file\n", name  # nothing written through
        assert (out / f"{name}.part").is_symlink()  # and the user's links left as they were
    for name in RESULTS:
        assert (out / name).is_file() and not (out / name).is_symlink(), name
    assert names(out) == sorted(RESULTS + [f"{n}.part" for n in PLANTED])  # no temporary left behind


def test_an_output_name_that_is_a_link_is_refused_before_any_work(pair, tmp_path, capsys):  # noqa: F811
    out, victim = tmp_path / "out", tmp_path / "victim.csv"
    out.mkdir()
    victim.write_text("keep me\n")
    os.symlink(victim, out / "buildings.csv")
    with pytest.raises(ClassifyError, match=r"buildings\.csv: is a symbolic link"):
        classify(pair / "pre.las", pair / "post.las", out, model_path=pair / "model.skops")
    assert victim.read_text() == "keep me\n" and names(out) == ["buildings.csv"]
    assert (out / "buildings.csv").is_symlink()


def test_every_writer_refuses_a_link_and_never_opens_a_planted_temporary(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("keep")
    os.symlink(victim, tmp_path / "a.txt")
    with pytest.raises(ResultsError, match="symbolic link"):
        write_text(tmp_path / "a.txt", "x")
    with pytest.raises(PointCloudError, match="symbolic link"):
        with replacing(tmp_path / "a.txt", PointCloudError):
            pass
    os.symlink(victim, tmp_path / "b.txt.part")
    os.mkdir(tmp_path / "c.txt.part")  # a user's folder at the old temporary name
    (tmp_path / "c.txt.part" / "theirs").write_text("theirs")
    write_text(tmp_path / "b.txt", "b")
    with pytest.raises(RuntimeError):
        with open_replacing(tmp_path / "c.txt", "w") as f:
            f.write("half")
            raise RuntimeError
    assert victim.read_text() == "keep" and (tmp_path / "b.txt").read_text() == "b"
    assert (tmp_path / "c.txt.part" / "theirs").read_text() == "theirs" and not (tmp_path / "c.txt").exists()
    assert names(tmp_path) == ["a.txt", "b.txt", "b.txt.part", "c.txt.part", "victim"]


def test_temporaries_are_private_unpredictable_and_each_writers_own(tmp_path):
    a, b = Temporary(tmp_path / "x.csv"), Temporary(tmp_path / "x.csv")
    assert a.folder != b.folder and a.path.name == b.path.name == "x.csv"
    assert a.folder.parent == tmp_path and a.folder.name.startswith(".x.csv.") and a.folder.name.endswith(".part")
    assert (a.folder.stat().st_mode & 0o777) == 0o700  # mkdtemp: nobody else can put a name in it
    a.path.write_text("a")
    b.path.write_text("b")
    a.commit()
    assert (tmp_path / "x.csv").read_text() == "a"
    b.commit()  # two writers of one name: each renames its own complete file, never the other's
    assert (tmp_path / "x.csv").read_text() == "b" and names(tmp_path) == ["x.csv"]


def test_a_killed_writers_temporary_is_removed_and_nothing_else(tmp_path):
    dead = Temporary(tmp_path / "y.csv")
    (dead.folder / TEMP_MARKER).write_text(f"{socket.gethostname()} 999999999\n")  # a pid that is not running
    alive = Temporary(tmp_path / "z.csv")
    theirs = tmp_path / ".y.csv.abcdefgh.part"  # the pattern, but no marker: not ours
    theirs.mkdir()
    (theirs / "data").write_text("theirs")
    removed = remove_stale_temporaries(tmp_path)
    assert removed == [dead.folder] and alive.folder.is_dir() and (theirs / "data").is_file()
    assert remove_stale_temporaries(tmp_path, every=True) == [alive.folder]  # a caller holding the folder's lock
    assert names(tmp_path) == [theirs.name]


def test_scan_never_follows_a_planted_part_link_and_refuses_a_link_output(tmp_path, capsys):
    from quakescan.acquisition.scan import scan
    from quakescan.acquisition.survey import preset
    from quakescan.formats.synthetic import box_city

    victim = tmp_path / "victim.las"
    victim.write_bytes(b"keep")
    os.symlink(victim, tmp_path / "x.las.part")
    survey = preset("paper").replace(pulse_rate_hz=20_000.0)
    scan(box_city(rows=1, cols=1), survey, tmp_path / "x.las", seed=1)
    scan(box_city(rows=1, cols=1), survey, tmp_path / "y.las", seed=1, checkpoint=tmp_path / "y.las.lines")
    assert victim.read_bytes() == b"keep" and (tmp_path / "x.las").read_bytes()[:4] == b"LASF"
    assert (tmp_path / "x.las").read_bytes() == (tmp_path / "y.las").read_bytes()
    os.symlink(victim, tmp_path / "link.las")
    with pytest.raises(PointCloudError, match="symbolic link"):
        scan(box_city(rows=1, cols=1), survey, tmp_path / "link.las", seed=1)
    os.symlink(tmp_path / "elsewhere", tmp_path / "z.las.lines")  # its checkpoint folder planted as a link
    with pytest.raises(PointCloudError, match="z.las.lines: is a symbolic link"):
        scan(box_city(rows=1, cols=1), survey, tmp_path / "z.las", seed=1, checkpoint=tmp_path / "z.las.lines")
    (tmp_path / "w.las.lines").mkdir()
    (tmp_path / "w.las.lines" / "line_000000.json").write_text("the user's")
    with pytest.raises(PointCloudError, match="a folder the scan did not make"):
        scan(box_city(rows=1, cols=1), survey, tmp_path / "w.las", seed=1, checkpoint=tmp_path / "w.las.lines")
    assert (tmp_path / "w.las.lines" / "line_000000.json").read_text() == "the user's"
    assert victim.read_bytes() == b"keep" and not (tmp_path / "elsewhere").exists()
    assert names(tmp_path) == ["link.las", "victim.las", "w.las.lines", "x.las", "x.las.part", "y.las", "z.las.lines"]


def test_the_footprints_command_refuses_a_link_output(tmp_path, capsys):
    from quakescan.formats.scene import write_scene
    from quakescan.formats.synthetic import box_city

    write_scene(box_city(rows=1, cols=2), tmp_path / "scene")
    victim = tmp_path / "victim.geojson"
    victim.write_text("keep")
    os.symlink(victim, tmp_path / "fp.geojson")
    assert main(["footprints", str(tmp_path / "scene"), "-o", str(tmp_path / "fp.geojson")]) == 2
    assert "fp.geojson: is a symbolic link" in capsys.readouterr().err and victim.read_text() == "keep"
