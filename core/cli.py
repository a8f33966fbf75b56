"""`quakescan` command line. Argument parsing, progress and messages live here only."""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import QuakeScanError

log = logging.getLogger("quakescan")


class _Progress:
    """A percentage on stderr, at most every 2 s or 5 %."""

    def __init__(self, label: str, enabled: bool):
        self.label, self.enabled = label, enabled
        self.last_t, self.last_f = 0.0, -1.0

    def __call__(self, done, total):
        if not self.enabled or total <= 0:
            return
        f = done / total
        now = time.monotonic()
        if f >= 1 or f - self.last_f >= 0.05 or now - self.last_t >= 2:
            print(f"\r{self.label}: {100 * f:5.1f} %", end="" if f < 1 else "\n", file=sys.stderr, flush=True)
            self.last_t, self.last_f = now, f


def _fingerprint(scene_dir: Path, survey, seed: int) -> str:
    h = hashlib.sha256()
    for name in ("scene.json", "mesh.ply"):
        p = scene_dir / name
        if p.is_file():
            h.update(p.read_bytes())
    h.update(json.dumps(survey.to_json(), sort_keys=True).encode())
    h.update(str(seed).encode())
    h.update(__version__.encode())
    return h.hexdigest()[:16]


def cmd_scan(args) -> int:
    from .scan import scan
    from .scene import read_scene
    from .survey import load_survey

    scene_dir = Path(args.scene)
    out = Path(args.output)
    survey = load_survey(args.survey)
    if args.beam:
        survey = survey.replace(beam=args.beam)
    summary_path = Path(args.summary) if args.summary else out.with_name(out.name + ".summary.json")
    fp = _fingerprint(scene_dir, survey, args.seed)
    if not args.force and out.is_file() and summary_path.is_file():
        try:
            if json.loads(summary_path.read_text()).get("fingerprint") == fp:
                print(f"{out}: up to date (same scene, survey and seed); use --force to rescan")
                return 0
        except json.JSONDecodeError:
            pass
    scene = read_scene(scene_dir)
    progress = _Progress(f"scan {scene_dir.name}", args.progress or sys.stderr.isatty())
    summary = scan(scene, survey, out, seed=args.seed, threads=args.threads, progress=progress,
                   source=str(scene_dir))
    report = summary.to_json()
    report["fingerprint"] = fp
    report["survey"] = survey.to_json()
    _write_json_atomic(summary_path, report)
    if args.trajectory:
        _write_trajectory(scene, survey, Path(args.trajectory))
    _print_summary(summary, scene)
    return 0


