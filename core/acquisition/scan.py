"""Virtual UAV laser scanning (ULS, and ALS with the `als` preset) of a scene: the flight
plan cut into batches of pulses, simulated on worker threads (`quakescan.acquisition.beams`),
written in flight order to one LAS/LAZ file, resumable per flight line
(`quakescan.acquisition.scan_checkpoint`); and what a scan will cost before it flies
(`estimate_scan`).
"""
from __future__ import annotations

import logging
import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..errors import QuakeScanError, SceneError, SurveyError
from ..formats.pointcloud import LasChunkWriter, make_header
from ..formats.scene import Scene, check_crs
from ..runtime.progress import ProgressCallback
from ..runtime.workers import EVERY_CORE, check_workers
from ._scan_reference import loops
from .beams import Simulator
from .las_output import label_counts, las_offset
from .pulses import Batch, pulse_count
from .raycast import RayCaster, check_scannable, ground_level
from .survey import FlightLine, FlightPlan, Survey, plan_flight

log = logging.getLogger(__name__)

DEFAULT_BATCH_RAYS = 1 << 20


@dataclass
class ScanSummary:
    output: str
    pulses_swept: int = 0  # all pulses of the mirror's sweep; only the FOV share leaves the scanner
    pulses_emitted: int = 0
    pulses_cast: int = 0
    rays_cast: int = 0
    points: int = 0
    pulses_with_sub_rays: int = 0
    points_by_return: dict = field(default_factory=dict)
    points_by_surface: dict = field(default_factory=dict)
    points_by_building: dict = field(default_factory=dict)
    lines: int = 0
    flight_duration_s: float = 0.0
    wall_time_s: float = 0.0
    beam: str = "single"
    seed: int = 0
    lines_resumed: int = 0  # flight lines taken from the checkpoint of an interrupted run

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["points_by_building"] = {str(k): v for k, v in sorted(self.points_by_building.items())}
        return d


def _batches(survey: Survey, plan: FlightPlan, batch_rays: int):
    rays_per_pulse = survey.sub_rays if survey.beam == "full" else 1
    # batches are counted in raw pulses; only the FOV share of them is cast
    size = max(1, int(batch_rays / (rays_per_pulse * survey.fov_fraction)))
    number = 0
    for line in plan.lines:
        n = pulse_count(survey, line)
        for j0 in range(0, n, size):
            yield Batch(line, j0, min(n, j0 + size), number)
            number += 1


def scan(scene: Scene, survey: Survey, out_path: str | os.PathLike, seed: int = 0,
         workers: int = -1, batch_rays: int = DEFAULT_BATCH_RAYS,
         lines: list | None = None, progress: ProgressCallback | None = None, source: str = "scene",
         require_buildings: bool = True, fast: bool = True,
         checkpoint: str | os.PathLike | None = None, fingerprint: str = "") -> ScanSummary:
    """Scan `scene` with `survey` and write the point cloud to `out_path` (.las / .laz).

    `lines` replaces the planned flight lines (tests use a single line); `progress` is
    called with (pulses_done, pulses_total). Same scene, survey and seed give the same
    bytes, whatever `workers` (threads; -1: every core). `fast` chooses the loops once, for the whole
    scan: `fast=False` runs the numpy reference of the compiled loops (same bytes, slower).

    `checkpoint`: a folder where every finished flight line is kept
    (`quakescan.acquisition.scan_checkpoint`); a rerun of the same scan (same `fingerprint`, the caller's
    digest of its inputs, and the same scene, survey, seed and batches) takes the finished
    lines from there instead of scanning them again, and writes the same bytes as an
    uninterrupted scan. Removed on success.
    """
    started = time.perf_counter()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise QuakeScanError(f"seed must be an integer >= 0, got {seed!r}")
    workers = check_workers(workers)
    check_crs(scene.crs, source)
    if require_buildings:
        check_scannable(scene, source)
    elif len(scene.faces) == 0:
        raise SceneError(f"{source}: the scene is empty (no faces); nothing to scan")
    caster = RayCaster(scene)
    ground_z = ground_level(scene)
    plan = plan_flight(survey, scene.bounds(), ground_z)
    if lines is not None:
        plan = FlightPlan(list(lines), plan.ground_z, plan.flight_z)
    threads = workers if workers != EVERY_CORE else os.cpu_count() or 1
    summary = ScanSummary(output=str(out_path), lines=len(plan.lines), flight_duration_s=plan.duration_s,
                          beam=survey.beam, seed=seed)
    total = sum(pulse_count(survey, ln) for ln in plan.lines)
    offset, shift = las_offset(scene, caster)
    by_return = np.zeros(16, np.int64)
    by_face = np.zeros(len(scene.faces), np.int64)
    las_writer = LasChunkWriter(out_path, offset, scene.crs, survey.acquisition_date)
    saved = None
    if checkpoint is not None:
        from .scan_checkpoint import LineCheckpoint, plan_key

        # Before the writer opens (and truncates) its temporary file: a killed run's is kept.
        saved = LineCheckpoint(checkpoint, plan_key(fingerprint, scene, survey, seed, batch_rays, plan.lines),
                               las_part=not las_writer.compressed, point_size=las_writer.header.point_format.size)
        if not las_writer.compressed:
            # the partial file is written in the checkpoint's folder, where a rerun after kill -9 finds it
            las_writer = LasChunkWriter(out_path, offset, scene.crs, survey.acquisition_date,
                                        temporary=saved.las_part)
            las_writer.keep_partial_as = saved.partial_las
    with las_writer as writer, ThreadPoolExecutor(max_workers=threads) as pool:
        sim = Simulator(caster, survey, seed, shift=shift, header=writer.header, loops=loops(fast))
        pending: deque = deque()
        line_return = np.zeros(16, np.int64)
        line_face = np.zeros(len(scene.faces), np.int64)

        def take(record, bounds, stats):
            writer.write_record(record, bounds)
            for k, v in stats.items():
                setattr(summary, k, getattr(summary, k) + v)

        def consume(item):
            if isinstance(item, FlightLine):  # a finished line of an earlier run
                info = saved.line_record(item.index)
                for record, bounds, stats in saved.batches(item.index, sim.record_from_bytes):
                    take(record, bounds, stats)
                by_return[:] += info["by_return"]
                np.add.at(by_face, np.asarray(info["by_face"][0], np.int64), np.asarray(info["by_face"][1], np.int64))
                summary.lines_resumed += 1
            else:
                batch, future = item
                record, stats = future.result()
                bounds = stats.pop("las_bounds", None)
                b_return, b_face = stats.pop("by_return"), stats.pop("by_face")
                first_point = writer.count
                take(record, bounds, stats)
                by_return[:] += b_return
                by_face[:] += b_face
                if saved is not None:
                    saved.add_batch(batch.line.index, record, bounds, stats, first_point)
                    line_return[:] += b_return
                    line_face[:] += b_face
                    if batch.j1 == pulse_count(survey, batch.line):
                        saved.finish_line(batch.line.index, line_return, line_face)
                        line_return[:] = 0
                        line_face[:] = 0
            if progress:
                progress(summary.pulses_swept, total)

        # Workers simulate and pack batches; this thread only writes, in order. A bounded
        # window of batches in flight keeps memory flat.
        done = saved.finished_lines(plan.lines) if saved is not None else set()
        if done:
            log.info("%s: %d of %d flight lines were finished by an earlier run", source, len(done), len(plan.lines))
        try:
            for batch in _batches(survey, plan, batch_rays):
                if batch.line.index in done:
                    if batch.j0 == 0:
                        pending.append(batch.line)
                    continue
                pending.append((batch, pool.submit(sim.run_batch, batch)))
                if len(pending) >= 2 * threads:
                    consume(pending.popleft())
            while pending:
                consume(pending.popleft())
        except BaseException:
            for item in pending:  # stop what has not started; the checkpoint keeps finished lines
                if not isinstance(item, FlightLine):
                    item[1].cancel()
            if saved is not None:
                saved.abandon()
            raise
        if summary.points == 0:
            raise SurveyError(f"{source}: the survey recorded no points: its flight lines miss the scene "
                              f"or every surface is beyond max_range_m={survey.max_range_m}")
    if saved is not None:
        saved.remove()
    summary.points_by_return = {str(r): int(c) for r, c in enumerate(by_return) if c}
    summary.points_by_surface, summary.points_by_building = label_counts(scene, caster, by_face, source)
    summary.wall_time_s = time.perf_counter() - started
    return summary


