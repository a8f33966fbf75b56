#!/usr/bin/env python3
"""Rebuild the model that QuakeScan ships (core/data/default_model.skops), reproducibly.

    .venv/bin/python blender_scripts/make_default_model.py [--work out/default_model] [--seed 0] [--size large]
    .venv/bin/python blender_scripts/make_default_model.py --recalibrate MODEL [--work …] -o OUT   # its temperature only

One command from nothing (`quakescan.learning.default_model`): the transfer training set
(`quakescan.learning.trainset.default_plan`: generic, region-specific and Rotterdam cities, mixed and
paper-design post-event scenes, every ULS/ALS/DIM acquisition randomised, cross-source
pairs), the density-invariant surface descriptors, random forest against gradient
boosting with and without calibrated probabilities compared by cross-validation that holds
out whole cities, the winner fitted on every row, the data limits it was trained on, and
the provenance (plan, comparison table, choice, command, date) written into the file.
Every step skips outputs that exist, so an interrupted run continues. Same seed, same model.
"""
from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from quakescan.learning.default_model import DEFAULT_MODEL  # noqa: E402
from quakescan.learning.default_model import make_default_model, recalibrate_default_model  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(REPO / "out" / "default_model"), help="working folder (training set)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", choices=("full", "large", "quick"), default="large",
                   help="training set plan (default large, the shipped model's: the full plan and as many cities "
                   "again; full: `quakescan training-set`'s; both measured in docs/transfer.md)")
    p.add_argument("--scenes", choices=("clean", "realistic", "both"), default="both",
                   help="training scenes: the generator's bare ones, realistic ones (roof detail, trees, cars; "
                   "labels through footprints) or both (default: the shipped model's)")
    p.add_argument("--damage", choices=("patterns", "both"), default="both",
                   help="both (default, the shipped model's): the bare training set also holds physics twins of "
                   "four mixed cities (grade-4/5 buildings collapsed by rigid-body simulation; "
                   "quakescan.learning.trainset.PHYSICS_TWINS); patterns: the add-on's patterns only")
    p.add_argument("--small", action="store_true",
                   help="also the plan's two cities of small buildings (sheds, garages, row houses)")
    p.add_argument("--threads", type=int, default=-1, help="worker threads, or -1 for every core (default)")
    p.add_argument("--keep-clouds", action="store_true",
                   help="keep the training clouds (27 GB for the large plan; by default each is removed once "
                   "its pairs are described: the tables are what the model is made from)")
    p.add_argument("--real-data", default=str(REPO.parent / "shared" / "data"),
                   help="folder of the real archives whose points get injected damage for training "
                   "(quakescan.learning.realset; default ../shared/data; skipped where absent)")
    p.add_argument("--no-real", action="store_true", help="simulated training rows only")
    p.add_argument("--recalibrate", metavar="MODEL",
                   help="refit only the real-point temperature of MODEL (its estimator, and so every grade, kept) "
                   "on this recipe's tables under --work, and write it to --output")
    p.add_argument("-o", "--output", default=str(DEFAULT_MODEL))
    a = p.parse_args(argv)
    # the library logs its stage messages (training set, classifier comparison) to quakescan.stages
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("quakescan.stages").setLevel(logging.INFO)
    t0 = time.perf_counter()
    real_data = None if a.no_real or not Path(a.real_data).is_dir() else Path(a.real_data)
    if real_data is None and not a.no_real:
        print(f"warning: {a.real_data} is absent: the model is trained on simulated rows only", file=sys.stderr)
    command = "python blender_scripts/make_default_model.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    if a.recalibrate:
        rec = recalibrate_default_model(Path(a.recalibrate), Path(a.work), Path(a.output), seed=a.seed,
                                        note=command.strip(), size=a.size, scenes=a.scenes, damage=a.damage,
                                        small=a.small, workers=a.threads, keep_clouds=a.keep_clouds,
                                        real_data=real_data)
        print(f"temperature {rec['temperature']} -> {a.output}; {time.perf_counter() - t0:.0f} s")
        return 0
    model, scores, table = make_default_model(Path(a.work), Path(a.output), seed=a.seed, size=a.size,
                                              scenes=a.scenes, damage=a.damage, small=a.small, workers=a.threads,
                                              command=command.strip(), keep_clouds=a.keep_clouds,
                                              real_data=real_data)
    print(f"{len(table.y)} building rows; {model.provenance['classifier_selection']['chosen']}: cross-validated "
          f"overall accuracy {100 * model.provenance['test_overall_accuracy']:.1f} %; {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
