"""Atomic writes: a file appears under its final name complete, or not at all.

Every writer of the library goes through here. The content is written to a temporary name
in the same folder (a rename is atomic only within one file system), flushed to the disk
(`fsync`: a resumed run trusts a file because it is there, so it must not be an empty
shell after a power cut) and renamed over the final name; on any error the temporary file
is removed and the final name keeps what it had before.

The temporary name is nobody else's (docs/formats.md, "The output folder"): a private
folder `.<name>.<random>.part/` made with `mkdtemp` (created exclusively, mode 0700) beside
the output holds the content under the output's own name until the rename. A name planted
in advance (a symbolic link at `<name>.part`, a folder of that name) is never opened,
followed or removed, and two writers of one name never share a temporary file. A final
name that is a symbolic link is refused (`check_output_name`): QuakeScan never makes one, so
it is somebody else's, and neither writing through it nor replacing it is ours to do.

    write_text(path, text); write_bytes(path, data); write_json(path, doc)
    with replacing(path) as tmp: laspy_or_savefig_or_savez(tmp)   # writers that need a path
    with open_replacing(path, "wb") as f: np.savez(f, ...)          # writers that take a file
    t = Temporary(path); ...write t.path...; t.commit()             # a streaming writer

A failure the system causes (disk full, no permission, the LAZ backend's LazrsError that
wraps them) becomes a `ResultsError` (or the `error` class asked for) naming the final
file and saying that nothing was left under it; a programming error stays what it is.
Standard library only: the Blender scripts can import it too.
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

from ..errors import QuakeScanError, ResultsError

TEMP_SUFFIX = ".part"
# Inside each private temporary folder: who made it (host and pid), so that a later run
# removes a killed writer's folder, and only folders that say they are QuakeScan's.
TEMP_MARKER = ".quakescan-temporary"


def check_output_name(path: str | os.PathLike, error: type[QuakeScanError] = ResultsError) -> Path:
    """`path` as a Path, or `error` when it cannot be an output file's name: empty (`-o ''`
    would write into the current folder), a folder, or a symbolic link (see the module's doc)."""
    if str(path).strip() == "" or Path(path).name in ("", ".", ".."):
        raise error(f"{str(path)!r}: not a file name to write (an empty or '.'/'..' output path)")
    path = Path(path)
    if "\0" in str(path):
        raise error(f"{str(path)!r}: a file name cannot hold a NUL character")
    if path.is_symlink():
        raise error(f"{path}: is a symbolic link, which QuakeScan did not make; it never writes through a link or "
                    "replaces one: remove the link or give the path of the file it points to")
    if path.is_dir():
        raise error(f"{path}: is a folder; give a file name to write")
    return path


class Temporary:
    """The private temporary file of one output `path` (see the module's doc): write to
    `.path`, then `commit()`; `discard()` (idempotent) removes it and its folder."""

    def __init__(self, path: str | os.PathLike, error: type[QuakeScanError] = ResultsError):
        self.final = check_output_name(path, error)
        try:
            self.final.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise error(f"{self.final}: cannot create its folder ({e.strerror or e})") from None
        try:
            self.folder = Path(tempfile.mkdtemp(prefix=f".{self.final.name}.", suffix=TEMP_SUFFIX,
                                                dir=self.final.parent))
            (self.folder / TEMP_MARKER).write_text(f"{socket.gethostname()} {os.getpid()}\n")
        except OSError as e:
            if hasattr(self, "folder"):
                shutil.rmtree(self.folder, ignore_errors=True)
            raise error(write_failure_message(self.final, e)) from e
        self.path = self.folder / self.final.name

    def commit(self) -> None:
        commit(self.path, self.final)
        self.discard()

    def discard(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)  # our own mkdtemp folder: nobody else's files


_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.[A-Za-z0-9_]{8}" + re.escape(TEMP_SUFFIX) + "$")


def remove_stale_temporaries(folder: str | os.PathLike, every: bool = False) -> list[Path]:
    """Remove the private temporary folders a killed writer left in `folder`: only folders of
    the temporary name pattern holding QuakeScan's marker, and of those (unless `every`, for a
    caller that holds the folder's lock) only the ones whose writer is not running on this
    host. Returns what was removed."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    host = socket.gethostname()
    for entry in entries:
        if not _TEMP_NAME.match(entry.name) or not entry.is_dir(follow_symlinks=False):
            continue
        try:
            who = (Path(entry.path) / TEMP_MARKER).read_text().split()
            made_on, pid = who[0], int(who[1])
        except (OSError, UnicodeDecodeError, ValueError, IndexError):
            continue  # no marker: not ours
        if not every and (made_on != host or _running(pid)):
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        removed.append(Path(entry.path))
    return removed


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # someone else's process (EPERM): running
        return True
    return True


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
    tmp = Temporary(path, error)
    try:
        yield tmp.path
        tmp.commit()
    except BaseException as e:
        tmp.discard()
        if isinstance(e, QuakeScanError) or not is_write_failure(e):
            raise
        raise error(write_failure_message(tmp.final, e)) from e


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


__all__ = ["TEMP_MARKER", "TEMP_SUFFIX", "Temporary", "check_output_name", "commit", "is_write_failure",
           "open_replacing", "remove_stale_temporaries", "replacing", "write_bytes", "write_failure_message",
           "write_json", "write_text"]
