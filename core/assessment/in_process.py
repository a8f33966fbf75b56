"""The classify run's engine in this process: both epochs read whole, the buildings described
tile by tile on this process's threads (`quakescan.change.pipeline.describe_pair`).
"""
from __future__ import annotations

import logging
from pathlib import Path

from ..change.pipeline import describe_pair
from ..change.tiling import members_by_id
from ..change.registration import register_pair
from ..formats.pair import load_pair
from ..formats.pointcloud import Epoch
from . import record
from .engine import Engine, Job, ReadPair

log = logging.getLogger(__name__)


class InProcess(Engine):
    """Read, register and describe in this process, on `workers` threads (-1: every core)."""

    def __init__(self, workers: int = -1):
        self.workers = workers

    def read(self, job: Job, load) -> ReadPair:
        load()  # the model first: a model that cannot be used is refused before the clouds are read
        data = load_pair(job.pre_path, job.post_path, job.footprints_path, job.id_field, labels=False)
        pre = data.pre
        return ReadPair(points={"pre": len(pre), "post": len(data.post)}, noise_points=data.noise_points,
                        crs=pre.crs, footprints=data.footprints,
                        footprint_ids_without_points=data.footprint_ids_without_points,
                        map_xy=pre.xyz[:: record.map_step(len(pre)), :2] + pre.origin[:2],
                        outline_points=XYByBuilding(pre) if data.footprints is None else None,
                        outline_origin=pre.origin, state=data, coverage=data.coverage)

    def describe(self, job: Job, pair: ReadPair, settings, summary: dict) -> tuple[list, int]:
        data = pair.state
        summary["registration"] = register_pair(data.pre, data.post, settings, job.align, summary, self.workers)
        job.before_first_write()
        ckpt = record.RowCheckpoint(job.out / ".checkpoint.jsonl", job.digest)
        resumed = len(ckpt.rows)
        if resumed:
            log.warning("%s: resuming, %d buildings already described", job.out, resumed)
        rows = describe_pair(data.pre, data.post, settings, workers=self.workers, progress=job.progress,
                             done=ckpt.rows, on_tile=ckpt.add)
        return rows, resumed

    def write_graded_cloud(self, job: Job, pair: ReadPair, path: Path, grade_by_building: dict) -> None:
        from ..results.graded_cloud import write_grade_las

        post = pair.state.post
        write_grade_las(path, post.xyz, post.origin, post.crs, post.building_id, grade_by_building,
                        source=job.post_path)

    def close(self, job: Job, pair: ReadPair) -> None:
        (job.out / ".checkpoint.jsonl").unlink(missing_ok=True)


class XYByBuilding:
    """{building ID: its points' local x/y} for the outlines, each building's copied only when
    asked for: all of them at once were a second copy of a city's x/y (1.2 GB of a 75 M-point
    epoch, with an 8-byte argsort beside it: the run's memory peak)."""

    def __init__(self, e: Epoch):
        self.xyz = e.xyz
        self.members = members_by_id(e.building_id)

    def get(self, bid: int, default=None):
        idx = self.members(bid) if bid > 0 else None
        return default if idx is None or len(idx) == 0 else self.xyz[idx, :2]
