"""Commands that run the whole chain: demo, the paper's experiment, the robustness study."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime.output_folder import exclusive_run
from ..runtime.workers import EVERY_CORE
from .options import (PROGRESS_HELP, THREADS_HELP, add_dask_options, dask_client_for, check_folder_output, check_number,
                      check_seed, check_threads)
from .reporting import reporter


def cmd_demo(args) -> int:
    """The built-in default: generate a small city, scan both epochs, classify, evaluate, map."""
    from ..demo import run_demo

    r = run_demo(args.output, seed=args.seed, buildings=args.buildings,
                 progress=reporter(args, ""))  # its stages name themselves: "scan pre", ...
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


def _robustness_scenes(args) -> tuple:
    """Pre-event scene and post-event scene(s) of `robustness`: --pre PRE --post POST [POST2 ...]."""
    if not (args.pre and args.post):
        raise QuakeScanError("robustness: give the scenes: --pre PRE_SCENE --post POST_SCENE [POST2 …]")
    return args.pre, args.post


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
    check_folder_output(Path(args.output))
    kw = {"radii": radii} if radii else {}
    try:
        spacing = check_spacing(args.spacing)
    except QuakeScanError as e:
        raise QuakeScanError(f"--spacing {args.spacing}: {e}") from None
    check_seed(args.seed)
    check_threads(args.threads)
    check_number("--threshold", args.threshold, 0.0)
    sample = DEFAULT_SAMPLE if args.sample is None else (None if args.sample == 0 else args.sample)
    if sample is not None and sample < 0:
        raise QuakeScanError(f"--sample: expected a number of points >= 0 (0 = all), got {args.sample}")
    pre, posts = _robustness_scenes(args)
    post = posts[0] if len(posts) == 1 else posts
    with exclusive_run(args.output, "robustness", QuakeScanError):  # one study in the folder at a time
        res = run_experiment(pre, post, args.output, seed=args.seed, workers=args.threads,
                             progress=reporter(args, "robustness"),
                             threshold_pct=args.threshold, spacing=spacing, sample=sample, **kw)
    stages = f" over {len(res.stages)} stages" if len(res.stages) > 1 else ""
    print(f"robustness: best radius {res.best_radius:g} m, {len(res.robust)} robust features at "
          f"<= {args.threshold:g} %{stages}: {', '.join(res.robust)}")
    print(f"report -> {Path(args.output) / 'README.md'}")
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
    check_folder_output(Path(args.output))
    check_number("--trees", args.trees, 1, integer=True)
    check_seed(args.seed)
    check_threads(args.threads)
    check_number("--lod-height", args.lod_height, *LOD_HEIGHT_RANGE_M, low_open=True)
    check_number("--lod-curvature", args.lod_curvature, *LOD_CURVATURE_RANGE, low_open=True)
    settings = ExperimentSettings(buildings=args.buildings, test_mix=mix, seed=args.seed, n_estimators=args.trees,
                                  lod_height_m=args.lod_height, lod_curvature=args.lod_curvature,
                                  training=args.training)
    with exclusive_run(args.output, "experiment", QuakeScanError):  # one experiment in the folder at a time
        if args.workers is not None or args.scheduler:
            with dask_client_for(args) as client:
                results = run_paper_experiment(args.output, settings, progress=reporter(args, "experiment"),
                                               client=client)
        else:
            results = run_paper_experiment(args.output, settings, workers=args.threads,
                                           progress=reporter(args, "experiment"))
    for name, ev in results.items():
        print(f"{name}: overall accuracy {100 * ev.overall_accuracy:.1f} %, damaged vs undamaged F1 "
              f"{metric_text(ev.damaged, 'f1')}")
    print(f"report -> {Path(args.output) / 'README.md'}")
    return 0


def add_demo(sub) -> None:
    d = sub.add_parser("demo", help="run the whole chain on a built-in default: generate a small city, "
                       "scan both epochs, classify with the shipped model, evaluate, draw the map")
    d.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--seed", type=int, default=0, help="seed of the city and of both scans (default 0)")
    d.add_argument("--buildings", type=int, default=30, help="buildings in the demo city (default 30)")
    d.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    d.set_defaults(func=cmd_demo)


def add_robustness(sub) -> None:
    rb = sub.add_parser("robustness", help="which change features agree between ULS and DIM clouds (paper's "
                        "robust-feature selection)")
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


def add_experiment(sub) -> None:
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
    add_dask_options(ex, "generate, acquire and describe as Dask tasks (a city, a cloud, a table per task) on a "
                     "LocalCluster of N single-threaded worker processes (the same numbers as without)",
                     "the same on an existing Dask cluster (tcp://host:8786; its workers must reach the output "
                     "folder and run the scene generator)")
    ex.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    ex.set_defaults(func=cmd_experiment)
