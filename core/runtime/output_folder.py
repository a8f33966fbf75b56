"""The output folder is QuakeScan's only where QuakeScan made it (docs/formats.md, "The output folder").

What a command that writes a folder of results asks before it writes, and how it deletes:

    check_output_path(out, "-o")                      # not '' nor another odd path
    refuse_replacing_inputs(outputs, inputs)          # no result replaces one of the inputs
    with exclusive_run(out, "classify"):              # one run in a folder at a time
        own_subfolder(out / ".blocks")                # a working folder, with QuakeScan's marker
        ...
        remove_own_subfolder(out / ".blocks")         # deleted only with its marker

`runtime.atomic` makes the files themselves (private temporaries, no link written through).
Standard library only.
"""
from __future__ import annotations

import contextlib
import logging
import os
import shutil
import socket
import time
from pathlib import Path

from ..errors import QuakeScanError, ResultsError

log = logging.getLogger(__name__)

LOCK_NAME = ".quakescan.lock"
# Inside every working folder QuakeScan makes in an output folder (.blocks, .graded, the model
# cache): the folder is its to empty and delete only while this file says so.
FOLDER_MARKER = ".quakescan-folder"


def check_output_path(path, flag: str = "-o", error: type[QuakeScanError] = QuakeScanError) -> Path:
    """`path` as a Path, or `error` for a path that names nothing to write: empty or blank
    (`-o ''` would write into the current folder), or holding a NUL or a line break."""
    text = os.fspath(path) if isinstance(path, os.PathLike) else path
    if not isinstance(text, str) or text.strip() == "":
        raise error(f"{flag} {text!r}: an empty output path; give a file or folder name")
    if "\0" in text or "\n" in text or "\r" in text:
        raise error(f"{flag} {text!r}: an output path cannot hold a NUL character or a line break")
    return Path(text)


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)  # hard and symbolic links too
    except OSError:
        pass
    return a.resolve() == b.resolve()


def refuse_replacing_inputs(outputs, inputs, error: type[QuakeScanError] = QuakeScanError,
                            command: str = "the command") -> None:
    """Refuse, before anything is written, a run where one of `outputs` (paths it writes,
    replaces or deletes; a folder counts with everything in it) is one of `inputs` ((path,
    what) pairs, None paths skipped): the results would overwrite their own input, and a
    rerun would read the results as its input."""
    outputs = [Path(o) for o in outputs if o is not None]
    for p, what in inputs:
        if p is None:
            continue
        p = Path(p)
        for o in outputs:
            inside = o.is_dir() and not o.is_symlink() and p.resolve().is_relative_to(o.resolve())
            if inside or _same(p, o):
                raise error(f"{p}: the {what} is {o}, which {command} would replace with its results; move it out "
                            "of the output folder or give another output folder")


@contextlib.contextmanager
def exclusive_run(folder, command: str, error: type[QuakeScanError] = ResultsError):
    """Hold the advisory lock of output folder `folder` (made if missing) while the block
    runs: a second run into the folder gets `error` naming the first run's process. The
    lock is `fcntl.flock` on `folder/.quakescan.lock`, which the system releases when its
    process ends however it ends: a lock file left by a killed run is found unlocked, said
    so and taken over. The file is removed on leaving, and the folder too when this run made
    it and left nothing in it. Where the system has no such locks (Windows, some network
    file systems) the run goes on unlocked, with a note in the log."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():  # not a folder: the command says what it expected
        yield
        return
    made = not folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise error(f"{folder}: cannot create the output folder ({e.strerror or e})") from None
    lock = folder / LOCK_NAME
    fd = _acquire(lock, command, error)
    try:
        yield
    finally:
        if fd is not None:
            with contextlib.suppress(OSError):
                os.unlink(lock)  # before the unlock: a run waiting on this file retries with a new one
            os.close(fd)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: a run that stopped before writing leaves no folder


def _acquire(lock: Path, command: str, error) -> int | None:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        log.info("%s: this system has no advisory file locks; two runs into this folder would not be stopped",
                 lock.parent)
        return None
    if lock.is_symlink() or (lock.exists() and not lock.is_file()):
        raise error(f"{lock}: not QuakeScan's lock file (a link or a folder); remove it")
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
        except OSError as e:
            raise error(f"{lock}: cannot create the output folder's lock file ({e.strerror or e})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read(fd) or "another QuakeScan process"
            os.close(fd)
            raise error(f"{lock.parent}: another run is writing into this output folder ({holder}); wait for it to "
                        "finish or give another output folder") from None
        except OSError as e:  # no locks on this file system (ENOLCK, EOPNOTSUPP)
            os.close(fd)
            log.info("%s: cannot lock the output folder (%s); two runs into it would not be stopped",
                     lock.parent, e.strerror or e)
            return None
        try:  # a holder that finished removed the file it locked: lock the one under the name now
            same = os.path.samestat(os.fstat(fd), os.stat(lock, follow_symlinks=False))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    left = _read(fd)
    if left:
        log.warning("%s: the lock of an earlier run that did not finish (%s) was taken over", lock.parent, left)
    holder = f"pid {os.getpid()} on {socket.gethostname()}, quakescan {command}, since {time.strftime('%Y-%m-%d %H:%M:%S')}"
    os.ftruncate(fd, 0)
    os.pwrite(fd, (holder + "\n").encode(), 0)
    return fd


def _read(fd: int) -> str:
    try:
        return os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
    except OSError:
        return ""


def own_subfolder(path, error: type[QuakeScanError] = ResultsError) -> Path:
    """`path` as a working folder of QuakeScan's: made with its marker, or kept when it has
    the marker already. A folder (or link) of that name without the marker is somebody
    else's: `error`, never emptied or used."""
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise error(f"{path}: QuakeScan keeps a working folder under this name, and this is a link or a file it did "
                    "not make; move it away or give another output folder")
    if path.is_dir():
        if not (path / FOLDER_MARKER).is_file():
            raise error(f"{path}: a folder QuakeScan did not make (no {FOLDER_MARKER} in it); it keeps its working "
                        "files under this name: move the folder away or give another output folder")
        return path
    try:
        path.mkdir(parents=True)
        (path / FOLDER_MARKER).write_text("made by QuakeScan: its working files, deleted when the run ends\n")
    except OSError as e:
        raise error(f"{path}: cannot create a working folder ({e.strerror or e})") from None
    return path


def is_own_subfolder(path) -> bool:
    path = Path(path)
    return path.is_dir() and not path.is_symlink() and (path / FOLDER_MARKER).is_file()


def remove_own_subfolder(path) -> bool:
    """Delete working folder `path` with its contents if it is QuakeScan's (its marker);
    anything else is left as it is. True when it was removed (or was not there)."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return True
    if not is_own_subfolder(path):
        return False
    shutil.rmtree(path, ignore_errors=True)
    return not path.exists()


def empty_own_subfolder(path, error: type[QuakeScanError] = ResultsError) -> Path:
    """`path` as an empty working folder of QuakeScan's (an old one of its own emptied)."""
    path = Path(path)
    if is_own_subfolder(path):
        shutil.rmtree(path, ignore_errors=True)
    return own_subfolder(path, error)


__all__ = ["FOLDER_MARKER", "LOCK_NAME", "check_output_path", "empty_own_subfolder", "exclusive_run",
           "is_own_subfolder", "own_subfolder", "refuse_replacing_inputs", "remove_own_subfolder"]
