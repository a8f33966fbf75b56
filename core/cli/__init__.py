"""`quakescan` command line. Argument parsing, progress and messages live here only."""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import QuakeScanError
from ..runtime.atomic import write_json
from ..runtime.workers import EVERY_CORE

log = logging.getLogger("quakescan")


class Progress:
    """The one progress reporter of the command line: `label  done/total  pct  elapsed  ETA`
    on stderr, at most every `every_s` seconds or 5 %, and always at the end.

    Called as progress(done, total, stage=""), the one shape of `quakescan.runtime.progress`. The
    line's label is the reporter's label followed by the stage; a new stage starts a new
    count: its own first report, its elapsed time from that report, its own line. Elapsed
    time of the first stage counts from the reporter's creation (the command's start). The
    ETA assumes the remaining steps go at the rate since the first report, (t1, d1):

        ETA = (now − t1) × (total − done) / (done − d1)

    so that what comes before the first step (reading the input, compiling kernels, checking
    the registration: 26 of classify's 36 s on an AHN3 tile) and a burst of steps that finish
    together (a tile's buildings) do not skew it; it is unknown ("?") until `min_basis_s` have
    passed since the first report. On a terminal a line overwrites itself; elsewhere (a log,
    `--progress` in a pipe) each report is a line of its own. `clock` and `stream` are for
    the tests."""

    def __init__(self, label: str, enabled: bool, *, clock=time.monotonic, stream=None, every_s: float = 2.0,
                 min_basis_s: float = 1.0):
        self.base, self.enabled = label, enabled
        self.clock, self.every_s, self.min_basis_s = clock, every_s, min_basis_s
        self.stream = stream
        self.stage = ""
        self._start(clock())

    def _start(self, now: float) -> None:
        self.label = " ".join(p for p in (self.base, self.stage) if p)
        self.t0 = now
        self.first = None  # (time, done) of the first report
        self.last_t, self.last_f = -float("inf"), -1.0
        self.open_line = False  # a terminal line not yet ended by its last report

    def eta_s(self, done: int, total: int, now: float) -> float | None:
        """Seconds left at the rate since the first report; None while that rate is unknown."""
        if done >= total:
            return 0.0
        if self.first is None:
            return None
        t1, d1 = self.first
        if done <= d1 or now - t1 < self.min_basis_s:
            return None
        return (now - t1) * max(total - done, 0) / (done - d1)

    def line(self, done: int, total: int, now: float) -> str:
        eta = self.eta_s(done, total, now)
        return (f"{self.label}  {done:,}/{total:,}  {100 * done / total:3.0f} %  {_clock_time(now - self.t0)}  "
                f"ETA {'?' if eta is None else _clock_time(eta)}")

    def __call__(self, done: int, total: int, stage: str = "") -> None:
        if not self.enabled or total <= 0:
            return
        stream = self.stream or sys.stderr
        now = self.clock()
        if stage != self.stage:
            if self.open_line:
                print(file=stream, flush=True)
            self.stage = stage
            self._start(now)
        if self.first is None:
            self.first = (now, done)
        f = done / total
        step = f - self.last_f >= 0.05 - 1e-9  # 1e-9: 0.06 - 0.01 is less than 0.05 in floats
        if f >= 1 or step or now - self.last_t >= self.every_s:
            tty = stream.isatty()
            end = "\n" if f >= 1 or not tty else ""
            print(("\r" if tty else "") + self.line(done, total, now), end=end, file=stream, flush=True)
            self.last_t, self.last_f = now, f
            self.open_line = not end


def _clock_time(seconds: float) -> str:
    """m:ss, or h:mm:ss from an hour."""
    s = int(round(seconds))
    h, m = divmod(s, 3600)
    return f"{h}:{m // 60:02d}:{m % 60:02d}" if h else f"{m // 60}:{m % 60:02d}"


def _progress(args, label: str) -> Progress:
    """The reporter of a command: on a terminal by default, `--progress` forces it, `-q` silences it."""
    quiet = getattr(args, "quiet", False)
    return Progress(label, not quiet and (getattr(args, "progress", False) or sys.stderr.isatty()))


@contextlib.contextmanager
def _stage_messages(args):
    """Stage messages of the multi-step commands (experiment, training-set, demo; the library logs
    them to `quakescan.stages`): plain lines on stderr, unless `-q`. The logger is as it was
    once the command ends (tests run many commands in one process)."""
    stages = logging.getLogger("quakescan.stages")
    level, propagate = stages.level, stages.propagate
    handler = None
    if getattr(args, "quiet", False):
        stages.setLevel(logging.WARNING)
    else:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        stages.addHandler(handler)
        stages.setLevel(logging.INFO)
        stages.propagate = False  # shown once, plain, also under -v
    try:
        yield
    finally:
        if handler is not None:
            stages.removeHandler(handler)
        stages.setLevel(level)
        stages.propagate = propagate


def _note(args, message: str) -> None:
    """A one-line note on stderr (an old form of an argument, ...), unless `-q`."""
    if not getattr(args, "quiet", False):
        print(f"quakescan: note: {message}", file=sys.stderr)


def _cloud_fingerprint(kind: str, scene_dir: Path, survey, seed: int):
    """What a simulated cloud depends on (`quakescan.runtime.fingerprint`): the scene bundle's bytes, the
    survey and the seed (threads do not change the bytes)."""
    from ..runtime.fingerprint import make, scene_fingerprint

    return make(kind, inputs={"scene": scene_fingerprint(scene_dir)}, settings={"survey": survey.to_json(),
                                                                              "seed": seed})


def _out(*args, **kwargs) -> None:
    """print() that survives a closed stdout (`quakescan scan … | head -1`): the command goes on
    and finishes its files, its remaining messages are dropped."""
    try:
        print(*args, **kwargs)
        if kwargs.get("file") is None:
            sys.stdout.flush()
    except BrokenPipeError:
        _drop_stdout()


