"""Finished flight lines of a scan, kept so that an interrupted scan resumes from them.

A checkpoint is a folder beside the output (`OUT.las.lines/`, the laser sensors' `checkpoint` hook,
`quakescan.acquisition.sensor_lidar.line_checkpoint`) holding:

- `key.json`: what the lines were scanned from (`plan_key`: the caller's fingerprint, the
  scene, survey, seed, batch size and flight lines). A folder with another key is emptied:
  its lines belong to another scan.
- per finished line k, `line_0000k.json` (written atomically): each batch's point count,
  bounds and counters, and where the line's points start in the point stream.
- the points themselves. An uncompressed LAS is header + point records in scan order, so
  its points need no second copy: the writer writes it in this folder (`writing.las`, which
  a killed process leaves), a stopped scan's is kept as `partial.las`, and a rerun reads the
  finished lines' records back from it — no cost while scanning. A LAZ cannot be cut by points, so for
  `.laz` outputs each finished line's packed records also go to `line_0000k.bin` (renamed
  into place before its JSON is written).

A rerun writes a finished line's batches again through the same writer calls, in the same
order, so its LAS or LAZ bytes are those of an uninterrupted scan. The folder is removed
when the output is complete. The folder is the scan's only with its `key.json`: a folder of
that name without one (or a symbolic link) is somebody else's and refused, never emptied.
"""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from ..errors import PointCloudError
from ..runtime.atomic import commit, write_json
from ..runtime.fingerprint import make, scene_fingerprint

log = logging.getLogger(__name__)

_KEY = "key.json"


def plan_key(fingerprint: str, scene, survey, seed: int, batch_rays: int, lines) -> str:
    """The checkpoint key (`quakescan.runtime.fingerprint`): the caller's fingerprint (`acquire`'s of
    the acquisition), and what the scan's bytes depend on — the scene's arrays, origin,
    CRS and labels, the survey, the seed, the batch size and the flight lines — so that a
    library caller without a fingerprint cannot resume from another scan's lines either."""
    lines_doc = [np.concatenate([ln.start, ln.heading, [ln.length_m, ln.t_start, ln.speed_m_s]]).tolist()
                 for ln in lines]
    fp = make("scan-lines", inputs={"caller": fingerprint, "scene": scene_fingerprint(scene)},
              settings={"survey": survey.to_json(), "seed": int(seed), "batch_rays": int(batch_rays),
                        "lines": lines_doc})
    return fp.digest[:24]


def _check_own(folder: Path) -> None:
    """Refuse a checkpoint folder that is not the scan's (see the module's doc)."""
    if folder.is_symlink():
        raise PointCloudError(f"{folder}: is a symbolic link; the scan keeps its finished flight lines in a folder "
                              "of its own there: remove the link")
    if folder.is_dir() and not (folder / _KEY).is_file() and any(folder.iterdir()):
        raise PointCloudError(f"{folder}: a folder the scan did not make (no {_KEY}); it keeps its finished flight "
                              "lines there: move the folder away or write the scan under another name")


def _part(path: Path) -> Path:
    """A line file's name while it is written, in the scan's own folder."""
    return path.with_name(path.name + ".part")


def _open_new(path: Path):
    """`path` opened for writing, new: whatever was left under that name (a killed run's file,
    a link) is removed, never written through."""
    path.unlink(missing_ok=True)
    return os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb")


