"""Commands that acquire a scene: `acquire --kind K` (any registered sensor), `scan` and `dim`
(its names for the built-in laser scanning and dense image matching, with the options only
those have), and their settings templates."""
from __future__ import annotations

import sys
from pathlib import Path

from ..errors import QuakeScanError
from ..runtime.output_folder import refuse_replacing_inputs
from ..runtime.workers import EVERY_CORE
from .options import PROGRESS_HELP, THREADS_HELP, check_threads
from .reporting import echo, reporter

# How each command's messages name what it does.
_WORDS = {"acquire": {"what": "acquisition", "doing": "acquiring", "again": "acquire it again"},
          "scan": {"what": "scan", "doing": "scanning", "again": "rescan"},
          "dim": {"what": "simulation", "doing": "simulating", "again": "simulate it again"}}


def _check_flags(args) -> None:
    if args.seed < 0:
        raise QuakeScanError(f"--seed: expected an integer >= 0 (the same seed gives the same bytes), got {args.seed}")
    check_threads(args.threads)


def cmd_acquire(args) -> int:
    """A simulated point cloud of a scene bundle with the sensor `args.kind` (`quakescan.acquisition.acquire`)."""
    from ..acquisition import sensors
    from ..acquisition.acquire import Acquisition, plan, sidecar_path
    from ..acquisition.summary import write_summary
    from .scenes import scene_files

    words = _WORDS[args.command]
    _check_flags(args)
    scene_dir = Path(args.scene)
    out = Path(args.output)
    if out.suffix.lower() not in (".las", ".laz"):
        raise QuakeScanError(f"-o {out}: a point cloud's name must end in .las or .laz")
    if out.is_dir():
        raise QuakeScanError(f"-o {out}: is a folder; give the point cloud's file name (.las or .laz)")
    sensor = sensors.get(args.kind)
    spec = args.survey if args.survey is not None else sensor.default_preset
    settings = sensor.load_settings(spec)
    if getattr(args, "beam", None):
        settings = settings.replace(beam=args.beam)
    acquisition = Acquisition(sensor.kind, settings)
    summary_path = Path(args.summary) if getattr(args, "summary", None) else out.with_name(out.name + ".summary.json")
    trajectory = getattr(args, "trajectory", None)
    checkpoint = sensor.checkpoint(out) if sensor.checkpoint is not None else None
    survey_file = spec if Path(spec).is_file() else None  # else a preset's name
    refuse_replacing_inputs([out, summary_path, sidecar_path(out), trajectory, checkpoint],
                            scene_files(scene_dir) + [(survey_file, "survey file")], command=args.command)
    planned = plan(scene_dir, acquisition, out, seed=args.seed, reuse=not args.force)
    if planned.reusable is not None:
        if trajectory:
            _write_trajectory(planned, trajectory)
        echo(f"{out}: up to date (same scene, {sensor.settings_name} and seed); use --force to {words['again']}"
             + (f"; trajectory -> {trajectory}" if trajectory else ""))
        return 0
    estimate = planned.estimate()
    if estimate is not None:
        echo(estimate.describe())
    if getattr(args, "dry_run", False):
        if estimate is None:
            echo(f"{sensor.kind}: no estimate of the {words['what']} before it runs")
        return 0
    if estimate is not None and estimate.too_large and not args.force:
        raise QuakeScanError(f"{spec} over {scene_dir}: the plan reaches {estimate.points / 1e6:,.0f} M points and "
                             f"{estimate.megabytes / 1e3:,.1f} GB, beyond the limit of "
                             f"{estimate.max_points / 1e6:,.0f} M points; check the scene's extent and the "
                             f"{sensor.settings_name} (pulse rate, speed, overlap), or --force to {words['what']} "
                             "anyway")
    if estimate is not None and estimate.large:
        print(f"warning: a large {words['what']} (more than {estimate.large_points / 1e6:.0f} M points): check the "
              f"scene's extent (`quakescan validate`) and the {sensor.settings_name}; `--dry-run` shows the plan "
              f"without {words['doing']}", file=sys.stderr)
    # With a checkpoint, the finished part is kept; a rerun after an interruption continues from it.
    acquired = planned.run(args.threads, reporter(args, f"{args.command} {scene_dir.name}"), checkpoint=True)
    write_summary(summary_path, acquired, acquisition)
    if trajectory:
        _write_trajectory(planned, trajectory)
    _print_summary(acquired, planned, checkpoint)
    return 0


def _write_trajectory(planned, path) -> None:
    from ..acquisition.sensor_lidar import write_trajectory

    write_trajectory(planned.scene, planned.acquisition.settings, Path(path))


