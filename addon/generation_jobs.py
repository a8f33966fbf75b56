"""The generator's job pool (`--jobs N`): a job's scenes, and with physics its collapses,
shared out among N processes of the generator script, each writing what it makes atomically,
so that N processes give the bytes one gives and an interrupted run resumes as one does.

No bpy at module level: the shares are planned before Blender's modules load; the collapses
a child simulates import them on use.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from .generation_spec import log


def _scene_cost(grades, damage: str, buildings: int = 1) -> int:
    """A scene costs one unit, and with physics 50 more per grade-4/5 building (a collapse
    takes seconds, a pattern milliseconds). `grades`: a dict (building -> grade, mixed
    datasets) or one grade for all `buildings` (paper scenes)."""
    if damage == "patterns" or grades is None:
        return 1
    heavy = (sum(1 for g in grades.values() if g >= 4) if isinstance(grades, dict)
             else buildings * (int(grades) >= 4))
    return 1 + heavy * 50


def job_shares(todo, jobs: int, damage: str, buildings: int = 1) -> list:
    """Scene names split into at most `jobs` shares of about equal cost (_scene_cost).
    Largest first onto the cheapest share; deterministic."""
    def cost(grades):
        return _scene_cost(grades, damage, buildings)
    shares = [[0, []] for _ in range(min(jobs, len(todo)))]
    for name, grades, _ in sorted(todo, key=lambda t: -cost(t[1])):
        low = min(shares, key=lambda s: s[0])
        low[0] += cost(grades)
        low[1].append(name)
    return [names for _, names in shares if names]


@contextlib.contextmanager
def _child_spec(spec):
    """The job as a --jobs child reads it (one process: its share alone), in a file of its own
    for the children's lifetime."""
    fd, name = tempfile.mkstemp(prefix="quakescan-generate-", suffix=".json")
    os.close(fd)
    try:
        replace(spec, jobs=1).write(name)
        yield name
    finally:
        with contextlib.suppress(OSError):
            os.unlink(name)


def _child_command(script: Path, argv: list) -> list:
    """The generator `script` again with `argv`: in Blender's binary when it runs there, else
    with the Python that has the bpy module."""
    import bpy
    binary = bpy.app.binary_path
    if binary and "python" not in Path(binary).name.lower():
        return [binary, "-b", "--factory-startup", "--python-exit-code", "1", "-P", str(script), "--", *argv]
    return [sys.executable, str(script), *argv]


def run_jobs(spec, todo, buildings: int, script: Path) -> int:
    """Make `todo`'s scenes in spec.jobs child processes at once, each its share; every child
    writes its bundles atomically, so an interrupted run resumes as a single process does."""
    shares = job_shares(todo, spec.jobs, spec.damage, buildings)
    log(f"{len(todo)} scenes in {len(shares)} processes: " + "; ".join(",".join(s) for s in shares))
    with _child_spec(spec) as child:
        procs = [subprocess.Popen(_child_command(script, ["--spec", child, "--only-scenes", ",".join(s)]))
                 for s in shares]
        codes = [p.wait() for p in procs]
    failed = [",".join(s) for s, c in zip(shares, codes) if c]
    if failed:
        log(f"error: the process making {'; '.join(failed)} failed (see above); finished scenes are kept")
        return 1
    return 0


def parts_folder(out: Path, scene: str) -> Path:
    """Where --jobs children leave a scene's collapses until the scene is written."""
    return out / f".{scene}.collapses"


def collapse_scenes(spec, todo) -> list:
    """The scenes of `todo` with buildings that may collapse by physics, costliest first (a
    grade-5 collapse takes about three times a grade-4 one: every storey falls)."""
    if spec.damage == "patterns":
        return []

    def cost(grades):
        gs = list(grades.values()) if isinstance(grades, dict) else [int(grades)]
        return sum(3 if g >= 5 else 1 if g == 4 else 0 for g in gs) / len(gs)
    heavy = [t for t in todo if t[1] is not None and cost(t[1]) > 0]
    return sorted(heavy, key=lambda t: -cost(t[1]))


def simulate_collapses(spec, scenes, pre_objs, out: Path, claims: Path, street=None):
    """A --jobs child's share of the collapses: every child walks the same list (scenes
    costliest first, buildings in order) and simulates those it claims first (a file created
    exclusively in `claims`), so the processes stay busy until the last collapse; each is
    written to its scene's parts folder (collapse_parts), those already there are skipped."""
    from . import collapse_parts, post_scene
    from .scene_tools import DamageError

    if street is not None:
        from .street_objects import is_car_object
        pre_objs = [o for o in pre_objs if not is_car_object(o)]
    done = 0
    for name, grades, info in scenes:
        colliders = post_scene.PhysicsColliders(pre_objs, grades, spec.damage)
        folder = parts_folder(out, name)
        for src in colliders.sources:
            pg = src.qs_building
            if not colliders.collapses(src):
                continue
            if collapse_parts.is_done(folder, info, pg.building_id):
                continue
            try:
                os.close(os.open(claims / f"{name}-{pg.building_id}", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                continue  # another process has it
            t0 = time.perf_counter()
            try:
                obj, rec = post_scene.collapse_copy(src, colliders, settle_steps=spec.settle_steps)
            except DamageError as e:
                collapse_parts.save(folder, info, pg.building_id, error=str(e))
                log(f"{name}: building {pg.building_id} did not come to rest ({time.perf_counter() - t0:.1f} s)")
            else:
                try:
                    collapse_parts.save(folder, info, pg.building_id, obj, rec)
                finally:
                    post_scene.remove_object(obj)
                log(f"{name}: building {pg.building_id} collapsed in {time.perf_counter() - t0:.1f} s")
            done += 1
    log(f"{done} collapses simulated")


def run_collapse_jobs(spec, out: Path, script: Path) -> int:
    """Simulate the collapses of the scenes to make in spec.jobs child processes at once
    (simulate_collapses); the scenes are written afterwards from their parts."""
    claims = out / f".collapse-claims-{os.getpid()}"
    shutil.rmtree(claims, ignore_errors=True)
    claims.mkdir(parents=True)
    try:
        log(f"collapses in {spec.jobs} processes")
        with _child_spec(spec) as child:
            procs = [subprocess.Popen(_child_command(script, ["--spec", child, "--collapse-claims", str(claims)]))
                     for _ in range(spec.jobs)]
            codes = [p.wait() for p in procs]
    finally:
        shutil.rmtree(claims, ignore_errors=True)
    if any(codes):
        log("error: a process simulating collapses failed (see above); finished collapses are kept")
        return 1
    return 0

