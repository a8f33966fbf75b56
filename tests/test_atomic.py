"""quakescan.runtime.atomic: a file appears under its name complete or not at all; a failed write leaves
the previous file as it was and no temporary file."""
import json

import numpy as np
import pytest

from quakescan.errors import PointCloudError, ResultsError
from quakescan.runtime.atomic import commit, open_replacing, replacing, write_bytes, write_json, write_text


class Boom(Exception):
    pass


def _names(folder):
    return sorted(p.name for p in folder.iterdir())


def test_each_writer_writes_the_whole_content_and_nothing_else(tmp_path):
    write_bytes(tmp_path / "a.bin", b"\x00\x01")
    write_text(tmp_path / "b.txt", "é\r\nline\n")  # UTF-8, newlines as given
    write_json(tmp_path / "sub" / "c.json", {"x": [1, 2]})
    with open_replacing(tmp_path / "d.npz", "wb") as f:
        np.savez(f, a=np.arange(3))
    with replacing(tmp_path / "e.txt") as tmp:
        assert tmp.name == "e.txt" and tmp.parent.parent == tmp_path  # a rename within one file system
        tmp.write_text("by path")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "b.txt").read_bytes() == "é\r\nline\n".encode()
    assert json.loads((tmp_path / "sub" / "c.json").read_text()) == {"x": [1, 2]}
    assert (tmp_path / "sub" / "c.json").read_text().endswith("\n")
    with np.load(tmp_path / "d.npz") as d:
        assert d["a"].tolist() == [0, 1, 2]
    assert (tmp_path / "e.txt").read_text() == "by path"
    assert _names(tmp_path) == ["a.bin", "b.txt", "d.npz", "e.txt", "sub"]


@pytest.mark.parametrize("how", ["path", "file", "folder"])
def test_a_failed_write_leaves_the_old_file_untouched_and_no_partial_file(tmp_path, how):
    target = tmp_path / "out.dat"
    target.write_bytes(b"the old, complete content")
    with pytest.raises(Boom):
        if how == "path":
            with replacing(target) as tmp:
                tmp.write_bytes(b"half")
                raise Boom
        elif how == "file":
            with open_replacing(target, "wb") as f:
                f.write(b"half")
                f.flush()
                raise Boom
        else:
            with replacing(tmp_path / "bundle") as tmp:  # a writer that makes a folder
                tmp.mkdir()
                (tmp / "mesh.ply").write_bytes(b"half")
                raise Boom
    assert target.read_bytes() == b"the old, complete content"
    assert _names(tmp_path) == ["out.dat"]


def test_a_new_file_that_fails_is_never_there(tmp_path):
    with pytest.raises(Boom):
        with open_replacing(tmp_path / "new.json", "w") as f:
            f.write("{")
            raise Boom
    assert _names(tmp_path) == []


def test_a_system_failure_names_the_file_in_the_error_asked_for(tmp_path):
    with pytest.raises(PointCloudError, match=r"x\.las: cannot write \(.*nothing was left under this name"):
        with replacing(tmp_path / "x.las", PointCloudError) as tmp:
            tmp.write_bytes(b"LASF")
            raise PermissionError(13, "Permission denied")
    assert _names(tmp_path) == []
    (tmp_path / "d").mkdir()
    with pytest.raises(ResultsError, match="is a folder"):
        write_text(tmp_path / "d", "x")
    with pytest.raises(ValueError, match="not a write mode"):
        with open_replacing(tmp_path / "r", "rb"):
            pass


def test_commit_renames_a_finished_temporary_file_over_the_old_one(tmp_path):
    (tmp_path / "a").write_text("old")
    (tmp_path / "a.new").write_text("new")
    commit(tmp_path / "a.new", tmp_path / "a")
    assert (tmp_path / "a").read_text() == "new" and _names(tmp_path) == ["a"]
