"""The model cache: a model file loaded once loads again without skops, with the same
predictions, and only from a private folder, for the same bytes and versions."""
import fractions
import logging
import os
import pickle

import numpy as np
import pytest

from quakescan.learning import model_cache
from quakescan.learning.model import DamageModel, ModelError, load_model, save_model, train_forest

pytestmark = pytest.mark.usefixtures("one_native_thread")  # tiny fits (tests/conftest.py)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv(model_cache.CACHE_ENV, str(folder))
    return folder / "models"


@pytest.fixture
def model_file(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    y = np.where(x[:, 0] > 0.5, 5, np.where(x[:, 1] > 0, 3, 0))
    rf = train_forest(x, y, n_estimators=10, max_depth=5, seed=1)
    save_model(DamageModel(rf, ["a", "b", "c"], 1.5, {}, {"trained_on": "synthetic"}), tmp_path / "m.skops")
    return tmp_path / "m.skops", {"a": x[:, 0], "b": x[:, 1], "c": x[:, 2]}


@pytest.fixture
def skops_loads(monkeypatch):
    """How often skops builds a model file."""
    import skops.io as sio

    calls = []
    real = sio.load
    monkeypatch.setattr(sio, "load", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def entries(folder):
    return sorted(folder.glob("*.pickle"))


def test_a_model_loads_from_the_cache_the_second_time_with_the_same_predictions(cache, model_file, skops_loads):
    path, table = model_file
    first = load_model(path)
    assert len(skops_loads) == 1 and len(entries(cache)) == 1
    assert entries(cache)[0].stat().st_mode & 0o777 == 0o600 and cache.stat().st_mode & 0o777 == 0o700
    again = load_model(path)
    assert len(skops_loads) == 1  # not built again
    np.testing.assert_array_equal(again.predict_proba(table), first.predict_proba(table))
    assert (again.feature_names, again.radius_m, again.provenance, again.no_change_rule) == \
           (first.feature_names, first.radius_m, first.provenance, first.no_change_rule)
    assert again is not first


def test_other_bytes_or_other_versions_are_built_again(cache, model_file, skops_loads, monkeypatch):
    import sklearn

    path, _ = model_file
    load_model(path)
    path.write_bytes(path.read_bytes() + b"\0")  # a zip still, other bytes
    load_model(path)
    assert len(skops_loads) == 2 and len(entries(cache)) == 2
    monkeypatch.setattr(sklearn, "__version__", "0.0.1")  # a pickle of another scikit-learn is not read
    load_model(path)
    assert len(skops_loads) == 3 and len(entries(cache)) == 3


def test_a_cache_others_can_write_to_is_not_read(cache, model_file, skops_loads, caplog):
    path, _ = model_file
    load_model(path)
    (entry,) = entries(cache)
    entry.chmod(0o666)
    with caplog.at_level(logging.WARNING, logger=model_cache.__name__):
        load_model(path)
    assert len(skops_loads) == 2 and "writable by others" in caplog.text
    entry.chmod(0o600)
    cache.chmod(0o777)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=model_cache.__name__):
        load_model(path)
    assert len(skops_loads) == 3 and "the model cache is not used" in caplog.text
    cache.chmod(0o700)
    load_model(path)
    assert len(skops_loads) == 3


def test_a_broken_or_foreign_entry_is_built_again_and_replaced(cache, model_file, skops_loads):
    path, table = model_file
    want = load_model(path).predict_proba(table)
    (entry,) = entries(cache)
    entry.write_bytes(entry.read_bytes()[:100])  # cut short
    np.testing.assert_array_equal(load_model(path).predict_proba(table), want)
    entry.write_bytes(pickle.dumps({"not": "a model"}))
    np.testing.assert_array_equal(load_model(path).predict_proba(table), want)
    assert len(skops_loads) == 3
    load_model(path)
    assert len(skops_loads) == 3  # the last build replaced the foreign entry


def test_a_refused_file_is_never_kept(cache, tmp_path, model_file):
    import skops.io as sio

    path, _ = model_file
    doc = sio.load(path, trusted=sio.get_untrusted_types(file=path))
    doc["payload"] = fractions.Fraction(1, 3)  # a type no damage model contains (nor skops trusts)
    sio.dump(doc, tmp_path / "evil.skops")
    for _ in range(2):
        with pytest.raises(ModelError, match=r"evil\.skops: refused: the file asks to build types"):
            load_model(tmp_path / "evil.skops")
    assert not cache.exists() or not entries(cache)


def test_off_keeps_nothing_and_an_unwritable_cache_does_not_fail_the_load(tmp_path, model_file, monkeypatch,
                                                                          skops_loads):
    path, _ = model_file
    monkeypatch.setenv(model_cache.CACHE_ENV, "off")
    load_model(path)
    load_model(path)
    assert len(skops_loads) == 2 and model_cache.cache_folder() is None
    (tmp_path / "file").write_text("a file where the cache's folder would be")
    monkeypatch.setenv(model_cache.CACHE_ENV, str(tmp_path / "file"))
    assert load_model(path).radius_m == 1.5


def test_without_the_variable_the_cache_is_the_users(monkeypatch, tmp_path):
    monkeypatch.delenv(model_cache.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert model_cache.cache_folder() == tmp_path / "quakescan" / "models"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert model_cache.cache_folder() == tmp_path / "home" / ".cache" / "quakescan" / "models"


def test_prune_keeps_the_most_recently_used_within_count_and_bytes(tmp_path):
    from quakescan.runtime.output_folder import FOLDER_MARKER

    (tmp_path / FOLDER_MARKER).write_text("")  # the cache's own folder (tests/test_safe_folder_deletes.py)
    names = [f"{i:064x}.pickle" for i in range(6)]  # entry_name's names
    for i, name in enumerate(names):
        p = tmp_path / name
        p.write_bytes(b"x" * 100)
        os.utime(p, (1000 + i, 1000 + i))
    model_cache.prune(tmp_path, max_entries=4, max_bytes=10_000)
    assert [p.name for p in entries(tmp_path)] == names[2:]
    model_cache.prune(tmp_path, max_entries=4, max_bytes=250)
    assert [p.name for p in entries(tmp_path)] == names[4:]
    model_cache.prune(tmp_path, max_entries=4, max_bytes=50)  # the newest is kept even past the bytes
    assert [p.name for p in entries(tmp_path)] == names[5:]


def test_a_file_larger_than_any_model_is_refused_before_it_is_read(tmp_path, model_file, monkeypatch):
    import zipfile

    from quakescan.learning import model

    path, _ = model_file
    with zipfile.ZipFile(path) as z:
        inflated = sum(i.file_size for i in z.infolist())
    padded = tmp_path / "padded.skops"  # a zip after junk still opens (as a self-extracting archive)
    padded.write_bytes(b"\0" * 2 * inflated + path.read_bytes())
    monkeypatch.setattr(model, "MAX_MODEL_UNCOMPRESSED_BYTES", inflated + 1)
    with pytest.raises(ModelError, match=r"padded\.skops: refused: the file holds"):
        load_model(padded)
