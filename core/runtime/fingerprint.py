"""The one resume rule: an output is reused only when the fingerprint stored with it equals
the fingerprint the run would store now; otherwise it is made again, never silently reused.

A fingerprint (`make`) is what an output depends on, as JSON: what makes it (`kind`), the
identity of its inputs, its settings and the code and format version; `digest` is the
SHA-256 of that JSON in canonical form.

Identity of an input file:
- `content(path)`: SHA-256 of its bytes. For what is small next to the work it saves and
  may be rewritten in place with the same size and time (scene bundles, models, footprints,
  records): exact.
- `stat(path)`: resolved path, size and modification time. For point clouds: they are
  gigabytes, hashing one takes longer than many runs that reuse it, and every writer of
  the library replaces a cloud by renaming a new file over it (`quakescan.runtime.atomic`), which always
  gives it a new time; a moved or copied cloud counts as new (redone, never wrongly reused).
- `scene_fingerprint(scene)`: a Scene's arrays and manifest (a bundle is read first).

Where it is stored:
- beside the output, `OUT.fingerprint.json` (`is_current`, `record`, `forget`), with the
  output's size, so that a truncated or replaced output is made again; or
- inside the output's own JSON record where its format has one (classify's summary.json, a
  simulated cloud's acquisition record, `quakescan.acquisition.acquire`): `matches(doc, fp)`.

`forget` comes before the output is made again, `record` after it is complete: an
interruption in between leaves an output without a fingerprint, which is redone.
Standard library only (numpy only for a Scene object): the Blender scripts import it too.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from .atomic import write_json

FORMAT = "quakescan-fingerprint"
VERSION = 1
SUFFIX = ".fingerprint.json"


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def content(path: str | os.PathLike | None) -> dict | None:
    """Identity of a file by its bytes (None for no file: an optional input not given)."""
    if path is None:
        return None
    path = Path(path)
    return {"sha256": file_sha256(path), "bytes": path.stat().st_size}


def stat(path: str | os.PathLike | None) -> dict | None:
    """Identity of a large file by where it is, its size and its modification time."""
    if path is None:
        return None
    st = os.stat(path)
    return {"path": os.path.realpath(path), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def scene_fingerprint(scene) -> str:
    """A hash of a `quakescan.formats.scene.Scene`: its arrays, buildings, CRS, epoch, units and
    porous faces — all a simulator sees, so that a bundle read from disk and the same scene
    in memory hash alike, and a bundle rewritten with other bytes but the same scene does
    not make its clouds again."""
    import numpy as np

    h = hashlib.sha256()
    h.update(b"scene-object")
    for a in (scene.vertices, scene.faces, scene.face_building, scene.face_surface, scene.origin):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(json.dumps([b.to_json() for b in scene.buildings], sort_keys=True).encode())
    h.update(json.dumps([scene.crs, scene.epoch, scene.units]).encode())
    if scene.has_porous:  # only then: a scene without vegetation hashes as opaque faces, its outputs stay current
        h.update(np.ascontiguousarray(scene.face_porous, dtype=bool).tobytes())
        h.update(json.dumps(scene.transmission).encode())
    return h.hexdigest()


def _canonical(doc) -> str:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=True, default=_plain)


def _plain(o):
    """numpy scalars and arrays, paths and tuples as JSON."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"not JSON: {type(o).__name__}")


@dataclass(frozen=True)
class Fingerprint:
    """What an output depends on (see the module's doc); compare with `digest`."""

    kind: str
    inputs: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    code: dict = field(default_factory=dict)

    @property
    def digest(self) -> str:
        return hashlib.sha256(_canonical(self.to_json(with_digest=False)).encode()).hexdigest()

    def to_json(self, with_digest: bool = True) -> dict:
        doc = json.loads(_canonical({"kind": self.kind, "inputs": self.inputs, "settings": self.settings,
                                     "code": self.code}))
        return {"digest": self.digest, **doc} if with_digest else doc


def make(kind: str, inputs: dict | None = None, settings: dict | None = None, code: dict | None = None) -> Fingerprint:
    """The fingerprint of an output of `kind`; `code` adds versions of formats and algorithms
    to the QuakeScan version (always included: another QuakeScan may compute differently)."""
    return Fingerprint(kind, dict(inputs or {}), dict(settings or {}), {"quakescan": __version__, **(code or {})})


def matches(doc, fp: Fingerprint) -> bool:
    """Whether an output's own record `doc` (a dict, or None when unreadable) holds `fp`."""
    return isinstance(doc, dict) and doc.get("fingerprint") == fp.digest


def sidecar_path(output: str | os.PathLike) -> Path:
    """OUT.fingerprint.json beside the file or folder OUT."""
    output = Path(output)
    return output.with_name(output.name + SUFFIX)


def _size(output: Path) -> int | None:
    return output.stat().st_size if output.is_file() else None


def state(output: str | os.PathLike, fp: Fingerprint) -> str:
    """"current" (`output` exists, its fingerprint file holds `fp` and the size recorded with
    it), "missing" (no output), "unrecorded" (no readable fingerprint file), "other" (made
    from other inputs or settings) or "changed" (made so, but cut or replaced since)."""
    output = Path(output)
    if not output.exists():
        return "missing"
    try:
        doc = json.loads(sidecar_path(output).read_bytes())
    except (OSError, ValueError):
        return "unrecorded"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        return "unrecorded"
    if doc.get("digest") != fp.digest:
        return "other"
    return "current" if doc.get("output_bytes") == _size(output) else "changed"


def is_current(output: str | os.PathLike, fp: Fingerprint) -> bool:
    return state(output, fp) == "current"


def forget(output: str | os.PathLike) -> None:
    """Remove `output`'s fingerprint: it is about to be made again."""
    sidecar_path(output).unlink(missing_ok=True)


def record(output: str | os.PathLike, fp: Fingerprint) -> None:
    """Store `fp` beside the complete `output`."""
    output = Path(output)
    write_json(sidecar_path(output), {"format": FORMAT, "version": VERSION, **fp.to_json(),
                                      "output_bytes": _size(output)})


def reuse_or_make(output: str | os.PathLike, fp: Fingerprint, make_output) -> bool:
    """Reuse `output` when it is current for `fp`; else call `make_output()` (which writes it)
    and record `fp`. Returns True when reused."""
    if is_current(output, fp):
        return True
    forget(output)
    make_output()
    record(output, fp)
    return False


__all__ = ["FORMAT", "Fingerprint", "SUFFIX", "content", "file_sha256", "forget", "is_current", "make",
           "matches", "record", "reuse_or_make", "scene_fingerprint", "sidecar_path", "stat", "state"]
