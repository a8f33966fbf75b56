"""Commands on point clouds: per-point features, levels of detection, classify, evaluate."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


from ..errors import QuakeScanError
from ..runtime.atomic import write_json
from ..runtime.workers import EVERY_CORE
from .options import (PROGRESS_HELP, THREADS_HELP, add_dask_options, dask_client_for, check_cloud_output,
                      check_file_output, check_number, check_seed, check_threads, csv_list)
from .reporting import reporter


def cmd_features(args) -> int:
    """Features of every point as extra LAS dimensions (float32; CloudCompare shows them as
    scalar fields). NaN marks the degenerate neighbourhoods of quakescan.change.features."""
    from ..change.features import FEATURES, compute_features
    from ..formats.pointcloud import read_epoch, read_las, write_with_float_dims

    names = csv_list(args.features) or FEATURES
    src = Path(args.input)
    out = Path(args.output)
    check_cloud_output(out, src)
    check_number("--radius", args.radius, low=0.0, low_open=True)
    check_threads(args.threads)
    epoch = read_epoch(src)
    las = read_las(src)
    # checked before the features are computed: a clash would throw that work away
    clash = [n for n in names if n in set(las.point_format.dimension_names)]
    if clash:
        raise QuakeScanError(f"{src}: already has dimensions {clash}; write features of another file or radius")
    t0 = time.perf_counter()
    try:
        feats = compute_features(epoch.xyz, args.radius, names, workers=args.threads,
                                 progress=reporter(args, f"features {src.name}"))
    except QuakeScanError as e:  # e.g. a cloud too wide for the grid: say which file
        raise QuakeScanError(f"{src}: {e}") from None
    dt = time.perf_counter() - t0
    write_with_float_dims(las, out, {n: feats[n] for n in names}, {n: f"{n} r={args.radius:g} m" for n in names})
    print(f"features: {len(names)} features of {len(epoch):,} points at r = {args.radius:g} m in {dt:.1f} s "
          f"({len(epoch) / max(dt, 1e-9) / 1e3:,.0f} k points/s) -> {out}")
    return 0


def _first_and_second(args) -> tuple:
    """The two clouds of `calibrate-lod`: --pre FIRST --post SECOND."""
    if not (args.pre and args.post):
        raise QuakeScanError("calibrate-lod: give both clouds: --pre FIRST --post SECOND")
    return args.pre, args.post


def cmd_calibrate_lod(args) -> int:
    """Levels of detection of the split from two acquisitions of the same undamaged buildings."""
    from ..change.lod import calibrate
    from ..formats.pair import load_pair

    check_number("--radius", args.radius, low=0.0, low_open=True)
    check_number("--quantile", args.quantile, 0.5, 1.0, low_open=True, high_open=True)
    check_seed(args.seed)
    check_threads(args.threads)
    first_path, second_path = _first_and_second(args)
    if args.output:
        check_file_output(Path(args.output), [first_path, second_path, args.footprints])
    # classify's reading and checks (same CRS, overlapping extents, footprints in the clouds'
    # CRS); building points from footprints for real clouds, as classify assigns them
    pair = load_pair(first_path, second_path, args.footprints, args.id_field)
    first, second = pair.pre, pair.post
    lod = calibrate(first, second, radius_m=args.radius, quantile=args.quantile, seed=args.seed,
                    workers=args.threads, progress=reporter(args, "calibrate-lod"))
    print(f"calibrate-lod: {lod.points:,} building points; at the {100 * args.quantile:g}th percentile "
          f"|Δheight| {lod.height_at_quantile_m:.3f} m, |Δcurvature| {lod.curvature_at_quantile:.3f} 1/m")
    print(f"levels of detection: --lod-height {lod.lod_height_m:.3f} --lod-curvature {lod.lod_curvature:.3f}")
    if args.output:
        from ..runtime.atomic import write_text

        out = Path(args.output)
        write_text(out, json.dumps(lod.to_json(), indent=1))
        print(f"-> {out}")
    return 0


def cmd_classify(args) -> int:
    from ..assessment.run import classify

    check_threads(args.threads)
    if args.workers is not None or args.scheduler:
        summary = _classify_on_dask(args)
    else:
        summary = classify(args.pre, args.post, args.output, model_path=args.model, footprints_path=args.footprints,
                           id_field=args.id_field, align=args.align, workers=args.threads,
                           progress=reporter(args, "classify"),
                           write_las=not args.no_las, laz=args.laz, force=args.force,
                           unseen_damage=not args.assume_damage_visible, prior=args.prior, csv_raw=args.csv_raw)
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
    unresolved = summary.get("detectability", {}).get("no_damage_heavy_unresolved", 0)
    if unresolved:
        print(f"classify: {unresolved} of the buildings graded 'no damage' could not have shown heavy damage "
              "(too sparse for its smallest roof openings): hatched on the maps, `detectable_grade` in the results")
    blind_walls = summary.get("detectability", {}).get("no_damage_walls_unresolved", 0)
    if blind_walls:
        print(f"classify: {blind_walls} of the buildings graded 'no damage' have walls too sparsely sampled to show "
              "heavy damage confined to them (holes, break-outs): `walls_resolved` 0 in the results, and their "
              "probabilities count it (--assume-damage-visible: the model's own)")
    print(f"results -> {out / 'buildings.csv'}, {out / 'buildings.geojson'} (QGIS style buildings.qml), "
          f"{out / 'damage_map.png'}, {out / 'damage_map.html'} (opens offline)"
          + (f", {summary['post_grades']}" if "post_grades" in summary else ""))
    return 0


def _classify_on_dask(args) -> dict:
    """classify with its tiles as Dask tasks: a LocalCluster of --workers processes, or the
    cluster of --scheduler; the dashboard's address printed before the work starts."""
    from ..distributed.engine import classify_distributed

    with dask_client_for(args, args.memory_limit) as client:
        return classify_distributed(args.pre, args.post, args.output, client, model_path=args.model,
                                    footprints_path=args.footprints, id_field=args.id_field, align=args.align,
                                    progress=reporter(args, "classify"), write_las=not args.no_las, laz=args.laz,
                                    force=args.force, unseen_damage=not args.assume_damage_visible,
                                    prior=args.prior, csv_raw=args.csv_raw,
                                    on_stage=lambda name: print(f"classify: {name}", flush=True)
                                    if args.progress else None)


