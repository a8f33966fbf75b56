"""The models this user has loaded, kept ready to load again without skops.

skops checks a model file against an allow-list before it builds anything, and that costs:
the shipped model takes 1.7 s to load (0.4 s of it skops' own import, which walks every
scikit-learn module; 0.8 s building 7,330 arrays from the archive), against 0.6 s for the
same objects unpickled (scikit-learn's import, needed either way). Every `classify` pays
it; on a two-worker cluster the client pays it while both cores stream the epochs.

So once a file has passed every check, the DamageModel made of it is pickled here under a
name derived from the file's bytes and the versions that made it; a file with the same
bytes loads from here. The pickle is what this user's QuakeScan wrote, not the file's
content, and is trusted as Python trusts its own caches: only in a folder owned by this
user that no one else can write to. Anything else (another owner, a folder writable by
others, a broken entry) is not read, and the model is loaded through skops.

`QUAKESCAN_CACHE_DIR` moves the cache (models go to its `models/`), `off` turns it off;
without it, `$XDG_CACHE_HOME/quakescan` or `~/.cache/quakescan`.

The cache reads, writes and deletes only its own entries: files named as `entry_name` names
them (64 hex digits and `.pickle`) in a folder holding its marker (`runtime.output_folder`'s
FOLDER_MARKER). A `models/` folder without the marker is taken as the cache only when it
holds nothing but such entries (a cache of an earlier QuakeScan); one with other files is a
user's folder and left alone: no model is kept there and none of its files is pruned.
"""
from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import pickle
import re
import stat
import sys
from pathlib import Path

from .. import __version__

log = logging.getLogger(__name__)

CACHE_ENV = "QUAKESCAN_CACHE_DIR"
OFF = "off"
SUFFIX = ".pickle"
# The entries kept, the most recently used first: a few models and every retrained one a
# study loads, not every model ever tried (a random forest pickles to ~30 MB).
MAX_ENTRIES = 8
MAX_TOTAL_BYTES = 512 * 2 ** 20
ENTRY = re.compile(r"^[0-9a-f]{64}" + re.escape(SUFFIX) + "$")  # `entry_name`'s names, nothing else


def cache_folder() -> Path | None:
    """Where the models are kept, or None when the cache is off."""
    chosen = os.environ.get(CACHE_ENV)
    if chosen is not None:
        if chosen.strip().lower() in (OFF, ""):
            return None
        return Path(chosen).expanduser() / "models"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "quakescan" / "models"


def entry_name(data: bytes) -> str:
    """The entry of a model file with these bytes, for the versions running now: a pickle
    is read back only by the scikit-learn, numpy and QuakeScan that wrote it."""
    import numpy
    import sklearn

    versions = (f"quakescan {__version__} sklearn {sklearn.__version__} numpy {numpy.__version__} "
                f"python {sys.version_info.major}.{sys.version_info.minor} pickle {pickle.HIGHEST_PROTOCOL}")
    h = hashlib.sha256(data)
    h.update(b"\0" + versions.encode())
    return h.hexdigest() + SUFFIX


def recall(name: str, kind: type):
    """The model of class `kind` kept under `name` (`entry_name` of a model file's bytes), or None."""
    folder = cache_folder()
    if folder is None or not ENTRY.match(name) or not _private(folder, warn=True) or not _own(folder, adopt=False):
        return None
    path = folder / name
    try:
        with open(path, "rb") as f:
            if not _private_file(os.fstat(f.fileno())):
                log.warning("%s: not read (not this user's, or writable by others)", path)
                return None
            model = pickle.load(f)
    except FileNotFoundError:
        return None
    except Exception as e:  # a broken entry (an interrupted disk, another version): loaded anew
        log.debug("%s: not read (%s)", path, e)
        return None
    if not isinstance(model, kind):  # the caller's class: this module is below the model's
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # the most recently used are the ones kept
    return model


def remember(name: str, model) -> None:
    """Keep `model` under `name` (`entry_name` of the bytes it was made of) for the next
    load. Never fails the load: a cache that cannot be written is only logged."""
    folder = cache_folder()
    if folder is None:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        if not ENTRY.match(name) or not _private(folder, warn=False) or not _own(folder, adopt=True):
            return
        from ..runtime.atomic import open_replacing

        with open_replacing(folder / name, "wb") as f:
            os.fchmod(f.fileno(), 0o600)
            pickle.dump(model, f, protocol=pickle.HIGHEST_PROTOCOL)
        prune(folder)
    except Exception as e:
        log.debug("%s: model not kept (%s)", folder, e)


def prune(folder: Path, max_entries: int = MAX_ENTRIES, max_bytes: int = MAX_TOTAL_BYTES) -> None:
    """Delete all but the most recently used entries that fit `max_entries` and `max_bytes`:
    the cache's own entries only (their names, in a folder with its marker)."""
    if not _own(folder, adopt=False):
        return
    entries = []
    for p in folder.glob("*" + SUFFIX):
        if not ENTRY.match(p.name) or p.is_symlink():
            continue
        with contextlib.suppress(OSError):
            s = p.stat()
            entries.append((s.st_mtime, s.st_size, p))
    entries.sort(key=lambda e: e[0], reverse=True)
    total = 0
    for i, (_, size, p) in enumerate(entries):
        total += size
        if i >= max_entries or (i > 0 and total > max_bytes):
            with contextlib.suppress(OSError):
                p.unlink()


def _own(folder: Path, adopt: bool) -> bool:
    """True when `folder` is the cache's (its marker). `adopt`: mark a folder that holds
    nothing but entries and the atomic writer's temporaries (new, or an earlier QuakeScan's
    cache); a folder with anything else is a user's, said once in the log."""
    from ..runtime.atomic import TEMP_SUFFIX
    from ..runtime.output_folder import FOLDER_MARKER

    marker = folder / FOLDER_MARKER
    if marker.is_file() and not marker.is_symlink():
        return True
    if not adopt:
        return False
    others = [p.name for p in folder.iterdir()
              if not ENTRY.match(p.name) and not (p.name.startswith(".") and p.name.endswith(TEMP_SUFFIX))]
    if others:
        log.warning("%s: not used as the model cache: it holds files that are not the cache's (%s); set %s to a "
                    "folder of its own", folder, ", ".join(sorted(others)[:3]), CACHE_ENV)
        return False
    fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write("QuakeScan's model cache: it reads, keeps and deletes only its own entries here\n")
    return True


def _private_file(s: os.stat_result) -> bool:
    """Owned by this user and writable by no one else."""
    mine = not hasattr(os, "getuid") or s.st_uid == os.getuid()
    return mine and not s.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def _private(folder: Path, warn: bool) -> bool:
    try:
        s = folder.stat()
    except OSError:
        return False
    if _private_file(s) and stat.S_ISDIR(s.st_mode):
        return True
    if warn:
        log.warning("%s: the model cache is not used: the folder is not this user's or others can write to it "
                    "(models load through skops; set %s to another folder or to %r)", folder, CACHE_ENV, OFF)
    return False
