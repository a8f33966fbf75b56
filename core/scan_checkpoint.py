"""Finished flight lines of a scan, kept so that an interrupted scan resumes from them.

A checkpoint is a folder beside the output (`OUT.las.lines/`, the CLI's choice) holding:

- `key.json`: what the lines were scanned from (the caller's fingerprint of scene, survey
  and seed, the batch size and the flight plan's lines). A folder with another key is
  emptied: its lines belong to another scan.
- per finished line k: `line_0000k.bin`, the packed LAS records of its batches, one after
  the other, exactly as they went to the writer; and `line_0000k.json`, each batch's point
  count, bounds and counters. The data file is renamed into place first and the JSON,
  written atomically, last: a line is finished only when both exist and agree in size.

A rerun writes a finished line's batches again through the same writer calls, in the same
order, so its LAS or LAZ bytes are those of an uninterrupted scan. The folder is removed
when the output is complete. It costs the output's size in LAS records while a scan runs.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_KEY = "key.json"


def plan_key(fingerprint: str, scene, survey, seed: int, batch_rays: int, lines) -> str:
    """The checkpoint key: the caller's fingerprint (the CLI's of the scene bundle's files),
    and what the scan's bytes depend on — the scene's arrays, origin, CRS and labels, the
    survey, the seed, the batch size and the flight lines — so that a library caller without
    a fingerprint cannot resume from another scan's lines either."""
    h = hashlib.sha256(f"{fingerprint}|{seed}|{batch_rays}|{scene.crs}|".encode())
    h.update(json.dumps(survey.to_json(), sort_keys=True).encode())
    for a in (scene.vertices, scene.faces, scene.face_building, scene.face_surface, scene.origin,
              scene.face_porous if scene.face_porous is not None else np.zeros(0)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([b.to_json() for b in scene.buildings], sort_keys=True, default=str).encode())
    h.update(str(scene.transmission).encode())
    for ln in lines:
        h.update(np.concatenate([ln.start, ln.heading, [ln.length_m, ln.t_start, ln.speed_m_s]]).tobytes())
    return h.hexdigest()[:24]


class LineCheckpoint:
    """Finished lines in `folder` for the scan whose key is `key` (see `plan_key`)."""

    def __init__(self, folder: str | os.PathLike, key: str):
        self.folder = Path(folder)
        self.key = key
        self._data = None  # open data file of the line being scanned
        self._batches: list = []
        self._offset = 0
        key_path = self.folder / _KEY
        stale = True
        if key_path.is_file():
            try:
                stale = json.loads(key_path.read_text()).get("key") != key
            except (json.JSONDecodeError, UnicodeDecodeError, OSError, AttributeError):
                stale = True
        if stale:
            self._clear()
            self.folder.mkdir(parents=True, exist_ok=True)
            self._write_json(key_path, {"key": key})

    def _clear(self) -> None:
        if self.folder.is_dir():
            for p in self.folder.iterdir():
                if p.name == _KEY or p.name.startswith("line_"):
                    p.unlink()

    @staticmethod
    def _write_json(path: Path, data) -> None:
        from .results import _atomic

        with _atomic(path) as tmp:
            tmp.write_text(json.dumps(data) + "\n")

    def _paths(self, line_index: int):
        stem = self.folder / f"line_{line_index:06d}"
        return stem.with_suffix(".bin"), stem.with_suffix(".json")

    def finished(self, line_index: int) -> dict | None:
        """The record of a finished line (None when it is not finished)."""
        data, meta = self._paths(line_index)
        if not (data.is_file() and meta.is_file()):
            return None
        try:
            record = json.loads(meta.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError, OSError):
            return None
        if record.get("bytes") != data.stat().st_size:
            return None
        return record

    # --- writing, one line at a time, batches in order ------------------------------------
    def add_batch(self, line_index: int, record, bounds, stats: dict) -> None:
        """Append one batch (its packed record, `record_bounds`-style bounds or None, its counters)."""
        data, _ = self._paths(line_index)
        if self._data is None:
            self._data = open(data.with_name(data.name + ".part"), "wb")
            self._batches, self._offset = [], 0
        raw = b"" if record is None or len(record) == 0 else record.array.tobytes()
        self._data.write(raw)
        self._offset += len(raw)
        self._batches.append({
            "points": 0 if record is None else len(record), "bytes": len(raw),
            "bounds": None if bounds is None else [np.asarray(b).tolist() for b in bounds],
            "stats": {k: int(v) for k, v in stats.items()},
        })

    def finish_line(self, line_index: int, by_return: np.ndarray, by_face: np.ndarray) -> None:
        """The line's batches are all added: make it a finished line."""
        data, meta = self._paths(line_index)
        self._data.close()
        self._data = None
        os.replace(data.with_name(data.name + ".part"), data)
        faces = np.flatnonzero(by_face)
        self._write_json(meta, {"line": line_index, "bytes": self._offset, "batches": self._batches,
                                "by_return": by_return.tolist(),
                                "by_face": [faces.tolist(), by_face[faces].tolist()]})

    def abandon(self) -> None:
        """Drop the line being written (the scan stopped in it)."""
        if self._data is not None:
            name = self._data.name
            self._data.close()
            self._data = None
            Path(name).unlink(missing_ok=True)

    # --- reading ----------------------------------------------------------------------------
    def batches(self, line_index: int, record_of):
        """(record or None, bounds or None, stats) of each batch of a finished line, in order;
        `record_of(bytes)` turns a batch's bytes back into a packed record."""
        data, _ = self._paths(line_index)
        info = self.finished(line_index)
        with open(data, "rb") as f:
            for b in info["batches"]:
                raw = f.read(b["bytes"])
                bounds = None if b["bounds"] is None else tuple(np.asarray(v) for v in b["bounds"])
                yield (record_of(raw) if b["points"] else None), bounds, dict(b["stats"])

    def remove(self) -> None:
        """The output is complete: the checkpoint is no longer needed."""
        self.abandon()
        self._clear()
        try:
            self.folder.rmdir()
        except OSError:  # someone else's files in it: leave them
            log.warning("%s: left in place (holds files that are not the scan's)", self.folder)

