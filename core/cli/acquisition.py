"""Commands that acquire a scene: scan (ULS/ALS), dim, and their settings templates."""
from __future__ import annotations

import sys
from pathlib import Path

from ..acquisition.summary import cloud_fingerprint, cloud_is_up_to_date, write_cloud_summary
from ..errors import QuakeScanError
from ..runtime.output_folder import refuse_replacing_inputs
from ..runtime.workers import EVERY_CORE
from .options import PROGRESS_HELP, THREADS_HELP, check_threads
from .reporting import echo, reporter


def _refuse_replacing_inputs(command: str, outputs, scene_dir, survey) -> None:
    """No output of an acquisition is one of its inputs (the scene's files, the survey file)."""
    from .scenes import scene_files

    survey_file = survey if survey is not None and Path(survey).is_file() else None  # else a preset's name
    refuse_replacing_inputs(outputs, scene_files(scene_dir) + [(survey_file, "survey file")], command=command)


def _check_scan_flags(args) -> None:
    if args.seed < 0:
        raise QuakeScanError(f"--seed: expected an integer >= 0 (the same seed gives the same bytes), got {args.seed}")
    check_threads(args.threads)


def cmd_scan(args) -> int:
    from ..acquisition.scan import scan
    from ..acquisition.sensor_lidar import write_trajectory
    from ..acquisition.survey import load_survey
    from ..formats.scene import read_scene

    _check_scan_flags(args)
    scene_dir = Path(args.scene)
    out = Path(args.output)
    if out.suffix.lower() not in (".las", ".laz"):
        raise QuakeScanError(f"-o {out}: a point cloud's name must end in .las or .laz")
    if out.is_dir():
        raise QuakeScanError(f"-o {out}: is a folder; give the point cloud's file name (.las or .laz)")
    survey = load_survey(args.survey)
    if args.beam:
        survey = survey.replace(beam=args.beam)
    summary_path = Path(args.summary) if args.summary else out.with_name(out.name + ".summary.json")
    _refuse_replacing_inputs("scan", [out, summary_path, args.trajectory, out.with_name(out.name + ".lines")],
                             scene_dir, args.survey)
    fp = cloud_fingerprint("scan", scene_dir, survey, args.seed)
    if not args.force and cloud_is_up_to_date(out, summary_path, fp):
        if args.trajectory:
            write_trajectory(read_scene(scene_dir), survey, Path(args.trajectory))
        echo(f"{out}: up to date (same scene, survey and seed); use --force to rescan"
             + (f"; trajectory -> {args.trajectory}" if args.trajectory else ""))
        return 0
    scene = read_scene(scene_dir)
    from ..acquisition.scan import LARGE_SCAN_POINTS, MAX_SCAN_POINTS, estimate_scan

    plan = estimate_scan(scene, survey, laz=out.suffix.lower() == ".laz")
    echo(plan.describe())
    if args.dry_run:
        return 0
    if plan.too_large and not args.force:
        raise QuakeScanError(f"{args.survey} over {scene_dir}: the plan reaches {plan.points / 1e6:,.0f} M points and "
                             f"{plan.megabytes / 1e3:,.1f} GB, beyond the limit of {MAX_SCAN_POINTS / 1e6:,.0f} M "
                             "points; check the scene's extent and the survey (pulse rate, speed, overlap), "
                             "or --force to scan anyway")
    if plan.large:
        print(f"warning: a large scan (more than {LARGE_SCAN_POINTS / 1e6:.0f} M points): check the scene's extent "
              f"(`quakescan validate`) and the survey; `--dry-run` shows the plan without scanning", file=sys.stderr)
    progress = reporter(args, f"scan {scene_dir.name}")
    # Finished flight lines are kept here; a rerun after an interruption continues from them.
    checkpoint = out.with_name(out.name + ".lines")
    summary = scan(scene, survey, out, seed=args.seed, workers=args.threads, progress=progress,
                   source=str(scene_dir), checkpoint=checkpoint, fingerprint=fp.digest)
    report = summary.to_json()
    report["survey"] = survey.to_json()
    write_cloud_summary(summary_path, report, out, fp)
    if args.trajectory:
        write_trajectory(scene, survey, Path(args.trajectory))
    if summary.lines_resumed:
        echo(f"resumed: {summary.lines_resumed} of {summary.lines} flight lines came from the interrupted run "
             f"({checkpoint})")
    _print_summary(summary, scene)
    return 0


