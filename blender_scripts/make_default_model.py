#!/usr/bin/env python3
"""Rebuild the model that QuakeScan ships (core/data/default_model.skops), reproducibly.

    .venv/bin/python blender_scripts/make_default_model.py [--work out/default_model] [--seed 1]

The paper's "VLS generic" classifier: the generic simulated dataset of 112 buildings
(blender_scripts/generate_scenes.py --set generic --dataset paper: every building heavy,
extreme and destroyed in three post-event scenes), scanned with the paper's survey; the
undamaged class from the pre-event scene scanned a second time with new range noise.
Four training pairs: (pre, pre rescanned) grade 0, (pre, post_heavy) 3, (pre, post_extreme)
4, (pre, post_destruction) 5. Random forest with the paper's settings (100 trees, depth 5),
fitted on the buildings with changed points (the others are "no damage" by rule) with
balanced class weights (core.model.train_damage_forest), on the pipeline's default descriptors (the paper's robust features at r = 1.5 m), 70/30
split grouped by building; the held-out scores go into the model's provenance. Each step
skips outputs that exist, so an interrupted run continues. Same seed, same model.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from core.classify import DEFAULT_MODEL  # noqa: E402
from core.demo import generate, scan_scene  # noqa: E402
from core.model import save_model  # noqa: E402
from core.pipeline import PipelineSettings  # noqa: E402
from core.training import TrainingPair, train  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(REPO / "out" / "default_model"), help="working folder for scenes and scans")
    p.add_argument("--buildings", type=int, default=112)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("-o", "--output", default=str(DEFAULT_MODEL))
    a = p.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    print(f"1/3 generating the generic dataset ({a.buildings} buildings, seed {a.seed})", flush=True)
    generate("generic", "paper", a.buildings, a.seed, work / "generic")
    print("2/3 scanning pre (twice), post_heavy, post_extreme, post_destruction", flush=True)
    scans = {"pre": ("pre", 1), "pre_rescan": ("pre", 2), "post_heavy": ("post_heavy", 3),
             "post_extreme": ("post_extreme", 4), "post_destruction": ("post_destruction", 5)}
    for name, (scene, k) in scans.items():
        scan_scene(work / "generic" / scene, work / f"{name}.las", seed=a.seed * 10 + k)
    print("3/3 training", flush=True)
    pre = str(work / "pre.las")
    pairs = [TrainingPair(pre, str(work / f"{n}.las")) for n in ("pre_rescan", "post_heavy", "post_extreme",
                                                                  "post_destruction")]
    model, ev, table = train(pairs, PipelineSettings(), seed=a.seed,
                             command="python blender_scripts/make_default_model.py " + " ".join(argv or sys.argv[1:]))
    model.provenance["dataset"] = (f"generic simulated ULS, {a.buildings} buildings, generator seed {a.seed}, "
                                   "paper survey; pairs pre/pre-rescan (0), heavy (3), extreme (4), destruction (5)")
    if ev is not None:
        model.provenance["test_table"] = ev.table()
    out = Path(a.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_model(model, out)
    print(f"{len(table.y)} building rows; held-out overall accuracy "
          f"{100 * ev.overall_accuracy:.1f} % on {ev.n} buildings" if ev else "")
    if ev is not None:
        print(ev.table())
    print(f"model -> {out} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
