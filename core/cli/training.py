"""Commands that make models: train (from labelled pairs) and training-set (the shipped model's data)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..errors import QuakeScanError
from ..runtime.output_folder import exclusive_run
from ..runtime.workers import EVERY_CORE
from .options import (PROGRESS_HELP, THREADS_HELP, add_dask_options, dask_client_for, check_file_output,
                      check_folder_output, check_number, check_seed, check_threads, csv_list)
from .reporting import reporter


def _training_pairs(args) -> list:
    """The pairs of `train`: --pre/--post (repeated, in order)."""
    pre, post = args.pre or [], args.post or []
    if len(pre) != len(post):
        raise QuakeScanError(f"train: {len(pre)} --pre and {len(post)} --post: give one --post per --pre")
    if not pre:
        raise QuakeScanError("train: no training pair; give --pre PRE --post POST (repeat both for more pairs)")
    return list(zip(pre, post))


def _check_split_flags(args) -> None:
    """The pipeline's flags in the ranges a model may hold (quakescan.change.pipeline,
    quakescan.change.split), named."""
    from ..change.settings import RADIUS_RANGE_M
    from ..change.split import LOD_CURVATURE_RANGE, LOD_HEIGHT_RANGE_M

    check_number("--radius", args.radius, *RADIUS_RANGE_M)
    check_number("--lod-height", args.lod_height, *LOD_HEIGHT_RANGE_M, low_open=True)
    check_number("--lod-curvature", args.lod_curvature, *LOD_CURVATURE_RANGE, low_open=True)
    check_number("--min-changed-share", args.min_changed_share, 0.0, 1.0, high_open=True)


def _pipeline_settings(args):
    from ..change.settings import training_settings
    from ..change.split import SplitSettings

    split = SplitSettings(lod_height_m=args.lod_height, lod_curvature=args.lod_curvature,
                          min_changed_share=args.min_changed_share, seed=args.seed)
    return training_settings(getattr(args, "descriptors", "paper"), radius_m=args.radius,
                             point_features=csv_list(args.features) or None, split=split,
                             per_point_lod=bool(getattr(args, "per_point_lod", False)))


def _pipeline_options(q) -> None:
    q.add_argument("--radius", type=float, default=1.5, help="feature radius in m (default 1.5)")
    q.add_argument("--features", help="point features whose change describes a building "
                   "(default: the paper's robust set)")
    q.add_argument("--lod-height", type=float, default=0.3, help="level of detection of height change, m "
                   "(default 0.3)")
    q.add_argument("--lod-curvature", type=float, default=0.2, help="level of detection of curvature change, 1/m "
                   "(default 0.2)")
    q.add_argument("--min-changed-share", type=float, default=0.003,
                   help="fewer changed points than this share of a building: unchanged (default 0.003)")


def cmd_train(args) -> int:
    from ..learning.model import save_model
    from ..learning.training import TrainingError, TrainingPair, train

    check_number("--trees", args.trees, 1, integer=True)
    check_number("--depth", args.depth, 1, integer=True)
    check_number("--test-size", args.test_size, 0.0, 1.0, high_open=True)
    check_seed(args.seed)
    check_threads(args.threads)
    _check_split_flags(args)
    given = _training_pairs(args)
    out = Path(args.output)
    check_file_output(out, [p for pair in given for p in pair] + list(args.truth or []) + [args.footprints])
    if args.truth and len(args.truth) != len(given):
        n = len(given)
        raise TrainingError(f"{len(args.truth)} --truth files for {n} pair{'s' * (n != 1)}: give one per pair "
                            "or none (then grades come from the post epochs' grade dimension)")
    pairs = [TrainingPair(pre, post, args.truth[k] if args.truth else None, args.footprints)
             for k, (pre, post) in enumerate(given)]
    settings = _pipeline_settings(args)
    model, ev, table = train(pairs, settings, n_estimators=args.trees, max_depth=args.depth,
                             test_size=args.test_size, seed=args.seed, workers=args.threads,
                             progress=reporter(args, "describe"),  # a stage per pair
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


def cmd_training_set(args) -> int:
    """The transfer training set: cities, random acquisitions, descriptor tables (resumable)."""
    from ..learning.default_model import TABLE_SETTINGS
    from ..learning.trainset import build, default_plan

    check_seed(args.seed)
    check_threads(args.threads)
    check_folder_output(Path(args.output))
    plan = default_plan(args.seed, args.size, args.scenes, args.damage, args.small)
    with exclusive_run(args.output, "training-set", QuakeScanError):  # one build in the folder at a time
        if args.workers is not None or args.scheduler:
            table = _training_set_on_dask(args, plan, TABLE_SETTINGS)
        else:
            table = build(args.output, plan, TABLE_SETTINGS, workers=args.threads,
                          progress=reporter(args, "training set"))
    counts = dict(zip(*(v.tolist() for v in np.unique(table.y, return_counts=True))))
    print(f"{args.output}: {len(table.y)} building rows, grades {counts}; manifest.json and tables/")
    return 0


def _training_set_on_dask(args, plan, settings):
    """The training set's cities and pairs as Dask tasks: a LocalCluster of --workers processes
    or the cluster of --scheduler; the dashboard's address printed before the work starts."""
    from ..learning.trainset import build

    with dask_client_for(args) as client:
        return build(args.output, plan, settings, progress=reporter(args, "training set"), client=client)


def add_train(sub) -> None:
    tr = sub.add_parser("train", help="train a random forest from labelled pre/post pairs")
    tr.add_argument("--pre", action="append", help="pre-event point cloud of a pair (repeat --pre and --post "
                    "for more pairs, in the same order)")
    tr.add_argument("--post", action="append", help="post-event point cloud of a pair")
    tr.add_argument("--truth", action="append", help="CSV building_id,grade per pair (default: the post "
                    "epoch's grade dimension)")
    tr.add_argument("--footprints", help="GeoJSON footprints when the clouds have no building_id")
    _pipeline_options(tr)
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


def add_training_set(sub) -> None:
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
    add_dask_options(ts, "generate, acquire and describe as Dask tasks (one per city, one per pair) on a "
                     "LocalCluster of N single-threaded worker processes (the same tables as without)",
                     "the same on an existing Dask cluster (tcp://host:8786; its workers must reach the output "
                     "folder and run the scene generator)")
    ts.add_argument("--progress", action="store_true", help=PROGRESS_HELP)
    ts.set_defaults(func=cmd_training_set)
