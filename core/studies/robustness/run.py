"""The robustness experiment from scene bundles: acquire every epoch with ULS and DIM (kept
when current), read them in one frame, select the robust features, write the report."""
from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path

from ...runtime.progress import ProgressCallback
from .report import write_report
from .selection import (DEFAULT_SAMPLE, RADII, THRESHOLD_PCT, RobustnessError, RobustnessResult, check_spacing,
                        robustness)

log = logging.getLogger(__name__)

def run_experiment(pre_scene_dir: str | os.PathLike, post_scene_dir, out_dir: str | os.PathLike,
                   radii: Sequence[float] = RADII, seed: int = 0,
                   workers: int = -1, progress: ProgressCallback | None = None, survey=None, photo_survey=None,
                   threshold_pct: float = THRESHOLD_PCT, sample: int | None = DEFAULT_SAMPLE,
                   spacing: float | None = None) -> RobustnessResult:
    """Scan the scenes with ULS (`survey`, default the paper preset) and DIM (`photo_survey`,
    default the paper preset) into out_dir/clouds/ (`quakescan.acquisition.acquire.acquire`: a
    cloud made from the same scene, survey and seed is kept, one of another run is made again),
    read them all in the pre ULS cloud's frame, run `robustness` and write the report to
    out_dir. `post_scene_dir` is one post-event scene folder (clouds {uls,dim}_post.las) or a sequence of them, the demolition stages in order
    (clouds {uls,dim}_post1.las, _post2.las, ...; stage k is scanned with seed + k).
    `spacing` thins every cloud before the features (module doc). `progress(done, total)`
    over the clouds and then the radii."""
    from ...acquisition import sensors
    from ...acquisition.acquire import Acquisition, acquire
    from ...formats.pointcloud import read_epoch

    started = time.perf_counter()
    spacing = check_spacing(spacing)
    survey = survey or sensors.get("uls").default()
    photo_survey = photo_survey or sensors.get("dim").default()
    settings = {"uls": survey, "dim": photo_survey}
    if isinstance(post_scene_dir, (str, os.PathLike)):
        post_dirs = [Path(post_scene_dir)]
    else:
        post_dirs = [Path(p) for p in post_scene_dir]
    if not post_dirs:
        raise RobustnessError("no post-event scene given")
    stages = ["post"] if len(post_dirs) == 1 else [f"post{i + 1}" for i in range(len(post_dirs))]
    out = Path(out_dir)
    clouds = out / "clouds"
    clouds.mkdir(parents=True, exist_ok=True)
    scenes = {"pre": Path(pre_scene_dir), **dict(zip(stages, post_dirs))}
    seeds = {"pre": seed, **{st: seed + 1 + i for i, st in enumerate(stages)}}  # different noise per epoch
    paths = {}
    n_clouds = 2 * len(scenes)
    total_steps = n_clouds + 2 * len(set(radii))
    step = 0
    for src in ("uls", "dim"):
        for ep, folder in scenes.items():
            path = clouds / f"{src}_{ep}.las"
            paths[(src, ep)] = path
            t0 = time.perf_counter()
            # reused only when made from the same scene, settings and seed: a folder of another
            # run's clouds is acquired again, never mixed into this one
            got = acquire(folder, Acquisition(src, settings[src]), path, seed=seeds[ep], workers=workers)
            if got.resumed:
                log.info("robustness: keeping %s", path)
            else:
                log.info("robustness: %s %s cloud in %.1f s", src, ep, time.perf_counter() - t0)
            step += 1
            if progress:
                progress(step, total_steps)
    uls_pre = read_epoch(paths[("uls", "pre")])
    origin = uls_pre.origin
    ep = {k: read_epoch(p, origin=origin) for k, p in paths.items() if k != ("uls", "pre")}

    def inner(done, total):
        if progress:
            progress(n_clouds + done, total_steps)

    res = robustness(uls_pre, [ep[("uls", st)] for st in stages], ep[("dim", "pre")],
                     [ep[("dim", st)] for st in stages], radii=radii, threshold_pct=threshold_pct,
                     workers=workers, progress=inner, sample=sample, seed=seed, spacing=spacing,
                     stage_names=stages)
    res.wall_time_s = time.perf_counter() - started
    counts = {f"{s}_{e}": len(x) for (s, e), x in [(("uls", "pre"), uls_pre)] + list(ep.items())}
    post_txt = ", ".join(f"{st} `{scenes[st]}`" for st in stages)
    context = (f"Scenes: pre `{scenes['pre']}`, {post_txt}; ULS survey '{survey.name}' "
               f"(pulse rate {survey.pulse_rate_hz:g} Hz), DIM photo survey '{photo_survey.name}' "
               f"(point step {photo_survey.point_step_px:g} px); seed {seed}; sample {sample}; thinning "
               + ("none" if spacing is None else f"{spacing:g} m") + ". Cloud points (as simulated): "
               + ", ".join(f"{k} {v}" for k, v in counts.items()) + ".")
    write_report(res, out, context)
    return res