def _print_summary(summary, scene) -> None:
    s = summary
    n_b = len(scene.buildings)
    hit_b = len(s.points_by_building)
    echo(f"{s.output}: {s.points:,} points from {s.pulses_emitted:,} pulses "
         f"({s.rays_cast:,} rays, beam {s.beam}) over {s.lines} flight lines, "
         f"{s.flight_duration_s:.0f} s of flight, {s.wall_time_s:.1f} s wall time "
         f"({s.pulses_emitted / max(s.wall_time_s, 1e-9) / 1e6:.2f} M pulses/s)")
    echo("  by surface: " + ", ".join(f"{k} {v:,}" for k, v in s.points_by_surface.items()))
    echo("  by return:  " + ", ".join(f"{k}: {v:,}" for k, v in s.points_by_return.items()))
    echo(f"  buildings with points: {hit_b} of {n_b}")


def cmd_survey_template(args) -> int:
    from ..acquisition.survey import load_survey, write_survey_template

    write_survey_template(args.output, load_survey(args.preset))
    print(f"{args.output}: survey '{args.preset}' with every field documented in '_doc'")
    return 0


def cmd_dim(args) -> int:
    """A photogrammetric (dense image matching) point cloud of a scene bundle."""
    from ..acquisition.sensors import get, simulate
    from ..formats.scene import read_scene

    scene_dir = Path(args.scene)
    out = Path(args.output)
    survey = get("dim").load_settings(args.survey)
    summary_path = out.with_name(out.name + ".summary.json")
    _refuse_replacing_inputs("dim", [out, summary_path], scene_dir, args.survey)
    fp = cloud_fingerprint("dim", scene_dir, survey, args.seed)
    if not args.force and cloud_is_up_to_date(out, summary_path, fp):
        echo(f"{out}: up to date (same scene, photo survey and seed); use --force to simulate it again")
        return 0
    summary = simulate("dim", read_scene(scene_dir), survey, out, seed=args.seed, workers=args.threads,
                       progress=reporter(args, "dim"), source=str(scene_dir))
    report = summary.to_json()
    report["photo_survey"] = survey.to_json()
    write_cloud_summary(summary_path, report, out, fp)
    print(f"dim: {summary.points:,} points from {summary.cameras:,} images (nadir GSD {100 * summary.gsd_nadir_m:.1f} cm) "
          f"in {summary.wall_time_s:.1f} s -> {out}")
    return 0


def cmd_dim_survey_template(args) -> int:
    from ..acquisition.dim_settings import preset_dim, write_photo_survey_template

    write_photo_survey_template(args.output, preset_dim(args.preset))
    print(f"photo survey template ({args.preset}) -> {args.output}")
    return 0


def add_scan(sub) -> None:
    s = sub.add_parser("scan", help="scan a scene bundle with a virtual UAV laser scanner")
    s.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    s.add_argument("-o", "--output", required=True, help="output point cloud, .las or .laz")
    s.add_argument("--survey", default="paper", help="preset name (paper, als) or survey JSON file (default paper)")
    s.add_argument("--beam", choices=("single", "adaptive", "full"), help="override the survey's beam model")
    s.add_argument("--seed", type=int, default=0, help="seed of the range noise (same seed, same bytes)")
    s.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    s.add_argument("--trajectory", help="also write the platform trajectory as CSV (also when the scan is "
                   "up to date)")
    s.add_argument("--summary", help="summary JSON path (default: OUTPUT.summary.json)")
    s.add_argument("--force", action="store_true", help="rescan even if the output is up to date, and scan a plan "
                   "beyond the size limit (500 M points)")
    s.add_argument("--dry-run", action="store_true",
                   help="print the flight plan (lines, flight time, pulses, points, file size) and stop")
    s.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    s.set_defaults(func=cmd_scan)


def add_survey_template(sub) -> None:
    t = sub.add_parser("survey-template", help="write a documented survey JSON file to edit")
    t.add_argument("-o", "--output", required=True, help="survey JSON file to write")
    t.add_argument("--preset", default="paper", help="preset whose values the file holds: paper or als "
                   "(default paper)")
    t.set_defaults(func=cmd_survey_template)


def add_dim(sub) -> None:
    dm = sub.add_parser("dim", help="simulate a photogrammetric (DIM) point cloud of a scene bundle")
    dm.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    dm.add_argument("-o", "--output", required=True, help="output point cloud, .las or .laz")
    dm.add_argument("--survey", default="paper", help="photo survey preset (paper) or JSON file (default paper)")
    dm.add_argument("--seed", type=int, default=0, help="seed of sampling and noise (same seed, same bytes)")
    dm.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    dm.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    dm.add_argument("--force", action="store_true", help="simulate again even if the output is up to date "
                    "(same scene, photo survey and seed)")
    dm.set_defaults(func=cmd_dim)


def add_dim_survey_template(sub) -> None:
    dt = sub.add_parser("dim-survey-template", help="write a documented photo survey JSON file to edit")
    dt.add_argument("-o", "--output", required=True, help="photo survey JSON file to write")
    dt.add_argument("--preset", default="paper", help="preset whose values the file holds: paper (default)")
    dt.set_defaults(func=cmd_dim_survey_template)