def _cloud_is_up_to_date(out: Path, summary_path: Path, fp) -> bool:
    """The summary holds the same fingerprint and the output is the file the run wrote (size
    and SHA-256 as recorded): a truncated or replaced output is made again."""
    from ..runtime.fingerprint import file_sha256, matches

    if not (out.is_file() and summary_path.is_file()):
        return False
    try:
        summary = json.loads(summary_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return False
    if not matches(summary, fp):
        return False
    recorded = summary.get("output_file")
    if not isinstance(recorded, dict) or recorded.get("bytes") != out.stat().st_size:
        return False
    return recorded.get("sha256") == file_sha256(out)


def _write_cloud_summary(summary_path: Path, report: dict, out: Path, fp) -> None:
    """The run's summary with what `_cloud_is_up_to_date` compares a rerun against."""
    from ..runtime.fingerprint import file_sha256

    report["fingerprint"] = fp.digest
    report["output_file"] = {"bytes": out.stat().st_size, "sha256": file_sha256(out)}
    write_json(summary_path, report)


def _check_scan_flags(args) -> None:
    if args.seed < 0:
        raise QuakeScanError(f"--seed: expected an integer >= 0 (the same seed gives the same bytes), got {args.seed}")
    _check_threads(args.threads)


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
    fp = _cloud_fingerprint("scan", scene_dir, survey, args.seed)
    if not args.force and _cloud_is_up_to_date(out, summary_path, fp):
        if args.trajectory:
            write_trajectory(read_scene(scene_dir), survey, Path(args.trajectory))
        _out(f"{out}: up to date (same scene, survey and seed); use --force to rescan"
             + (f"; trajectory -> {args.trajectory}" if args.trajectory else ""))
        return 0
    scene = read_scene(scene_dir)
    from ..acquisition.scan import LARGE_SCAN_POINTS, MAX_SCAN_POINTS, estimate_scan

    plan = estimate_scan(scene, survey, laz=out.suffix.lower() == ".laz")
    _out(plan.describe())
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
    progress = _progress(args, f"scan {scene_dir.name}")
    # Finished flight lines are kept here; a rerun after an interruption continues from them.
    checkpoint = out.with_name(out.name + ".lines")
    summary = scan(scene, survey, out, seed=args.seed, workers=args.threads, progress=progress,
                   source=str(scene_dir), checkpoint=checkpoint, fingerprint=fp.digest)
    report = summary.to_json()
    report["survey"] = survey.to_json()
    _write_cloud_summary(summary_path, report, out, fp)
    if args.trajectory:
        write_trajectory(scene, survey, Path(args.trajectory))
    if summary.lines_resumed:
        _out(f"resumed: {summary.lines_resumed} of {summary.lines} flight lines came from the interrupted run "
             f"({checkpoint})")
    _print_summary(summary, scene)
    return 0


def _print_summary(summary, scene) -> None:
    s = summary
    n_b = len(scene.buildings)
    hit_b = len(s.points_by_building)
    _out(f"{s.output}: {s.points:,} points from {s.pulses_emitted:,} pulses "
         f"({s.rays_cast:,} rays, beam {s.beam}) over {s.lines} flight lines, "
         f"{s.flight_duration_s:.0f} s of flight, {s.wall_time_s:.1f} s wall time "
         f"({s.pulses_emitted / max(s.wall_time_s, 1e-9) / 1e6:.2f} M pulses/s)")
    _out("  by surface: " + ", ".join(f"{k} {v:,}" for k, v in s.points_by_surface.items()))
    _out("  by return:  " + ", ".join(f"{k}: {v:,}" for k, v in s.points_by_return.items()))
    _out(f"  buildings with points: {hit_b} of {n_b}")


def cmd_import_cityjson(args) -> int:
    from ..formats.cityjson import import_cityjson
    from ..formats.scene import write_scene

    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"-o {out}: exists and is not a folder; a scene bundle is a folder (give a new name)")
    if out.is_dir() and any(out.iterdir()) and not (out / "scene.json").is_file():
        raise QuakeScanError(f"-o {out}: a folder that holds other files than a scene bundle; give a new or empty "
                             "folder")
    scene = import_cityjson(args.input, lod=args.lod, terrain_margin=args.buffer, crs=args.crs,
                            material=args.material)
    if args.bbox is not None:
        from ..formats.scene import buildings_in_box, crop_to_buildings

        keep = buildings_in_box(scene, args.bbox)
        if not len(keep):
            raise QuakeScanError(f"--bbox {args.bbox}: no building of {args.input} has its centre inside")
        scene = crop_to_buildings(scene, keep, args.buffer)
    write_scene(scene, args.output)
    b = scene.bounds()
    span = (b[1, :2] - b[0, :2]) / 1e3
    _out(f"{args.output}: {len(scene.buildings)} buildings ({args.material}), {len(scene.faces):,} triangles, "
         f"{span[0]:.2f} × {span[1]:.2f} km, origin {scene.origin.tolist()}, crs {scene.crs}")
    if span.max() > LARGE_SCENE_KM:
        print(f"warning: the scene spans {span[0]:.1f} × {span[1]:.1f} km and a survey flies over all of it; "
              "--bbox X0,Y0,X1,Y1 keeps the buildings of an area (`quakescan scan --dry-run` shows the cost)",
              file=sys.stderr)
    return 0


LARGE_SCENE_KM = 2.0  # a scene wider than this makes every survey a long flight


def _bbox(text: str) -> tuple:
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X0,Y0,X1,Y1 (four numbers), got {text!r}") from None
    if not (x0 < x1 and y0 < y1):
        raise argparse.ArgumentTypeError(f"expected X0 < X1 and Y0 < Y1, got {text!r}")
    return x0, y0, x1, y1


def cmd_validate(args) -> int:
    from ..formats.scene import read_scene

    scene = read_scene(args.scene)
    _out(f"{args.scene}: valid scene bundle ({scene.epoch}), {len(scene.buildings)} buildings, "
         f"{len(scene.faces):,} triangles" + (f", crs {scene.crs}" if scene.crs else ", no crs"))
    return 0


def cmd_footprints(args) -> int:
    from ..formats.footprints import footprints_from_scene, write_footprints
    from ..formats.scene import read_scene

    fp = footprints_from_scene(read_scene(args.scene))
    write_footprints(fp, args.output)
    print(f"{args.output}: {len(fp)} building footprints (top-view outlines) of {args.scene}"
          + (f" in {fp.crs}" if fp.crs else ""))
    return 0


