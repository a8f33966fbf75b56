"""What the classify run asks of an engine (`Engine`), and what it hands it (`Job`) and gets
back (`ReadPair`): the seam between the run's one skeleton (`quakescan.assessment.run`) and
the ways of describing a pair (this process, `in_process`; Dask, `quakescan.distributed.engine`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..runtime.progress import ProgressCallback


@dataclass
class Job:
    """What a run asks its engine for: the inputs, the output folder and the run's digest
    (the checkpoints' key). `before_first_write()` retires a previous run's results: an engine
    calls it once, after its input checks and before it writes into `out`."""

    pre_path: object
    post_path: object
    footprints_path: object
    id_field: str | None
    align: bool | None
    out: Path
    digest: str
    progress: ProgressCallback | None
    before_first_write: Callable[[], None]


@dataclass
class ReadPair:
    """What an engine read of the pair, for the rows' description and the result files.

    `map_xy`: world x/y of the pre-event points drawn under the damage map; `outline_points`
    ({building ID: local x/y} or None) and `outline_origin`: the points a building's outline is
    drawn around where no footprint gives it; `state`: the engine's own; `coverage`: how many
    footprints each epoch's points reach (empty without footprints)."""

    points: dict
    noise_points: dict
    crs: str | None
    footprints: object
    footprint_ids_without_points: list
    map_xy: object
    outline_points: object
    outline_origin: tuple
    state: object = None
    stages: list = field(default_factory=list)
    coverage: dict = field(default_factory=dict)  # `quakescan.formats.footprints.coverage`


class Engine:
    """How a run reads a pair, describes its buildings and writes the graded cloud: an engine
    subclasses this and gives `read`, `describe` and `write_graded_cloud`; the other steps do
    nothing unless it has something of its own to do there.

    `read(job, load)` calls `load()` (which reads the model and returns its pipeline
    settings) when it suits the engine, at the latest before returning; `describe` returns
    every building's row (not sorted) and how many came from a checkpoint, and records the
    registration in `summary`; `described` is told when every row is in, `add_to_summary`
    adds the engine's own entries, `close` removes what it made for the run."""

    working_folders: tuple = ()

    def read(self, job: Job, load: Callable[[], object]) -> ReadPair:
        raise NotImplementedError

    def describe(self, job: Job, pair: ReadPair, settings, summary: dict) -> tuple[list, int]:
        raise NotImplementedError

    def write_graded_cloud(self, job: Job, pair: ReadPair, path: Path, grade_by_building: dict) -> None:
        raise NotImplementedError

    def described(self, job: Job, pair: ReadPair) -> None:
        """Every row is described (the engine may start freeing what only describing needed)."""

    def add_to_summary(self, pair: ReadPair, summary: dict, seconds: dict, end: float) -> None:
        """The engine's own entries of the summary and its `seconds`."""

    def close(self, job: Job, pair: ReadPair) -> None:
        """The run's results are written: remove what the engine made for it."""


__all__ = ["Engine", "Job", "ReadPair"]