def cmd_evaluate(args) -> int:
    from ..results.evaluation import evaluate_files, plot_confusion

    out = Path(args.output) if args.output else Path(args.result).parent
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"{out}: -o is an existing file; evaluate writes a folder (confusion.png, "
                             "evaluation.json)")
    from ..runtime.output_folder import refuse_replacing_inputs

    refuse_replacing_inputs([out / "confusion.png", out / "evaluation.json"],
                            [(args.result, "result CSV"), (args.truth, "truth")], command="evaluate")
    ev = evaluate_files(args.result, args.truth)
    print(f"evaluate: {ev.n} assessable buildings, overall accuracy {100 * ev.overall_accuracy:.1f} %"
          + (f", {ev.not_assessable} not assessable" if ev.not_assessable else "")
          + (f", {len(ev.missing)} in the truth but not in the result" if ev.missing else ""))
    print(ev.table())
    plot_confusion(ev, out / "confusion.png")
    write_json(out / "evaluation.json", ev.to_json())
    print(f"confusion matrix -> {out / 'confusion.png'}, metrics -> {out / 'evaluation.json'}")
    return 0


def add_features(sub) -> None:
    f = sub.add_parser("features", help="per-point geometric features as extra LAS dimensions")
    f.add_argument("input", help="LAS/LAZ point cloud")
    f.add_argument("-o", "--output", required=True, help="output LAS/LAZ with one extra dimension per feature")
    f.add_argument("--radius", type=float, required=True, help="spherical neighbourhood radius in m")
    f.add_argument("--features", help="comma-separated names (default: all 24)")
    f.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    f.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    f.set_defaults(func=cmd_features)


def add_calibrate_lod(sub) -> None:
    lc = sub.add_parser("calibrate-lod", help="levels of detection of the changed/unchanged split, measured on "
                        "two acquisitions of the same undamaged buildings (use them with train --lod-*)")
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


def _prior(text: str) -> dict:
    from ..learning.unseen_damage import PriorError, parse_prior

    try:
        return parse_prior(text)
    except PriorError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_classify(sub) -> None:
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
    cl.add_argument("--csv-raw", action="store_true",
                    help="write footprint IDs into buildings.csv as they are, for programs that read it; by default "
                    "an ID that begins with = + - @, a tab or CR gets a leading ' so that a spreadsheet shows it "
                    "instead of running it as a formula")
    cl.add_argument("--assume-damage-visible", action="store_true",
                    help="report the model's own probabilities, which assume any damage shows in the data; by default "
                    "they count the damage each building's data could not have shown (wall holes under an airborne "
                    "laser, roof openings below its resolution), so 'no damage' is not said with more confidence "
                    "than the data allow")
    cl.add_argument("--prior", type=_prior, default=None, metavar="0:70,3:10,4:10,5:10",
                    help="the mix of grades you expect (shares of any scale, one for each grade of the model), for "
                    "the equal one the model's probabilities carry; the grades stay the model's, the probabilities "
                    "are reweighted (default: equal)")
    cl.add_argument("--force", action="store_true", help="recompute even when OUT_DIR holds the finished results "
                    "of the same inputs, model and options")
    cl.add_argument("--laz", action="store_const", const=True, default=None,
                    help="compress the per-point grades (post_grades.laz); default: as the post-event file is")
    cl.add_argument("--threads", type=int, default=EVERY_CORE, help=THREADS_HELP)
    add_dask_options(cl, "describe the tiles as Dask tasks on a LocalCluster of N single-threaded worker processes "
                     "(the same results as without; the inputs are streamed to OUT_DIR/.blocks, never loaded whole)",
                     "the same on an existing Dask cluster (tcp://host:8786; its workers must reach OUT_DIR)")
    cl.add_argument("--memory-limit", default="auto",
                    help="memory per LocalCluster worker (e.g. 4GB; default: the machine's memory shared out)")
    cl.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    cl.add_argument("-o", "--output", required=True, help="output folder")
    cl.set_defaults(func=cmd_classify)


def add_evaluate(sub) -> None:
    ev = sub.add_parser("evaluate", help="accuracy of a classification against the truth")
    ev.add_argument("result", help="buildings.csv written by classify")
    ev.add_argument("--truth", required=True, help="CSV building_id,grade or a post-event scene bundle folder")
    ev.add_argument("-o", "--output", help="folder for confusion.png and evaluation.json (default: the result's)")
    ev.set_defaults(func=cmd_evaluate)
