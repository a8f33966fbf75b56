"""QuakeScan deletes only what it recorded making (issue 45): its working folders carry its
marker, a user's folder of the same name is refused and kept; the model cache prunes only
its own entries."""
import os

import pytest

from quakescan.cli import main
from quakescan.learning import model_cache
from quakescan.errors import ClassifyError
from quakescan.runtime.output_folder import FOLDER_MARKER, own_subfolder, remove_own_subfolder
from tests.safe_folder_pair import RESULTS, names, pair  # noqa: F401  (a fixture)

distributed = pytest.importorskip("distributed")


def _user_folder(path):
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("the user's")
    return path


@pytest.mark.parametrize("name", [".blocks", ".graded"])
def test_a_users_working_folder_name_is_refused_and_kept(pair, tmp_path, name):  # noqa: F811
    from quakescan.distributed.engine import classify_distributed

    out = tmp_path / "out"
    _user_folder(out / name)
    with pytest.raises(ClassifyError, match=rf"{name}: a folder QuakeScan did not make \(no {FOLDER_MARKER}"):
        classify_distributed(pair / "pre.las", pair / "post.las", out, None, model_path=pair / "model.skops")
    assert (out / name / "notes.txt").read_text() == "the user's" and names(out) == [name]


def test_workers_1_makes_and_removes_only_its_own_folders(pair, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "out"
    _user_folder(out / "buildings.csv.part")  # a user's folder at a writer's temporary name: not QuakeScan's to remove
    _user_folder(out / ".blocks-mine")
    assert main(["classify", "--pre", str(pair / "pre.las"), "--post", str(pair / "post.las"), "--model",
                 str(pair / "model.skops"), "-o", str(out), "--workers", "1", "--memory-limit", "2GB"]) == 0
    assert names(out) == sorted(RESULTS + ["buildings.csv.part", ".blocks-mine"])
    assert (out / "buildings.csv.part" / "notes.txt").read_text() == "the user's"
    assert (out / ".blocks-mine" / "notes.txt").read_text() == "the user's"


def test_own_subfolders_are_removed_by_their_marker_only(tmp_path):
    theirs = _user_folder(tmp_path / "theirs")
    assert not remove_own_subfolder(theirs) and (theirs / "notes.txt").is_file()
    os.symlink(own_subfolder(tmp_path / "ours"), tmp_path / "link")
    assert not remove_own_subfolder(tmp_path / "link") and (tmp_path / "ours").is_dir()  # a link is nobody's to follow
    assert remove_own_subfolder(tmp_path / "ours") and not (tmp_path / "ours").exists()


def test_the_model_cache_never_prunes_a_users_pickles(tmp_path, monkeypatch):
    """QUAKESCAN_CACHE_DIR pointed at a user's folder whose models/ holds their own pickles."""
    users = tmp_path / "project" / "models"
    users.mkdir(parents=True)
    os.chmod(users, 0o700)
    for i in range(20):
        (users / f"run{i:02d}.pickle").write_bytes(b"the user's model")
    monkeypatch.setenv(model_cache.CACHE_ENV, str(tmp_path / "project"))
    name = "ab" * 32 + ".pickle"
    model_cache.remember(name, object())  # not a cache folder: nothing kept, nothing pruned
    model_cache.prune(users, max_entries=0, max_bytes=0)
    assert sorted(p.name for p in users.iterdir()) == [f"run{i:02d}.pickle" for i in range(20)]
    # the cache's own folder: only names of its pattern are entries, a user's pickle there is kept
    cache = tmp_path / "cache" / "models"
    monkeypatch.setenv(model_cache.CACHE_ENV, str(tmp_path / "cache"))
    model_cache.remember(name, {"a": 1})
    assert (cache / FOLDER_MARKER).is_file() and (cache / name).is_file()
    (cache / "mine.pickle").write_bytes(b"the user's")
    for i in range(12):
        model_cache.remember(f"{i:064x}.pickle", {"i": i})
    assert (cache / "mine.pickle").read_bytes() == b"the user's"
    assert len([p for p in cache.glob("*.pickle") if p.name != "mine.pickle"]) == model_cache.MAX_ENTRIES
    assert model_cache.recall("mine.pickle", object) is None  # never read as an entry either


def test_an_earlier_quakescans_cache_is_adopted(tmp_path, monkeypatch):
    cache = tmp_path / "models"
    cache.mkdir(mode=0o700)
    old = cache / (f"{1:064x}.pickle")
    old.write_bytes(b"old entry")
    monkeypatch.setenv(model_cache.CACHE_ENV, str(tmp_path))
    model_cache.remember(f"{2:064x}.pickle", {"b": 2})
    assert (cache / FOLDER_MARKER).is_file() and (cache / f"{2:064x}.pickle").is_file() and old.is_file()