def cmd_survey_template(args) -> int:
    from ..acquisition.survey import load_survey, write_survey_template

    write_survey_template(args.output, load_survey(args.preset))
    print(f"{args.output}: survey '{args.preset}' with every field documented in '_doc'")
    return 0


def _csv_list(text: str | None) -> tuple | None:
    return None if text is None else tuple(t.strip() for t in text.split(",") if t.strip())


def cmd_features(args) -> int:
    """Features of every point as extra LAS dimensions (float32; CloudCompare shows them as
    scalar fields). NaN marks the degenerate neighbourhoods of quakescan.change.features."""
    import laspy

    from ..change.features import FEATURES, compute_features
    from ..formats.pointcloud import read_epoch, read_las
    from ..runtime.atomic import replacing

    names = _csv_list(args.features) or FEATURES
    src = Path(args.input)
    out = Path(args.output)
    _check_cloud_output(out, src)
    _check_number("--radius", args.radius, low=0.0, low_open=True)
    _check_threads(args.threads)
    epoch = read_epoch(src)
    las = read_las(src)
    t0 = time.perf_counter()
    try:
        feats = compute_features(epoch.xyz, args.radius, names, workers=args.threads,
                                 progress=_progress(args, f"features {src.name}"))
    except QuakeScanError as e:  # e.g. a cloud too wide for the grid: say which file
        raise QuakeScanError(f"{src}: {e}") from None
    dt = time.perf_counter() - t0
    present = set(las.point_format.dimension_names)
    clash = [n for n in names if n in present]
    if clash:
        raise QuakeScanError(f"{src}: already has dimensions {clash}; write features of another file or radius")
    las.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.float32,
                                               description=f"{n} r={args.radius:g} m"[:31]) for n in names])
    for n in names:
        las[n] = feats[n].astype(np.float32)
    with replacing(out) as tmp:
        las.write(tmp, do_compress=out.suffix.lower() == ".laz")
    print(f"features: {len(names)} features of {len(epoch):,} points at r = {args.radius:g} m in {dt:.1f} s "
          f"({len(epoch) / max(dt, 1e-9) / 1e3:,.0f} k points/s) -> {out}")
    return 0


def _check_cloud_output(out: Path, src: Path) -> None:
    """A point cloud output that is neither an existing folder nor the input, named .las/.laz
    (its suffix decides the format: anything else would get LAS bytes under a wrong name)."""
    if out.suffix.lower() not in (".las", ".laz"):
        raise QuakeScanError(f"{out}: -o must name a .las or .laz file (the suffix decides the format)")
    if out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing folder; give a .las or .laz file name")
    if out.exists() and src.exists() and os.path.samefile(out, src):
        raise QuakeScanError(f"{out}: -o is the input file; write the features to another file")


def _check_folder_output(out: Path) -> None:
    """A report folder that is not an existing file."""
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing file; give a folder for the report")


def _check_file_output(out: Path, inputs) -> None:
    """An output file that is not an existing folder and not one of the inputs."""
    if out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing folder; give a file name")
    for p in inputs:
        if p is not None and out.exists() and Path(p).exists() and os.path.samefile(out, p):
            raise QuakeScanError(f"{out}: -o is the input file {p}; write to another file")


def _check_number(flag: str, value, low=None, high=None, *, low_open=False, high_open=False,
                  integer=False) -> None:
    """Refuse a flag's value outside its range, naming the flag (argparse checks types only)."""
    if value is None:
        return
    bad = isinstance(value, float) and not np.isfinite(value)
    if low is not None:
        bad |= value <= low if low_open else value < low
    if high is not None:
        bad |= value >= high if high_open else value > high
    if bad:
        lo = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
        hi = "" if high is None else f"{'<' if high_open else '<='} {high:g}"
        what = "an integer" if integer else "a number"
        raise QuakeScanError(f"{flag}: expected {what} {' and '.join(t for t in (lo, hi) if t)}, got {value}")


SEED_MAX = 2 ** 32 - 1  # numpy and scikit-learn take seeds in [0, 2**32)


def _check_seed(value) -> None:
    _check_number("--seed", value, 0, SEED_MAX, integer=True)


def _check_threads(value) -> None:
    """--threads: the library's `workers` (`quakescan.runtime.workers`), a count >= 1 or -1 for every core."""
    if value != EVERY_CORE and value < 1:
        raise QuakeScanError(f"--threads: expected a number of worker threads >= 1 (or -1: every core), got {value}")


def _check_split_flags(args) -> None:
    """The pipeline's flags in the ranges a model may hold (quakescan.change.pipeline, quakescan.change.split), named."""
    from ..change.pipeline import RADIUS_RANGE_M
    from ..change.split import LOD_CURVATURE_RANGE, LOD_HEIGHT_RANGE_M

    _check_number("--radius", args.radius, *RADIUS_RANGE_M)
    _check_number("--lod-height", args.lod_height, *LOD_HEIGHT_RANGE_M, low_open=True)
    _check_number("--lod-curvature", args.lod_curvature, *LOD_CURVATURE_RANGE, low_open=True)
    _check_number("--min-changed-share", args.min_changed_share, 0.0, 1.0, high_open=True)


def _pipeline_settings(args):
    from ..change.pipeline import training_settings
    from ..change.split import SplitSettings

    split = SplitSettings(lod_height_m=args.lod_height, lod_curvature=args.lod_curvature,
                          min_changed_share=args.min_changed_share, seed=args.seed)
    return training_settings(getattr(args, "descriptors", "paper"), radius_m=args.radius,
                             point_features=_csv_list(args.features) or None, split=split,
                             per_point_lod=bool(getattr(args, "per_point_lod", False)))