class LineCheckpoint:
    """Finished lines in `folder` for the scan whose key is `key` (see `plan_key`).

    `las_part`: True for an uncompressed LAS output, whose writer writes its temporary file
    here (`.las_part`; its points are kept, see the module's doc), False for LAZ (records go
    to line files). `point_size`: bytes per LAS point record."""

    def __init__(self, folder: str | os.PathLike, key: str, las_part: bool = False, point_size: int = 0):
        self.folder = Path(folder)
        self.key = key
        _check_own(self.folder)
        self.las_part = self.folder / "writing.las" if las_part else None
        self.point_size = point_size
        self._data = None  # open data file of the line being scanned (LAZ outputs)
        self._batches: list = []
        self._offset = 0
        self._first_point = 0
        self.replay_source = self.folder / "replay.las"
        key_path = self.folder / _KEY
        stale = True
        if key_path.is_file():
            try:
                stale = json.loads(key_path.read_text()).get("key") != key
            except (json.JSONDecodeError, UnicodeDecodeError, OSError, AttributeError):
                stale = True
        if stale:
            self._clear()
            if self.las_part is not None:
                self.las_part.unlink(missing_ok=True)  # another scan's
            self.folder.mkdir(parents=True, exist_ok=True)
            self._write_json(key_path, {"key": key})
        self._usable_points = self._pick_replay_source() if self.las_part is not None else 0

    @property
    def partial_las(self) -> Path:
        """Where a stopped scan's LAS goes (the writer moves it here)."""
        return self.folder / "partial.las"

    def _clear(self) -> None:
        if self.folder.is_dir():
            for p in self.folder.iterdir():
                if p.name in (_KEY, "partial.las", "replay.las", "writing.las") or p.name.startswith("line_"):
                    p.unlink()

    def _complete_points(self, path: Path) -> int:
        """Whole point records in a (partial) LAS of this scan's format: from its size, not its
        header's count, which a killed writer never wrote."""
        import laspy

        try:
            with laspy.open(path) as f:
                h = f.header
                if h.point_format.size != self.point_size:
                    return 0
                start = h.offset_to_point_data
        except Exception:  # no readable header: nothing to take from it
            return 0
        return max(0, (path.stat().st_size - start) // self.point_size)

    def _pick_replay_source(self) -> int:
        """Keep the candidate with the most points as replay.las (they are prefixes of one
        stream), remove the others; returns its number of whole points."""
        candidates = [p for p in (self.partial_las, self.replay_source, self.las_part) if p.is_file()]
        best, best_n = None, 0
        for p in candidates:
            n = self._complete_points(p)
            if n > best_n:
                best, best_n = p, n
        for p in candidates:
            if p != best:
                p.unlink()
        if best is not None and best != self.replay_source:
            os.replace(best, self.replay_source)
        return best_n

    @staticmethod
    def _write_json(path: Path, data) -> None:
        write_json(path, data, indent=None)

    def _paths(self, line_index: int):
        stem = self.folder / f"line_{line_index:06d}"
        return stem.with_suffix(".bin"), stem.with_suffix(".json")

    def _record(self, line_index: int) -> dict | None:
        data, meta = self._paths(line_index)
        if not meta.is_file():
            return None
        try:
            record = json.loads(meta.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError, OSError):
            return None
        if not isinstance(record, dict) or not isinstance(record.get("batches"), list):
            return None
        if self.las_part is None:
            if not data.is_file() or record.get("bytes") != data.stat().st_size:
                return None
        elif record.get("first_point", -1) + sum(b["points"] for b in record["batches"]) > self._usable_points:
            return None
        return record

    def finished_lines(self, lines) -> set:
        """Indices of the flight lines (of `lines`, in scan order) that a rerun can take from
        here. From a LAS, only lines whose points all lie in the kept partial file."""
        done = set()
        for ln in lines:
            if self._record(ln.index) is not None:
                done.add(ln.index)
        return done

    # --- writing, one line at a time, batches in order ------------------------------------
    def add_batch(self, line_index: int, record, bounds, stats: dict, first_point: int) -> None:
        """Add one batch (its packed record, `record_bounds`-style bounds or None, its counters);
        `first_point`: points written before this batch."""
        if not self._batches:
            self._first_point, self._offset = first_point, 0
        raw_size = 0
        if self.las_part is None:
            data, _ = self._paths(line_index)
            if self._data is None:
                self._data_path = _part(data)
                self._data = _open_new(self._data_path)
            raw = b"" if record is None or len(record) == 0 else record.array.tobytes()
            self._data.write(raw)
            raw_size = len(raw)
        self._offset += raw_size
        self._batches.append({
            "points": 0 if record is None else len(record), "bytes": raw_size,
            "bounds": None if bounds is None else [np.asarray(b).tolist() for b in bounds],
            "stats": {k: int(v) for k, v in stats.items()},
        })

    def finish_line(self, line_index: int, by_return: np.ndarray, by_face: np.ndarray) -> None:
        """The line's batches are all added: make it a finished line."""
        data, meta = self._paths(line_index)
        if self._data is not None:
            self._data.close()
            self._data = None
            commit(_part(data), data)
        faces = np.flatnonzero(by_face)
        self._write_json(meta, {"line": line_index, "bytes": self._offset, "first_point": self._first_point,
                                "batches": self._batches, "by_return": by_return.tolist(),
                                "by_face": [faces.tolist(), by_face[faces].tolist()]})
        self._batches = []

    def abandon(self) -> None:
        """Drop the line being written (the scan stopped in it)."""
        self._batches = []
        if self._data is not None:
            self._data.close()
            self._data = None
            self._data_path.unlink(missing_ok=True)

    # --- reading ----------------------------------------------------------------------------
    def line_record(self, line_index: int) -> dict:
        return self._record(line_index)

    def batches(self, line_index: int, record_of):
        """(record or None, bounds or None, stats) of each batch of a finished line, in order;
        `record_of(bytes)` turns a batch's bytes back into a packed record."""
        data, _ = self._paths(line_index)
        info = self._record(line_index)
        if self.las_part is None:
            source, start = data, 0
        else:
            import laspy

            with laspy.open(self.replay_source) as f:
                start = f.header.offset_to_point_data + info["first_point"] * self.point_size
            source = self.replay_source
        with open(source, "rb") as f:
            f.seek(start)
            for b in info["batches"]:
                raw = f.read(b["points"] * self.point_size if self.las_part is not None else b["bytes"])
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
