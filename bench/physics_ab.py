"""Variants of the collapse by physics side by side, interleaved on the same buildings.

    .venv/bin/python bench/physics_ab.py --buildings 16 \\
        --variants '{"base": {}, "early": {"EARLY_STOP_SHARE": 0.02}}' [--out rows.json]

Builds bench_physics.py's city (generic, `--buildings`, `--seed`) and collapses each of its
buildings as grade 4 and grade 5 (the paper scenes' grades, neighbours as colliders as the
generator gives them) once per variant: a variant sets constants of addon/physics.py (the
first is the reference). The variants take turns on each building, their order alternating,
so that a machine shared with other work slows them alike: compare the CPU ratios, not the
seconds. Per grade: CPU and wall time, collapses that did not settle (→ patterns), frames,
creeping and dropped shards, and bench_physics.py's standing and debris / catalogue measures
on the buildings every variant made by physics, with the mean per-building difference to the
reference. Not a BENCHMARKS.md section: a tool for choosing the constants.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_physics import building_measures  # noqa: E402


def _world_arrays(physics, scene_tools, gm, obj):
    bm = scene_tools.read_bmesh(obj)
    try:
        v, t, s, _, _ = gm.arrays(bm)
    finally:
        bm.free()
    M = physics.world_matrix(obj)
    return v @ M[:3, :3].T + M[:3, 3], t, s


def measure(physics, scene_tools, gm, src, obj):
    """bench_physics.measure for one building: (share standing, debris, expected debris)."""
    pv, pt, _ = _world_arrays(physics, scene_tools, gm, src)
    qv, qt, qs = _world_arrays(physics, scene_tools, gm, obj)
    return building_measures(pv, pt, qv, qt[qs != 3], qt[qs == 3], src.qs_building.material)


def collapse_all(args, variants) -> list:
    import bpy

    import addon
    from addon import citygen, physics, scene_tools
    from addon.geometry import mesh as gm
    from addon.geometry.shell import ShellSpec

    if not hasattr(bpy.types.Object, "qs_building"):
        addon.register()
    plan = citygen.city_plan("generic", args.buildings, args.seed)
    scene = bpy.data.scenes.new("physics_ab")
    pre = bpy.data.collections.new("pre")
    scene.collection.children.link(pre)
    scene_tools.create_terrain_object(pre, *plan.bounds)
    for b in plan.buildings:
        scene_tools.create_building_object(pre, ShellSpec(**b.shell), b.id, location=(b.location[0], b.location[1], 0.0),
                                           rotation_z=b.rotation, vulnerability_class=b.vulnerability_class,
                                           seed=b.seed)
    pre_objs = scene_tools.scene_objects(pre)
    defaults = {c: getattr(physics, c) for v in variants.values() for c in v}
    names = list(variants)
    rows, turn = [], 0
    for g in args.grades:
        colliders = scene_tools.PhysicsColliders(pre_objs, g, "physics")
        for src in colliders.sources:
            if not colliders.collapses(src):
                continue
            for name in (names if turn % 2 == 0 else names[::-1]):
                for c, value in {**defaults, **variants[name]}.items():
                    setattr(physics, c, value)
                row = {"variant": name, "grade": g, "building": src.qs_building.building_id}
                t0, c0 = time.perf_counter(), time.process_time()
                try:
                    obj, rec = scene_tools.collapse_copy(src, colliders)
                except scene_tools.DamageError as e:
                    row.update(wall=time.perf_counter() - t0, cpu=time.process_time() - c0, fallback=True,
                               error=str(e))
                else:
                    row.update(wall=time.perf_counter() - t0, cpu=time.process_time() - c0, fallback=False)
                    p = rec["params"]
                    row.update({k: p[k] for k in ("frames", "shards", "settled", "creeping_shards",
                                                  "unsettled_shards_dropped", "unsettled_volume_share")})
                    row["standing"], row["debris"], row["expected"] = measure(physics, scene_tools, gm, src, obj)
                    scene_tools.remove_object(obj)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
            turn += 1
    for c, value in defaults.items():
        setattr(physics, c, value)
    return rows


def _ratio(r):
    return r["debris"] / r["expected"] if r["expected"] > 1.0 else np.nan


def summary(rows) -> str:
    names = list(dict.fromkeys(r["variant"] for r in rows))
    ref = names[0]
    by = {(r["variant"], r["grade"], r["building"]): r for r in rows}
    cpu_all = {n: sum(r["cpu"] for r in rows if r["variant"] == n) for n in names}
    lines = [f"all collapses: CPU s (ratio to {ref}): "
             + ", ".join(f"{n} {cpu_all[n]:.1f} ({cpu_all[n] / cpu_all[ref]:.3f})" for n in names)]
    for g in sorted({r["grade"] for r in rows}):
        ids = sorted({r["building"] for r in rows if r["grade"] == g})
        common = [b for b in ids if all(not by[(n, g, b)]["fallback"] for n in names)]
        lines.append(f"grade {g}: {len(ids)} collapses; measures over the {len(common)} every variant made by physics")
        cpu_ref = sum(by[(ref, g, b)]["cpu"] for b in ids)
        for n in names:
            rs = [by[(n, g, b)] for b in ids]
            cs = [by[(n, g, b)] for b in common]
            cpu = sum(r["cpu"] for r in rs)
            st = np.array([r["standing"] for r in cs])
            rat = np.array([_ratio(r) for r in cs])
            d_st = np.abs(st - np.array([by[(ref, g, b)]["standing"] for b in common]))
            d_rat = np.abs(rat - np.array([_ratio(by[(ref, g, b)]) for b in common]))
            lines.append(
                f"  {n}: CPU {cpu:.1f} s ({cpu / cpu_ref:.3f}), wall {sum(r['wall'] for r in rs):.1f} s, "
                f"did not settle (→ patterns) {sum(r['fallback'] for r in rs)}, frames (mean) "
                f"{np.mean([r['frames'] for r in rs if not r['fallback']]):.0f}; standing {st.mean():.3f} "
                f"(|d| {d_st.mean():.3f}), debris / catalogue median {np.nanmedian(rat):.2f} "
                f"(|d| {np.nanmean(d_rat):.3f}), creeping {sum(r['creeping_shards'] for r in cs)}, dropped "
                f"{sum(r['unsettled_shards_dropped'] for r in cs)} "
                f"({100 * np.mean([r['unsettled_volume_share'] for r in cs]):.2f} % of the volume, mean)")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--buildings", type=int, default=16)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--grades", default="4,5", help="comma-separated, of 4 and 5")
    ap.add_argument("--variants", required=True,
                    help='JSON: {"name": {"CONSTANT": value, ...}, ...}; the first is the reference')
    ap.add_argument("--out", default=None, help="also write the rows (JSON) here")
    args = ap.parse_args(argv)
    args.grades = [int(g) for g in args.grades.split(",")]
    rows = collapse_all(args, json.loads(args.variants))
    if args.out:
        Path(args.out).write_text(json.dumps(rows))
    print(summary(rows))


if __name__ == "__main__":
    main()