def cmd_calibrate_lod(args) -> int:
    """Levels of detection of the split from two acquisitions of the same undamaged buildings."""
    from ..change.lod import calibrate
    from ..learning.classification import load_pair

    _check_number("--radius", args.radius, low=0.0, low_open=True)
    _check_number("--quantile", args.quantile, 0.5, 1.0, low_open=True, high_open=True)
    _check_seed(args.seed)
    _check_threads(args.threads)
    first_path, second_path = _first_and_second(args)
    if args.output:
        _check_file_output(Path(args.output), [first_path, second_path, args.footprints])
    # classify's reading and checks (same CRS, overlapping extents, footprints in the clouds'
    # CRS); building points from footprints for real clouds, as classify assigns them
    pair = load_pair(first_path, second_path, args.footprints, args.id_field)
    first, second = pair.pre, pair.post
    lod = calibrate(first, second, radius_m=args.radius, quantile=args.quantile, seed=args.seed,
                    workers=args.threads, progress=_progress(args, "calibrate-lod"))
    print(f"calibrate-lod: {lod.points:,} building points; at the {100 * args.quantile:g}th percentile "
          f"|Δheight| {lod.height_at_quantile_m:.3f} m, |Δcurvature| {lod.curvature_at_quantile:.3f} 1/m")
    print(f"levels of detection: --lod-height {lod.lod_height_m:.3f} --lod-curvature {lod.lod_curvature:.3f}")
    if args.output:
        from ..runtime.atomic import write_text

        out = Path(args.output)
        write_text(out, json.dumps(lod.to_json(), indent=1))
        print(f"-> {out}")
    return 0


def _old_form(args, form: str, use: str) -> None:
    _note(args, f"`{form}` is the old form of this argument; `{use}` is the form to use")


def _training_pairs(args) -> list:
    """The pairs of `train`: --pre/--post (repeated, in order), or the older --pair PRE POST."""
    pre, post = args.pre or [], args.post or []
    if len(pre) != len(post):
        raise QuakeScanError(f"train: {len(pre)} --pre and {len(post)} --post: give one --post per --pre")
    if args.pair and pre:
        raise QuakeScanError("train: give the pairs as --pre/--post or as --pair, not both")
    if args.pair:
        _old_form(args, "--pair PRE POST", "--pre PRE --post POST")
        return [tuple(p) for p in args.pair]
    if not pre:
        raise QuakeScanError("train: no training pair; give --pre PRE --post POST (repeat both for more pairs)")
    return list(zip(pre, post))


def _first_and_second(args) -> tuple:
    """The two clouds of `calibrate-lod`: --pre/--post, or the older positional FIRST SECOND."""
    if args.first is None and args.second is None:
        if not (args.pre and args.post):
            raise QuakeScanError("calibrate-lod: give both clouds: --pre FIRST --post SECOND")
        return args.pre, args.post
    if args.pre or args.post:
        raise QuakeScanError("calibrate-lod: give the clouds as --pre/--post or as positional FIRST SECOND, not both")
    if args.second is None:
        raise QuakeScanError(f"calibrate-lod: only one cloud ({args.first}); give --pre FIRST --post SECOND")
    _old_form(args, "calibrate-lod FIRST SECOND", "calibrate-lod --pre FIRST --post SECOND")
    return args.first, args.second


def _robustness_scenes(args) -> tuple:
    """Pre-event scene and post-event scene(s) of `robustness`: --pre/--post, or the older
    positional PRE POST [POST2 ...]."""
    if args.scenes:
        if args.pre or args.post:
            raise QuakeScanError("robustness: give the scenes as --pre/--post or as positional PRE POST, not both")
        if len(args.scenes) < 2:
            raise QuakeScanError(f"robustness: only one scene ({args.scenes[0]}); "
                                 "give --pre PRE --post POST [POST2 …]")
        _old_form(args, "robustness PRE POST …", "robustness --pre PRE --post POST …")
        return args.scenes[0], args.scenes[1:]
    if not (args.pre and args.post):
        raise QuakeScanError("robustness: give the scenes: --pre PRE_SCENE --post POST_SCENE [POST2 …]")
    return args.pre, args.post


def cmd_train(args) -> int:
    from ..learning.model import save_model
    from ..learning.training import TrainingError, TrainingPair, train

    _check_number("--trees", args.trees, 1, integer=True)
    _check_number("--depth", args.depth, 1, integer=True)
    _check_number("--test-size", args.test_size, 0.0, 1.0, high_open=True)
    _check_seed(args.seed)
    _check_threads(args.threads)
    _check_split_flags(args)
    args.pair = _training_pairs(args)
    out = Path(args.output)
    _check_file_output(out, [p for pair in args.pair for p in pair] + list(args.truth or []) + [args.footprints])
    if args.truth and len(args.truth) != len(args.pair):
        n = len(args.pair)
        raise TrainingError(f"{len(args.truth)} --truth files for {n} pair{'s' * (n != 1)}: give one per pair "
                            "or none (then grades come from the post epochs' grade dimension)")
    pairs = [TrainingPair(pre, post, args.truth[k] if args.truth else None, args.footprints)
             for k, (pre, post) in enumerate(args.pair)]
    settings = _pipeline_settings(args)
    model, ev, table = train(pairs, settings, n_estimators=args.trees, max_depth=args.depth,
                             test_size=args.test_size, seed=args.seed, workers=args.threads,
                             progress=_progress(args, "describe"),  # a stage per pair
                             command="quakescan " + " ".join(sys.argv[1:]),
                             rule=settings.paper_descriptors)
    save_model(model, out)
    counts = dict(zip(*np.unique(table.y, return_counts=True)))
    print(f"train: {len(table.y)} building rows from {len(pairs)} pairs, grades {counts}; "
          f"{model.provenance['n_train']} train / {model.provenance['n_test']} test (grouped by building)")
    if ev is not None:
        print(f"held-out test: overall accuracy {100 * ev.overall_accuracy:.1f} % on {ev.n} buildings")
        print(ev.table())
    print(f"model -> {out}")
    return 0


