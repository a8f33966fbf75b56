"""Atomic writes: a file appears under its final name complete, or not at all.

Every writer of the library goes through here. The content is written to `<name>.part` in
the same folder (a rename is atomic only within one file system), flushed to the disk
(`fsync`: a resumed run trusts a file because it is there, so it must not be an empty
shell after a power cut) and renamed over the final name; on any error the temporary file
is removed and the final name keeps what it had before.

    write_text(path, text); write_bytes(path, data); write_json(path, doc)
    with replacing(path) as tmp: laspy_or_savefig_or_savez(tmp)   # writers that need a path
    with open_replacing(path, "wb") as f: np.savez(f, ...)          # writers that take a file

A failure the system causes (disk full, no permission, the LAZ backend's LazrsError that
wraps them) becomes a `ResultsError` (or the `error` class asked for) naming the final
file and saying that nothing was left under it; a programming error stays what it is.
Standard library only: the Blender scripts can import it too.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from pathlib import Path

from ..errors import QuakeScanError, ResultsError

TEMP_SUFFIX = ".part"


def temp_path(path: str | os.PathLike) -> Path:
    """Where the content of `path` is written before it is renamed into place."""
    path = Path(path)
    return path.with_name(path.name + TEMP_SUFFIX)


def is_write_failure(e: BaseException) -> bool:
    """True for the errors a write raises when the system refuses it (disk full, permission,
    I/O): OSError, and the LAZ backend's LazrsError, which wraps them in its own class."""
    return isinstance(e, OSError) or type(e).__module__.split(".")[0] == "lazrs"


def write_failure_message(path, e: BaseException) -> str:
    """"<path>: cannot write (...)", saying plainly when the disk is full."""
    text = getattr(e, "strerror", None) or str(e) or type(e).__name__
    if getattr(e, "errno", None) == errno.ENOSPC or "no space left" in str(e).lower():
        return (f"{path}: cannot write: no space left on the device; free some space or write to another "
                "folder (nothing was left under this name)")
    return f"{path}: cannot write ({text}; nothing was left under this name)"


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable; some systems (Windows) cannot open a folder: the
    rename is then as durable as the system makes it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def commit(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Flush the finished temporary file `tmp` to the disk and rename it to `path` (for a
    streaming writer that manages its own temporary file, `quakescan.formats.pointcloud.LasChunkWriter`)."""
    tmp, path = Path(tmp), Path(path)
    _fsync_file(tmp)
    os.replace(tmp, path)
    _fsync_folder(path.parent)


@contextlib.contextmanager
def replacing(path: str | os.PathLike, error: type[QuakeScanError] = ResultsError):
    """Yield the temporary path to write `path`'s content to; on success it is flushed and
    renamed to `path`, on any failure removed (and `path` left as it was). The writer may
    make a folder there (a scene bundle) when `path` does not exist yet."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise error(f"{path}: cannot create its folder ({e.strerror or e})") from None
    if path.is_dir():
        raise error(f"{path}: is a folder; give a file name to write")
    tmp = temp_path(path)
    try:
        yield tmp
        commit(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            if tmp.is_dir():  # a writer that makes a folder (a scene bundle)
                shutil.rmtree(tmp)
            else:
                tmp.unlink(missing_ok=True)
        if isinstance(e, QuakeScanError) or not is_write_failure(e):
            raise
        raise error(write_failure_message(path, e)) from e


@contextlib.contextmanager
def open_replacing(path: str | os.PathLike, mode: str = "wb", error: type[QuakeScanError] = ResultsError,
                   **open_kwargs):
    """Yield a file opened on the temporary path (`mode` "w..." text or "wb"); closed and
    renamed to `path` on success, removed on failure."""
    if not mode.startswith("w"):
        raise ValueError(f"open_replacing writes a new file; mode {mode!r} is not a write mode")
    with replacing(path, error) as tmp, open(tmp, mode, **open_kwargs) as f:
        yield f


def write_bytes(path: str | os.PathLike, data: bytes, error: type[QuakeScanError] = ResultsError) -> None:
    with open_replacing(path, "wb", error) as f:
        f.write(data)


def write_text(path: str | os.PathLike, text: str, error: type[QuakeScanError] = ResultsError) -> None:
    """UTF-8, newlines as given (the same bytes on every system)."""
    with open_replacing(path, "w", error, encoding="utf-8", newline="") as f:
        f.write(text)


def write_json(path: str | os.PathLike, doc, indent: int | None = 1, error: type[QuakeScanError] = ResultsError,
               **dumps_kwargs) -> None:
    """`doc` as strict JSON with a final newline: NaN and infinities, which JSON does not
    have, are written null (`quakescan.runtime.text_safety.json_text`, the one place)."""
    from .text_safety import json_text

    write_text(path, json_text(doc, indent=indent, **dumps_kwargs) + "\n", error)


__all__ = ["TEMP_SUFFIX", "commit", "is_write_failure", "open_replacing", "replacing", "temp_path",
           "write_bytes", "write_failure_message", "write_json", "write_text"]