# A scan above this many estimated points is announced as large before it starts: about
# 3.6 GB of LAS and, at the few million pulses per second of 2 cores, tens of minutes.
LARGE_SCAN_POINTS = 100_000_000
# Beyond this many estimated points `quakescan scan` refuses to start unless forced: about
# 18 GB of LAS and hours on 2 cores, which no survey of a damaged district needs.
MAX_SCAN_POINTS = 500_000_000
LAZ_RATIO = 0.18  # LAZ / LAS size of our clouds, the upper end measured: 0.07 (paper ULS) to 0.18 (ALS)


@dataclass(frozen=True)
class FlightPlanEstimate:
    """What a scan will cost, before it runs: from the flight plan alone."""

    lines: int
    line_km: float
    flight_time_s: float
    pulses: int  # pulses that leave the scanner (the FOV's share of the sweep)
    points: int  # one return per pulse: an upper bound (pulses that miss the scene give none;
    # the paper survey over the demo city: 7.4 M estimated, 2.6 M scanned)
    megabytes: float  # of the output file (LAZ when `laz`)
    area_km2: float

    @property
    def large_points(self) -> int:
        return LARGE_SCAN_POINTS

    @property
    def max_points(self) -> int:
        return MAX_SCAN_POINTS

    @property
    def large(self) -> bool:
        return self.points > self.large_points

    @property
    def too_large(self) -> bool:
        return self.points > self.max_points

    def describe(self) -> str:
        return (f"flight plan: {self.lines} lines, {self.line_km:.1f} km, {self.flight_time_s / 60:.1f} min of "
                f"flight over {self.area_km2:.2f} km²; {self.pulses / 1e6:,.1f} M pulses, at most "
                f"{self.points / 1e6:,.1f} M points and {self.megabytes:,.0f} MB")


def estimate_scan(scene: Scene, survey: Survey, laz: bool = False) -> FlightPlanEstimate:
    """The flight plan's lines, flight time, pulses, points and file size (see FlightPlanEstimate)."""
    plan = plan_flight(survey, scene.bounds(), ground_level(scene))
    pulses = int(sum(pulse_count(survey, ln) for ln in plan.lines) * survey.fov_fraction)
    record = make_header(scene.origin, None).point_format.size
    size = pulses * record / 1e6 * (LAZ_RATIO if laz else 1.0)
    b = scene.bounds()
    area = float((b[1, 0] - b[0, 0]) * (b[1, 1] - b[0, 1])) / 1e6
    return FlightPlanEstimate(len(plan.lines), sum(ln.length_m for ln in plan.lines) / 1e3, plan.duration_s,
                              pulses, pulses, size, area)