def cmd_classify(args) -> int:
    from ..learning.classification import classify

    _check_threads(args.threads)
    summary = classify(args.pre, args.post, args.output, model_path=args.model, footprints_path=args.footprints,
                       id_field=args.id_field, align=args.align, workers=args.threads,
                       progress=_progress(args, "classify"),
                       write_las=not args.no_las, laz=args.laz, force=args.force)
    if summary.get("up_to_date"):
        print(f"{args.output}: up to date (same inputs, model and options); --force recomputes")
        return 0
    out = Path(args.output)
    reg = summary.get("registration", {})
    if "alignment" in summary:
        a = summary["alignment"]
        why = (f"the epochs disagreed by up to {reg['offset_m']:.2f} m on stable ground (tolerance "
               f"{reg['tolerance_m']:.2f} m); " if reg.get("mode") == "auto" else "")
        print(f"alignment (ICP on stable areas): {why}std {a['std_after_m']:.3f} m, rmse {a['rmse_before_m']:.3f} -> "
              f"{a['rmse_after_m']:.3f} m")
    elif reg.get("mode") == "auto" and not reg.get("checked"):
        print(f"registration not checked ({reg.get('reason')}): an offset between the epochs would read as damage")
    labels = ", ".join(f"{k}: {v}" for k, v in summary["by_grade_name"].items())
    print(f"classify: {summary['buildings']} buildings ({labels}) in {summary['seconds']['total']:.1f} s")
    print(f"results -> {out / 'buildings.csv'}, {out / 'buildings.geojson'} (QGIS style buildings.qml), "
          f"{out / 'damage_map.png'}, {out / 'damage_map.html'} (opens offline)"
          + (f", {summary['post_grades']}" if "post_grades" in summary else ""))
    return 0


def cmd_evaluate(args) -> int:
    from ..results.evaluation import evaluate_files, plot_confusion

    out = Path(args.output) if args.output else Path(args.result).parent
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing file; evaluate writes a folder (confusion.png, "
                             "evaluation.json)")
    ev = evaluate_files(args.result, args.truth)
    print(f"evaluate: {ev.n} assessable buildings, overall accuracy {100 * ev.overall_accuracy:.1f} %"
          + (f", {ev.not_assessable} not assessable" if ev.not_assessable else "")
          + (f", {len(ev.missing)} in the truth but not in the result" if ev.missing else ""))
    print(ev.table())
    plot_confusion(ev, out / "confusion.png")
    write_json(out / "evaluation.json", ev.to_json())
    print(f"confusion matrix -> {out / 'confusion.png'}, metrics -> {out / 'evaluation.json'}")
    return 0


def cmd_dim(args) -> int:
    """A photogrammetric (dense image matching) point cloud of a scene bundle."""
    from ..acquisition.sensors import get, simulate
    from ..formats.scene import read_scene

    scene_dir = Path(args.scene)
    out = Path(args.output)
    survey = get("dim").load_settings(args.survey)
    summary_path = out.with_name(out.name + ".summary.json")
    fp = _cloud_fingerprint("dim", scene_dir, survey, args.seed)
    if not args.force and _cloud_is_up_to_date(out, summary_path, fp):
        _out(f"{out}: up to date (same scene, photo survey and seed); use --force to simulate it again")
        return 0
    summary = simulate("dim", read_scene(scene_dir), survey, out, seed=args.seed, workers=args.threads,
                       progress=_progress(args, "dim"), source=str(scene_dir))
    report = summary.to_json()
    report["photo_survey"] = survey.to_json()
    _write_cloud_summary(summary_path, report, out, fp)
    print(f"dim: {summary.points:,} points from {summary.cameras:,} images (nadir GSD {100 * summary.gsd_nadir_m:.1f} cm) "
          f"in {summary.wall_time_s:.1f} s -> {out}")
    return 0


def cmd_dim_survey_template(args) -> int:
    from ..acquisition.dim_settings import preset_dim, write_photo_survey_template

    write_photo_survey_template(args.output, preset_dim(args.preset))
    print(f"photo survey template ({args.preset}) -> {args.output}")
    return 0


def cmd_robustness(args) -> int:
    """The paper's robust-feature selection: relative change per feature on ULS vs DIM clouds."""
    from ..studies.robustness.run import run_experiment
    from ..studies.robustness.selection import DEFAULT_SAMPLE, check_spacing

    try:
        radii = tuple(float(r) for r in args.radii.split(",")) if args.radii else None
    except ValueError:
        raise QuakeScanError(f"--radii: expected comma-separated numbers of metres, got {args.radii!r}") from None
    if radii is not None and not all(np.isfinite(r) and r > 0 for r in radii):
        raise QuakeScanError(f"--radii: every radius must be a positive number of metres, got {args.radii!r}")
    _check_folder_output(Path(args.output))
    kw = {"radii": radii} if radii else {}
    try:
        spacing = check_spacing(args.spacing)
    except QuakeScanError as e:
        raise QuakeScanError(f"--spacing {args.spacing}: {e}") from None
    _check_seed(args.seed)
    _check_threads(args.threads)
    _check_number("--threshold", args.threshold, 0.0)
    sample = DEFAULT_SAMPLE if args.sample is None else (None if args.sample == 0 else args.sample)
    if sample is not None and sample < 0:
        raise QuakeScanError(f"--sample: expected a number of points >= 0 (0 = all), got {args.sample}")
    pre, posts = _robustness_scenes(args)
    post = posts[0] if len(posts) == 1 else posts
    res = run_experiment(pre, post, args.output, seed=args.seed, workers=args.threads,
                         progress=_progress(args, "robustness"),
                         threshold_pct=args.threshold, spacing=spacing, sample=sample, **kw)
    stages = f" over {len(res.stages)} stages" if len(res.stages) > 1 else ""
    print(f"robustness: best radius {res.best_radius:g} m, {len(res.robust)} robust features at "
          f"<= {args.threshold:g} %{stages}: {', '.join(res.robust)}")
    print(f"report -> {Path(args.output) / 'README.md'}")
    return 0


def cmd_training_set(args) -> int:
    """The transfer training set: cities, random acquisitions, descriptor tables (resumable)."""
    from ..learning.default_model import TABLE_SETTINGS
    from ..learning.trainset import build, default_plan

    _check_seed(args.seed)
    _check_threads(args.threads)
    _check_folder_output(Path(args.output))
    table = build(args.output, default_plan(args.seed, args.size, args.scenes, args.damage, args.small),
                  TABLE_SETTINGS, workers=args.threads,
                  progress=_progress(args, "training set"))
    counts = dict(zip(*(v.tolist() for v in np.unique(table.y, return_counts=True))))
    print(f"{args.output}: {len(table.y)} building rows, grades {counts}; manifest.json and tables/")
    return 0