def _print_summary(acquired, planned, checkpoint) -> None:
    from ..acquisition.dim import DimSummary
    from ..acquisition.scan import ScanSummary

    s = acquired.summary
    if isinstance(s, ScanSummary):
        if s.lines_resumed:
            echo(f"resumed: {s.lines_resumed} of {s.lines} flight lines came from the interrupted run "
                 f"({checkpoint})")
        n_b = len(planned.scene.buildings)
        hit_b = len(s.points_by_building)
        echo(f"{s.output}: {s.points:,} points from {s.pulses_emitted:,} pulses "
             f"({s.rays_cast:,} rays, beam {s.beam}) over {s.lines} flight lines, "
             f"{s.flight_duration_s:.0f} s of flight, {s.wall_time_s:.1f} s wall time "
             f"({s.pulses_emitted / max(s.wall_time_s, 1e-9) / 1e6:.2f} M pulses/s)")
        echo("  by surface: " + ", ".join(f"{k} {v:,}" for k, v in s.points_by_surface.items()))
        echo("  by return:  " + ", ".join(f"{k}: {v:,}" for k, v in s.points_by_return.items()))
        echo(f"  buildings with points: {hit_b} of {n_b}")
    elif isinstance(s, DimSummary):
        echo(f"dim: {s.points:,} points from {s.cameras:,} images (nadir GSD {100 * s.gsd_nadir_m:.1f} cm) "
             f"in {s.wall_time_s:.1f} s -> {acquired.path}")
    else:
        echo(f"{planned.acquisition.kind}: {s.points:,} points in {s.wall_time_s:.1f} s -> {acquired.path}")


def cmd_survey_template(args) -> int:
    from ..acquisition.survey import load_survey, write_survey_template

    write_survey_template(args.output, load_survey(args.preset))
    print(f"{args.output}: survey '{args.preset}' with every field documented in '_doc'")
    return 0


def cmd_dim_survey_template(args) -> int:
    from ..acquisition.dim_settings import preset_dim, write_photo_survey_template

    write_photo_survey_template(args.output, preset_dim(args.preset))
    print(f"photo survey template ({args.preset}) -> {args.output}")
    return 0


def _add_common(parser, survey_help: str, seed_help: str, after_survey=()) -> None:
    """The options of every acquiring command; `after_survey`: (flags, options) of a kind's own
    settings overrides, listed after --survey."""
    parser.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    parser.add_argument("-o", "--output", required=True, help="output point cloud, .las or .laz")
    parser.add_argument("--survey", default=None, help=survey_help)
    for flags, options in after_survey:
        parser.add_argument(*flags, **options)
    parser.add_argument("--seed", type=int, default=0, help=seed_help)
    parser.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)


def add_acquire(sub) -> None:
    a = sub.add_parser("acquire", help="simulate the point cloud of a scene bundle with any registered sensor "
                       "(scan and dim are its names for uls and dim)")
    a.add_argument("--kind", required=True, help="the sensor: uls, als, dim or one a module registered")
    _add_common(a, "the sensor's preset name or settings JSON file (default: its default preset)",
                "seed of the sensor's noise (same seed, same bytes)")
    a.add_argument("--summary", help="summary JSON path (default: OUTPUT.summary.json)")
    a.add_argument("--force", action="store_true", help="acquire again even if the output is up to date, and run "
                   "a plan beyond the sensor's size limit")
    a.add_argument("--dry-run", action="store_true",
                   help="print the sensor's estimate of the run (when it has one) and stop")
    a.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    a.set_defaults(func=cmd_acquire)


def add_scan(sub) -> None:
    s = sub.add_parser("scan", help="scan a scene bundle with a virtual UAV laser scanner")
    beam = (("--beam",), {"choices": ("single", "adaptive", "full"), "help": "override the survey's beam model"})
    _add_common(s, "preset name (paper, als) or survey JSON file (default paper)",
                "seed of the range noise (same seed, same bytes)", after_survey=(beam,))
    s.add_argument("--trajectory", help="also write the platform trajectory as CSV (also when the scan is "
                   "up to date)")
    s.add_argument("--summary", help="summary JSON path (default: OUTPUT.summary.json)")
    s.add_argument("--force", action="store_true", help="rescan even if the output is up to date, and scan a plan "
                   "beyond the size limit (500 M points)")
    s.add_argument("--dry-run", action="store_true",
                   help="print the flight plan (lines, flight time, pulses, points, file size) and stop")
    s.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    s.set_defaults(func=cmd_acquire, kind="uls", survey="paper")


def add_survey_template(sub) -> None:
    t = sub.add_parser("survey-template", help="write a documented survey JSON file to edit")
    t.add_argument("-o", "--output", required=True, help="survey JSON file to write")
    t.add_argument("--preset", default="paper", help="preset whose values the file holds: paper or als "
                   "(default paper)")
    t.set_defaults(func=cmd_survey_template)


def add_dim(sub) -> None:
    dm = sub.add_parser("dim", help="simulate a photogrammetric (DIM) point cloud of a scene bundle")
    _add_common(dm, "photo survey preset (paper) or JSON file (default paper)",
                "seed of sampling and noise (same seed, same bytes)")
    dm.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    dm.add_argument("--force", action="store_true", help="simulate again even if the output is up to date "
                    "(same scene, photo survey and seed)")
    dm.set_defaults(func=cmd_acquire, kind="dim", survey="paper")


def add_dim_survey_template(sub) -> None:
    dt = sub.add_parser("dim-survey-template", help="write a documented photo survey JSON file to edit")
    dt.add_argument("-o", "--output", required=True, help="photo survey JSON file to write")
    dt.add_argument("--preset", default="paper", help="preset whose values the file holds: paper (default)")
    dt.set_defaults(func=cmd_dim_survey_template)
