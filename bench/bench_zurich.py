#!/usr/bin/env python3
"""Real building shapes the model never saw: the Zurich LoD2 model, damaged, scanned, classified.

    .venv/bin/python bench/bench_zurich.py [--work out/bench_zurich] [--model MODEL] [--no-write]

The Zurich city model in `../shared/data` (49 real LoD2 buildings of 4-31 m, 161 building parts,
EPSG:2056) is reserved for evaluation: no training set, no model selection and no setting of
QuakeScan reads it. This script is the one place that does, and it only measures the shipped
model. Its buildings are scattered over 9 x 10 km, so they are packed into a compact city
first: each building (with its parts) is moved as a whole on to a row of a grid with streets of
STREET_M between bounding boxes, its lowest vertex at z = 0 (the terrain is laid through their
bottoms by the CityJSON importer); nothing of a shape is changed. The add-on's generator then
damages the packed city with a mix in the paper's proportions (35/19/32/35 of 121, scaled to
49 buildings), once with its parametric patterns and once with grades 4-5 collapsed by
rigid-body simulation (`--damage physics`), and the paper's ULS and DIM presets acquire both
epochs; the airborne (ALS-like) preset acquires the pre-event epoch again for the cross-source
pairs a responder has (a national archive before, a drone after). The shipped model classifies each pair; overall accuracy, F1 per grade and damaged vs
undamaged F1 against the scene's grades.

This is the closest the project gets to the independent benchmark (real shapes, damage by
another procedure, QuakeScan's own sensors). Nothing here feeds back into training: a number
from this table is reported, never tuned to.

Writes the table to stdout, BENCHMARKS.md (section "zurich") and WORK/results.json.
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
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, peak_rss_mb, table, write_section  # noqa: E402
from bench_transfer import classify_and_evaluate  # noqa: E402

ZURICH = ROOT.parent / "shared" / "data" / "zurich_subset_lod2.json"
STREET_M = 14.0  # between the bounding boxes of neighbouring buildings: a street with pavements
SEEDS = (97_001, 97_002)  # generator seeds (no training city uses the 97 000s): other grades, other patterns
PAPER_MIX = {0: 35, 3: 19, 4: 32, 5: 35}
SENSOR_SEEDS = {"uls": 21, "dim": 22, "als": 23}
# what a responder has: a drone both times, or a national airborne archive before and a drone after
PAIRS = {"ULS pair": ("uls", "uls"), "DIM pair": ("dim", "dim"), "ALS-like pre + DIM post": ("als", "dim"),
         "ALS-like pre + ULS post": ("als", "uls")}


def scaled_mix(n: int, mix: dict = PAPER_MIX) -> dict:
    """`mix` scaled to `n` buildings, largest remainders first (sums to n)."""
    total = sum(mix.values())
    exact = {g: n * c / total for g, c in mix.items()}
    out = {g: int(v) for g, v in exact.items()}
    for g in sorted(exact, key=lambda g: (out[g] - exact[g], g))[:n - sum(out.values())]:
        out[g] += 1
    return out


def packed_cityjson(src: Path, dst: Path, street_m: float = STREET_M) -> int:
    """The CityJSON `src` with every building (and its parts) moved as a whole on to rows of a
    compact grid, `street_m` between bounding boxes, its lowest vertex at z = 0; written to
    `dst`. Returns the number of buildings."""
    doc = json.loads(src.read_text())
    scale = np.asarray(doc["transform"]["scale"], dtype=np.float64)
    verts = np.asarray(doc["vertices"], dtype=np.int64)
    objs = doc["CityObjects"]

    def root(k):
        while objs[k].get("parents"):
            k = objs[k]["parents"][0]
        return k

    def indices(geom):
        out = []

        def walk(x):
            if isinstance(x, list):
                for y in x:
                    walk(y)
            elif isinstance(x, int):
                out.append(x)
        walk(geom["boundaries"])
        return out

    groups: dict[str, list[str]] = {}
    for k in objs:
        groups.setdefault(root(k), []).append(k)
    roots = sorted(groups)
    used = {r: sorted({i for k in groups[r] for g in objs[k].get("geometry", []) for i in indices(g)}) for r in roots}
    roots = [r for r in roots if used[r]]
    boxes = {r: (verts[used[r]].min(axis=0), verts[used[r]].max(axis=0)) for r in roots}
    sizes = {r: (boxes[r][1][:2] - boxes[r][0][:2]) * scale[:2] for r in roots}
    row_width = 1.15 * np.sqrt(sum(float(np.prod(s + street_m)) for s in sizes.values()))
    new_verts, moved = [], {}
    x = y = row_depth = 0.0
    for r in roots:  # rows left to right, then the next row
        w, d = sizes[r]
        if x > 0 and x + w > row_width:
            x, y, row_depth = 0.0, y + row_depth + street_m, 0.0
        shift = np.round(np.array([x, y, 0.0]) / scale).astype(np.int64) - boxes[r][0]
        for i in used[r]:  # a vertex two buildings share is copied: each moves with its own
            moved[(r, i)] = len(new_verts)
            new_verts.append((verts[i] + shift).tolist())
        x += w + street_m
        row_depth = max(row_depth, d)
    for r in roots:
        for k in groups[r]:
            for g in objs[k].get("geometry", []):
                g["boundaries"] = _renumber(g["boundaries"], lambda i, r=r: moved[(r, i)])
            objs[k].pop("geographicalExtent", None)
    doc["vertices"] = new_verts
    doc["transform"]["translate"] = [0.0, 0.0, 0.0]
    doc["CityObjects"] = {k: objs[k] for r in roots for k in groups[r]}
    doc.pop("metadata", None)  # its extent is the scattered one
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(doc))
    return len(roots)


def confusion_metrics(conf) -> dict:
    """Overall accuracy, F1 of each grade (0, 3, 4, 5) and damaged vs undamaged F1 of a
    confusion matrix (rows truth, columns prediction, over grades 0, 3, 4, 5)."""
    c = np.asarray(conf, dtype=np.float64)
    n = c.sum()

    def f1(tp, fp, fn):
        return 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
    per = [f1(c[k, k], c[:, k].sum() - c[k, k], c[k, :].sum() - c[k, k]) for k in range(len(c))]
    return {"n": int(n), "overall_accuracy": float(np.trace(c) / n) if n else 0.0, "f1": [float(v) for v in per],
            "damaged_f1": float(f1(c[1:, 1:].sum(), c[0, 1:].sum(), c[1:, 0].sum()))}


def _renumber(x, f):
    if isinstance(x, list):
        return [_renumber(y, f) for y in x]
    return f(x) if isinstance(x, int) else x


def city(work: Path, damage: str, seed: int) -> tuple[Path, dict, float, int]:
    """The packed Zurich city damaged with `damage` by generator seed `seed`, its
    preset-acquired pairs, the generation seconds and how many grade-4/5 collapses fell back
    to the patterns."""
    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.acquisition.survey import preset
    from quakescan.formats.cityjson import import_cityjson
    from quakescan.formats.scene import read_scene, write_scene
    from quakescan.generator import GenerationSpec, generate

    source = source_folder(work)
    if not (source / "scene.json").is_file():
        n = packed_cityjson(ZURICH, work / "zurich_packed.city.json")
        scene = import_cityjson(work / "zurich_packed.city.json")
        assert len(scene.building_ids) == n, (len(scene.building_ids), n)
        write_scene(scene, source)
    n = len(read_scene(source).building_ids)
    folder = work / f"seed_{seed}" / f"city_{damage}"
    t0 = time.perf_counter()
    generate(GenerationSpec("bundle", "mixed", None, seed, folder, grade_mix=scaled_mix(n), source=source,
                            damage=damage, force=True))
    seconds = time.perf_counter() - t0
    fallback = 0
    if damage != "patterns":
        fallback = sum(1 for b in read_scene(folder / "post").buildings
                       if b.grade >= 4 and "physics_collapse" not in {p["name"] for p in b.patterns})
    acq = {"uls": Acquisition("uls", preset("paper")), "dim": Acquisition("dim", preset_dim("paper")),
           "als": Acquisition("als", preset("als"))}
    clouds = {}
    for kind, sensor_seed in SENSOR_SEEDS.items():
        for scene_name, k in (("pre", 0), ("post", 1)):
            if kind == "als" and scene_name == "post":  # the archive is the pre-event epoch only
                continue
            p = work / f"seed_{seed}" / "clouds" / damage / f"{scene_name}_{kind}.las"
            p.parent.mkdir(parents=True, exist_ok=True)
            acquire(folder / scene_name, acq[kind], p, seed=sensor_seed * 10 + k)
            clouds[(scene_name, kind)] = p
    pairs = {name: (clouds[("pre", a)], clouds[("post", b)]) for name, (a, b) in PAIRS.items()}
    return folder, pairs, seconds, fallback


def source_folder(work: Path) -> Path:
    """The imported Zurich scene: another importer, another scene (and folder)."""
    from quakescan.formats.cityjson import IMPORT_VERSION

    return work / f"source_v{IMPORT_VERSION}"


def main(argv=None) -> int:
    from quakescan.learning.default_model import DEFAULT_MODEL

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_zurich"))
    p.add_argument("--model", default=str(DEFAULT_MODEL))
    p.add_argument("--seeds", default=",".join(str(v) for v in SEEDS),
                   help="generator seeds, comma-separated: each damages the same buildings anew (pooled in the table)")
    p.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    a = p.parse_args(argv)
    if not ZURICH.is_file():
        p.error(f"{ZURICH}: the Zurich CityJSON model is missing (the shared data folder sits beside the repository)")
    work = Path(a.work)
    t_start = time.perf_counter()
    seeds = [int(v) for v in a.seeds.split(",") if v.strip()]
    rows, results = [], {"machine": machine(), "model": a.model, "seeds": seeds, "rows": []}
    gen, fell = {"patterns": 0.0, "physics": 0.0}, {"patterns": 0, "physics": 0}
    pooled: dict = {}
    for damage in ("patterns", "physics"):
        for seed in seeds:
            folder, pairs, secs_gen, fallback = city(work, damage, seed)
            gen[damage] += secs_gen
            fell[damage] += fallback
            print(f"{damage}, seed {seed}: city generated in {secs_gen:.0f} s; collapses that fell back to the "
                  f"patterns: {fallback}", flush=True)
            for name, (pre, post) in pairs.items():
                tag = f"seed_{seed}/{damage}_{name.replace(' ', '_')}"
                _, secs, ev = classify_and_evaluate(pre, post, work / "results" / tag, a.model, folder)
                results["rows"].append({"damage": damage, "pair": name, "seed": seed,
                                        "overall_accuracy": ev.overall_accuracy, "n": ev.n,
                                        "not_assessable": ev.not_assessable,
                                        "confusion": np.asarray(ev.confusion).tolist(), "classify_s": round(secs, 1)})
                c, na = pooled.get((damage, name), (0, 0))
                pooled[(damage, name)] = (c + np.asarray(ev.confusion), na + ev.not_assessable)
                print(f"  {damage} {name}, seed {seed}: OA {100 * ev.overall_accuracy:.1f} % on {ev.n}", flush=True)
    for (damage, name), (conf, not_assessable) in pooled.items():
        m = confusion_metrics(conf)
        results.setdefault("pooled", []).append({"damage": damage, "pair": name, **m, "not_assessable": not_assessable})
        rows.append([damage, name, f"{100 * m['overall_accuracy']:.1f}",
                     *[f"{100 * v:.0f}" for v in m["f1"]], f"{100 * m['damaged_f1']:.1f}",
                     f"{m['n']} ({not_assessable})"])
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    results["peak_mib"] = round(peak_rss_mb())
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    from quakescan.formats.scene import read_scene

    mix = scaled_mix(len(read_scene(source_folder(work)).building_ids))
    seed_text = ", ".join(str(v) for v in seeds)
    text = "\n".join([
        "## Real building shapes never trained on: Zurich (`bench/bench_zurich.py`)", "",
        f"Machine: {machine()}. Command: `.venv/bin/python bench/bench_zurich.py`; {results['seconds'] / 60:.1f} min "
        f"(generating the cities {gen['patterns']:.0f} s with the patterns, {gen['physics']:.0f} s by physics, "
        f"skipped when up to date); peak {results['peak_mib']:,} MiB. Model: {Path(a.model).name}. The Zurich LoD2 "
        f"model's {sum(mix.values())} buildings packed into a compact city (shapes unchanged), grades "
        + "/".join(str(mix[g]) for g in (0, 3, 4, 5)) + f" (0/3/4/5, the paper's proportions), damaged by generator seeds "
        f"{seed_text} (each row pools them: {len(seeds)} x {sum(mix.values())} buildings), once with the "
        f"add-on's patterns and once with grades 4-5 collapsed by rigid-body simulation ({fell['physics']} collapses "
        "did not come to rest and kept the patterns); paper ULS and DIM presets, and the ALS-like preset before a drone after. Reserved for evaluation: measured "
        "here, never trained or tuned on. Overall accuracy %, F1 % per grade, damaged vs undamaged F1 %.", "",
        table(["damage", "pair", "OA", "F1 0", "F1 3", "F1 4", "F1 5", "F1 damaged", "assessed (not)"], rows)])
    print(text)
    if not a.no_write:
        write_section("zurich", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