def cmd_experiment(args) -> int:
    """The paper's four classifiers evaluated on a held-out region-specific DIM city."""
    from ..change.split import LOD_CURVATURE_RANGE, LOD_HEIGHT_RANGE_M
    from ..results.evaluation import metric_text
    from ..studies.experiment import ExperimentSettings, run_paper_experiment

    mix = None
    if args.test_mix:
        try:
            mix = {int(g): int(n) for g, n in (p.split(":") for p in args.test_mix.split(","))}
        except ValueError:
            raise QuakeScanError(f"--test-mix: expected GRADE:COUNT,..., got {args.test_mix!r}") from None
    if mix is not None and (any(g not in (0, 3, 4, 5) or n < 0 for g, n in mix.items()) or sum(mix.values()) < 1):
        raise QuakeScanError(f"--test-mix: grades must be 0, 3, 4 or 5 with counts >= 0 (at least one building), "
                             f"got {args.test_mix!r}")
    if args.buildings < 4:
        raise QuakeScanError(f"--buildings: buildings per training dataset must be >= 4, got {args.buildings}")
    _check_folder_output(Path(args.output))
    _check_number("--trees", args.trees, 1, integer=True)
    _check_seed(args.seed)
    _check_threads(args.threads)
    _check_number("--lod-height", args.lod_height, *LOD_HEIGHT_RANGE_M, low_open=True)
    _check_number("--lod-curvature", args.lod_curvature, *LOD_CURVATURE_RANGE, low_open=True)
    settings = ExperimentSettings(buildings=args.buildings, test_mix=mix, seed=args.seed, n_estimators=args.trees,
                                  lod_height_m=args.lod_height, lod_curvature=args.lod_curvature,
                                  training=args.training)
    results = run_paper_experiment(args.output, settings, workers=args.threads,
                                   progress=_progress(args, "experiment"))
    for name, ev in results.items():
        print(f"{name}: overall accuracy {100 * ev.overall_accuracy:.1f} %, damaged vs undamaged F1 "
              f"{metric_text(ev.damaged, 'f1')}")
    print(f"report -> {Path(args.output) / 'README.md'}")
    return 0