def _write_json_atomic(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


def _write_trajectory(scene, survey, path: Path) -> None:
    from .scan import ground_level
    from .survey import plan_flight

    plan = plan_flight(survey, scene.bounds(), ground_level(scene))
    traj = plan.trajectory()
    traj[:, 1:4] += scene.origin
    tmp = path.with_name(path.name + ".tmp")
    np.savetxt(tmp, traj, delimiter=",", fmt=["%.6f", "%.3f", "%.3f", "%.3f", "%.3f", "%d"],
               header="gps_time_s,x_m,y_m,z_m,heading_deg,line", comments="")
    os.replace(tmp, path)


def _print_summary(summary, scene) -> None:
    s = summary
    n_b = len(scene.buildings)
    hit_b = len(s.points_by_building)
    print(f"{s.output}: {s.points:,} points from {s.pulses_emitted:,} pulses "
          f"({s.rays_cast:,} rays, beam {s.beam}) over {s.lines} flight lines, "
          f"{s.flight_duration_s:.0f} s of flight, {s.wall_time_s:.1f} s wall time "
          f"({s.pulses_emitted / max(s.wall_time_s, 1e-9) / 1e6:.2f} M pulses/s)")
    print("  by surface: " + ", ".join(f"{k} {v:,}" for k, v in s.points_by_surface.items()))
    print("  by return:  " + ", ".join(f"{k}: {v:,}" for k, v in s.points_by_return.items()))
    print(f"  buildings with points: {hit_b} of {n_b}")


def cmd_import_cityjson(args) -> int:
    from .cityjson import import_cityjson
    from .scene import write_scene

    scene = import_cityjson(args.input, lod=args.lod)
    write_scene(scene, args.output)
    print(f"{args.output}: {len(scene.buildings)} buildings, {len(scene.faces):,} triangles, "
          f"origin {scene.origin.tolist()}, crs {scene.crs}")
    return 0


def cmd_validate(args) -> int:
    from .scene import read_scene

    scene = read_scene(args.scene)
    print(f"{args.scene}: valid scene bundle ({scene.epoch}), {len(scene.buildings)} buildings, "
          f"{len(scene.faces):,} triangles")
    return 0


def cmd_survey_template(args) -> int:
    from .survey import load_survey, write_survey_template

    write_survey_template(args.output, load_survey(args.preset))
    print(f"{args.output}: survey '{args.preset}' with every field documented in '_doc'")
    return 0


def cmd_demo(args) -> int:
    """The built-in default: a small box city, scanned with the paper's survey."""
    from .scan import scan
    from .scene import read_scene, write_scene
    from .survey import preset
    from .synthetic import box_city

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    scene_dir = out / "scene_pre"
    write_scene(box_city(rows=3, cols=4, footprint=14.0, street=12.0, height=(9.0, 12.0, 15.0, 6.0)),
                scene_dir)
    scene = read_scene(scene_dir)
    survey = preset("paper")
    las = out / "pre.las"
    summary = scan(scene, survey, las, seed=args.seed, progress=_Progress("scan demo", sys.stderr.isatty()),
                   source=str(scene_dir))
    report = summary.to_json()
    report["survey"] = survey.to_json()
    _write_json_atomic(out / "pre.las.summary.json", report)
    _print_summary(summary, scene)
    print(f"demo: scene bundle {scene_dir}, point cloud {las}, summary {out / 'pre.las.summary.json'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quakescan", description="Virtual UAV laser scanning of damaged buildings.")
    p.add_argument("--version", action="version", version=f"quakescan {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="run the built-in default end to end (box city → scan → LAS + summary)")
    d.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("scan", help="scan a scene bundle with a virtual UAV laser scanner")
    s.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    s.add_argument("-o", "--output", required=True, help="output point cloud, .las or .laz")
    s.add_argument("--survey", default="paper", help="preset name (paper) or survey JSON file")
    s.add_argument("--beam", choices=("single", "adaptive", "full"), help="override the survey's beam model")
    s.add_argument("--seed", type=int, default=0, help="seed of the range noise (same seed, same bytes)")
    s.add_argument("--threads", type=int, default=None, help="worker threads (default: all cores)")
    s.add_argument("--trajectory", help="also write the platform trajectory as CSV")
    s.add_argument("--summary", help="summary JSON path (default: OUTPUT.summary.json)")
    s.add_argument("--force", action="store_true", help="rescan even if the output is up to date")
    s.add_argument("--progress", action="store_true", help="show progress even when stderr is not a terminal")
    s.set_defaults(func=cmd_scan)

    c = sub.add_parser("import-cityjson", help="convert a CityJSON city model into a scene bundle")
    c.add_argument("input", help="CityJSON file (1.0, 1.1, 2.0)")
    c.add_argument("-o", "--output", required=True, help="scene bundle folder to write")
    c.add_argument("--lod", default=None, help="level of detail to use (default: the highest per building)")
    c.set_defaults(func=cmd_import_cityjson)

    v = sub.add_parser("validate", help="check a scene bundle and report the first problem")
    v.add_argument("scene")
    v.set_defaults(func=cmd_validate)

    t = sub.add_parser("survey-template", help="write a documented survey JSON file to edit")
    t.add_argument("-o", "--output", required=True)
    t.add_argument("--preset", default="paper")
    t.set_defaults(func=cmd_survey_template)
    return p


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
        return args.func(args)
    except QuakeScanError as e:
        print(f"quakescan: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("quakescan: interrupted; nothing partial was left under the output names", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