def cmd_demo(args) -> int:
    """The built-in default: generate a small city, scan both epochs, classify, evaluate, map."""
    from ..demo import run_demo

    r = run_demo(args.output, seed=args.seed, buildings=args.buildings,
                 progress=_progress(args, ""))  # its stages name themselves: "scan pre", ...
    ev = r["evaluation"]
    s = r["summary"]
    by_name = s.get("by_grade_name") or dict(sorted(s["by_label"].items()))  # a summary of an older QuakeScan
    labels = ", ".join(f"{k}: {v}" for k, v in by_name.items())
    print(f"demo: {s['buildings']} buildings classified ({labels})")
    print(f"demo: overall accuracy {100 * ev.overall_accuracy:.1f} % on {ev.n} assessable buildings")
    print(ev.table())
    res = r["result"]
    print(f"demo: results in {res}/ (buildings.csv, buildings.geojson with its QGIS style buildings.qml, "
          "damage_map.png, damage_map.html, post_grades.las, confusion.png, evaluation.json)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quakescan", description="Virtual UAV laser scanning of damaged buildings.")
    p.add_argument("--version", action="version", version=f"quakescan {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    p.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="run the whole chain on a built-in default: generate a small city, "
                       "scan both epochs, classify with the shipped model, evaluate, draw the map")
    d.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--seed", type=int, default=0, help="seed of the city and of both scans (default 0)")
    d.add_argument("--buildings", type=int, default=30, help="buildings in the demo city (default 30)")
    d.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    d.set_defaults(func=cmd_demo)

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

    from ..formats.scene import MATERIALS

    c = sub.add_parser("import-cityjson", help="convert a CityJSON city model into a scene bundle")
    c.add_argument("input", help="CityJSON file (1.0, 1.1, 2.0)")
    c.add_argument("-o", "--output", required=True, help="scene bundle folder to write")
    c.add_argument("--lod", default=None, help="level of detail to use (default: the highest per building)")
    c.add_argument("--bbox", type=_bbox, default=None, metavar="X0,Y0,X1,Y1",
                   help="keep the buildings whose centre lies in this box (the model's coordinates)")
    c.add_argument("--buffer", type=float, default=20.0,
                   help="terrain around each cluster of buildings, m (default 20; buildings closer than twice "
                   "this share one terrain patch)")
    c.add_argument("--crs", default=None, metavar="EPSG:NNNN",
                   help="CRS of a file whose metadata names none (must agree with the file's when it names one)")
    c.add_argument("--material", choices=MATERIALS, default="masonry",
                   help="material of every imported building (default masonry): damage patterns and the "
                   "scanner's reflectance depend on it")
    c.set_defaults(func=cmd_import_cityjson)

    v = sub.add_parser("validate", help="check a scene bundle and report the first problem")
    v.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    v.set_defaults(func=cmd_validate)

    fo = sub.add_parser("footprints", help="building footprints (top-view outlines) of a scene bundle as GeoJSON, "
                        "to label simulated clouds as real ones are labelled (classify --footprints)")
    fo.add_argument("scene", help="scene bundle folder (the pre-event scene: a cadastre predates the event)")
    fo.add_argument("-o", "--output", required=True, help="GeoJSON file to write")
    fo.set_defaults(func=cmd_footprints)

    t = sub.add_parser("survey-template", help="write a documented survey JSON file to edit")
    t.add_argument("-o", "--output", required=True, help="survey JSON file to write")
    t.add_argument("--preset", default="paper", help="preset whose values the file holds: paper or als "
                   "(default paper)")
    t.set_defaults(func=cmd_survey_template)

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

    dt = sub.add_parser("dim-survey-template", help="write a documented photo survey JSON file to edit")
    dt.add_argument("-o", "--output", required=True, help="photo survey JSON file to write")
    dt.add_argument("--preset", default="paper", help="preset whose values the file holds: paper (default)")
    dt.set_defaults(func=cmd_dim_survey_template)

    rb = sub.add_parser("robustness", help="which change features agree between ULS and DIM clouds (paper's "
                        "robust-feature selection)")
    rb.add_argument("scenes", nargs="*", metavar="SCENE", help="old form of --pre PRE --post POST …: "
                    "PRE POST [POST2 …] (still accepted)")
    rb.add_argument("--pre", help="pre-event scene bundle folder")
    rb.add_argument("--post", nargs="+", help="post-event scene bundle folder(s) of the same buildings; several: "
                    "demolition stages in order (robust = ULS and DIM agree at every stage)")
    rb.add_argument("-o", "--output", required=True, help="report folder (clouds are kept in OUTPUT/clouds)")
    rb.add_argument("--radii", help="comma-separated radii in m (default 1.0,1.5,...,4.0)")
    rb.add_argument("--threshold", type=float, default=10.0, help="robust if ULS and DIM differ by <= this, %% "
                    "(default 10)")
    rb.add_argument("--spacing", type=str, default=None, help="thin every cloud to about this point spacing in m "
                    "first (voxel grid, one seeded random point per cell; the paper: 0.1); default: no thinning")
    rb.add_argument("--sample", type=int, default=None, help="pre-event building points used (seeded sample; "
                    "default 20000, 0 = all)")
    rb.add_argument("--seed", type=int, default=0, help="seed of the scans, the thinning and the sample (default 0)")
    rb.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    rb.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    rb.set_defaults(func=cmd_robustness)

    ts = sub.add_parser("training-set", help="the transfer training set of the shipped model: many cities, random "
                        "ULS/ALS/DIM acquisitions, cross-source pairs, descriptor tables (resumable)")
    ts.add_argument("-o", "--output", required=True, help="folder for scenes, clouds, tables and manifest.json")
    ts.add_argument("--size", choices=("full", "large", "quick"), default="full",
                    help="full: ~2,900 buildings (the shipped model's); large: ~5,700 (full and as many again); "
                    "quick: 2 small cities")
    ts.add_argument("--seed", type=int, default=0, help="seed of the cities and acquisitions (default 0)")
    ts.add_argument("--scenes", choices=("clean", "realistic"), default="clean",
                    help="realistic: the same cities and acquisitions with roof and facade detail, trees, cars and "
                    "street furniture, buildings labelled through footprints as on real data")
    ts.add_argument("--damage", choices=("patterns", "both"), default="patterns",
                    help="both: with --scenes clean, also a twin of four mixed cities whose grade-4/5 buildings "
                    "collapse by rigid-body simulation (Blender; ~8 s a building), acquired as their twins")
    ts.add_argument("--small", action="store_true",
                    help="full/large: also two cities of small buildings (sheds, garages, row houses), acquired "
                    "ALS-like before")
    ts.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    ts.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    ts.set_defaults(func=cmd_training_set)

    ex = sub.add_parser("experiment", help="the paper's experiment: four classifiers on a held-out DIM city")
    ex.add_argument("which", choices=("paper",), help="which experiment (paper)")
    ex.add_argument("-o", "--output", required=True, help="report folder (data are kept in OUTPUT/data)")
    ex.add_argument("--buildings", type=int, default=112, help="buildings per training dataset (default 112)")
    ex.add_argument("--test-mix", help="test city grade counts (default the paper's 0:35,3:19,4:32,5:35)")
    ex.add_argument("--trees", type=int, default=100, help="trees in each random forest (default 100)")
    ex.add_argument("--training", choices=("paper", "paper+mixed"), default="paper+mixed",
                    help="training sets: the paper's design only, or with a mixed city each (default)")
    ex.add_argument("--lod-height", type=float, default=None,
                    help="level of detection of height change, m (default: measured on a DIM rescan)")
    ex.add_argument("--lod-curvature", type=float, default=None,
                    help="level of detection of curvature change, 1/m (default: measured on a DIM rescan)")
    ex.add_argument("--seed", type=int, default=0, help="seed of the cities, acquisitions and forests (default 0)")
    ex.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    ex.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    ex.set_defaults(func=cmd_experiment)

    f = sub.add_parser("features", help="per-point geometric features as extra LAS dimensions")
    f.add_argument("input", help="LAS/LAZ point cloud")
    f.add_argument("-o", "--output", required=True, help="output LAS/LAZ with one extra dimension per feature")
    f.add_argument("--radius", type=float, required=True, help="spherical neighbourhood radius in m")
    f.add_argument("--features", help="comma-separated names (default: all 24)")
    f.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    f.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    f.set_defaults(func=cmd_features)

    lc = sub.add_parser("calibrate-lod", help="levels of detection of the changed/unchanged split, measured on "
                        "two acquisitions of the same undamaged buildings (use them with train --lod-*)")
    lc.add_argument("first", nargs="?", help="old form of --pre FIRST (still accepted)")
    lc.add_argument("second", nargs="?", help="old form of --post SECOND (still accepted)")
    lc.add_argument("--pre", metavar="FIRST", help="LAS/LAZ of undamaged buildings with building IDs")
    lc.add_argument("--post", metavar="SECOND", help="the same buildings acquired again with the same scanner "
                    "or camera")
    lc.add_argument("-o", "--output", help="also write the levels as JSON")
    lc.add_argument("--footprints", help="GeoJSON building footprints in the clouds' CRS (real clouds without a "
                    "building_id dimension)")
    lc.add_argument("--id-field", default=None, help="footprint property holding the building ID (integer, or "
                    "text: buildings are then numbered and keep it as footprint_id)")
    lc.add_argument("--radius", type=float, default=1.5, help="feature radius in m (default 1.5)")
    lc.add_argument("--quantile", type=float, default=0.999, help="quantile of |change| (default 0.999)")
    lc.add_argument("--seed", type=int, default=0, help="seed of the sample of building points (default 0)")
    lc.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    lc.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    lc.set_defaults(func=cmd_calibrate_lod)

    def pipeline_options(q):
        q.add_argument("--radius", type=float, default=1.5, help="feature radius in m (default 1.5)")
        q.add_argument("--features", help="point features whose change describes a building "
                       "(default: the paper's robust set)")
        q.add_argument("--lod-height", type=float, default=0.3, help="level of detection of height change, m "
                       "(default 0.3)")
        q.add_argument("--lod-curvature", type=float, default=0.2, help="level of detection of curvature change, 1/m "
                       "(default 0.2)")
        q.add_argument("--min-changed-share", type=float, default=0.003,
                       help="fewer changed points than this share of a building: unchanged (default 0.003)")

    tr = sub.add_parser("train", help="train a random forest from labelled pre/post pairs")
    tr.add_argument("--pre", action="append", help="pre-event point cloud of a pair (repeat --pre and --post "
                    "for more pairs, in the same order)")
    tr.add_argument("--post", action="append", help="post-event point cloud of a pair")
    tr.add_argument("--pair", nargs=2, action="append", metavar=("PRE", "POST"),
                    help="old form of --pre PRE --post POST (still accepted)")
    tr.add_argument("--truth", action="append", help="CSV building_id,grade per pair (default: the post "
                    "epoch's grade dimension)")
    tr.add_argument("--footprints", help="GeoJSON footprints when the clouds have no building_id")
    pipeline_options(tr)
    tr.add_argument("--descriptors", choices=("paper", "surface", "both"), default="paper",
                    help="paper: the paper's change descriptors (split, no-change rule); surface: the "
                    "density-invariant descriptors of the shipped model (every building asked); both")
    tr.add_argument("--per-point-lod", action="store_true",
                    help="the paper's split with per-point levels of detection (M3C2 and the curvature's "
                    "standard error; --lod-height/--lod-curvature stay as floors)")
    tr.add_argument("--trees", type=int, default=100, help="trees in the random forest (default 100)")
    tr.add_argument("--depth", type=int, default=5, help="maximum depth of each tree (default 5)")
    tr.add_argument("--test-size", type=float, default=0.3, help="held-out share of buildings (default 0.3)")
    tr.add_argument("--seed", type=int, default=0, help="seed of the k-means split, the train/test split and the "
                    "forest (default 0)")
    tr.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    tr.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    tr.add_argument("-o", "--output", required=True, help="model file (.skops)")
    tr.set_defaults(func=cmd_train)

    cl = sub.add_parser("classify", help="damage grade per building from a pre/post pair")
    cl.add_argument("--pre", required=True, help="pre-event LAS/LAZ")
    cl.add_argument("--post", required=True, help="post-event LAS/LAZ (same CRS)")
    cl.add_argument("--footprints", help="GeoJSON building footprints in the clouds' CRS "
                    "(default: the clouds' building_id dimension)")
    cl.add_argument("--id-field", help="footprint property holding the building ID (integer, or text: buildings "
                    "are then numbered and keep it as footprint_id)")
    cl.add_argument("--model", help="model file (default: the shipped generic model)")
    reg = cl.add_mutually_exclusive_group()
    reg.add_argument("--align", dest="align", action="store_const", const=True, default=None,
                     help="ICP-align post to pre on stable areas first (default: check the registration and "
                     "align only where the epochs disagree beyond the model's tolerance)")
    reg.add_argument("--no-align", dest="align", action="store_const", const=False,
                     help="take the epochs as they are, unchecked")
    cl.add_argument("--no-las", action="store_true", help="skip the per-point LAS of predicted grades")
    cl.add_argument("--force", action="store_true", help="recompute even when OUT_DIR holds the finished results "
                    "of the same inputs, model and options")
    cl.add_argument("--laz", action="store_const", const=True, default=None,
                    help="compress the per-point grades (post_grades.laz); default: as the post-event file is")
    cl.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    cl.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    cl.add_argument("-o", "--output", required=True, help="output folder")
    cl.set_defaults(func=cmd_classify)

    ev = sub.add_parser("evaluate", help="accuracy of a classification against the truth")
    ev.add_argument("result", help="buildings.csv written by classify")
    ev.add_argument("--truth", required=True, help="CSV building_id,grade or a post-event scene bundle folder")
    ev.add_argument("-o", "--output", help="folder for confusion.png and evaluation.json (default: the result's)")
    ev.set_defaults(func=cmd_evaluate)
    for command in sub.choices.values():  # `quakescan CMD … -q` as well as `quakescan -q CMD …`
        command.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
    return p


# One knob with one default in every command: -1, every core, as the library's `workers`
# (`quakescan.runtime.workers`); outputs are the same bytes whatever it is, so the fastest is the default.
THREADS_HELP = "worker threads, >= 1, or -1 for every core (default: -1); the results do not depend on it"
PROGRESS_HELP = ("show progress (done/total, %%, elapsed, ETA) even when stderr is not a terminal; "
                 "on a terminal it is shown unless -q")
QUIET_HELP = "no progress, stage messages or notes on stderr (warnings and errors stay)"


def tune_allocator() -> None:
    """Keep freed batch buffers in the heap (glibc only).

    A scan allocates and frees ~100 MB per batch and thread; by default glibc returns such
    blocks to the OS and the next batch page-faults them back. BENCHMARKS.md compares the
    single-ray scan with and without it in the same run (the difference is within this
    machine's run-to-run noise for the fused single-ray loop; it mattered for the older,
    allocation-heavy path). Done here, in the command, not in the library: it is a
    process-wide setting."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 512 << 20)
        libc.mallopt(m_trim_threshold, 2 << 30)
    except (OSError, AttributeError, TypeError):
        pass  # not glibc: keep the default allocator


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    tune_allocator()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        with _stage_messages(args):
            code = args.func(args)
    except QuakeScanError as e:
        print(f"quakescan: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("quakescan: interrupted; nothing partial was left under the output names (a rerun of scan or "
              "classify continues from its finished flight lines or tiles)", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `quakescan … | head -1`: the reader left while the command still printed
        _drop_stdout()
        print("quakescan: the output pipe closed before the command finished", file=sys.stderr)
        return 141  # as a shell reports a command ended by SIGPIPE
    try:
        sys.stdout.flush()  # a closed pipe shows here, at the last buffered line, not at exit
    except BrokenPipeError:
        _drop_stdout()  # the command finished; only its messages went unread
    return code


def _drop_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's flush at exit does not fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
