"""Realism: do simulated undamaged buildings change between two acquisitions as much as real ones?

A classifier trained on simulated scenes reads anything its simulated undamaged buildings never
showed as damage. The purest real no-change pair is one airborne tile split into two random
halves (AHN3 Delft, `default_rng(5).random(n) < 0.5`, real footprints): the same flight, the
same day, no damage. Its simulated analogue: a city's pre-event scene scanned once by the
airborne (ALS-like) preset at the tile's density, with range noise and strip misalignment,
split the same way, its points assigned to buildings through the scene's footprints as the
real ones are. For each descriptor the shipped model reads, this script prints the 50th, 90th
and 99th percentiles over buildings, real beside simulated, for the generator's bare scenes
(`clean`) and its realistic ones (roof and facade detail, trees, hedges, cars, street
furniture: `realistic`), and whether the simulated 90th percentile lies within ±30 % of the
real one (or both within 0.005 of zero: a share below half a percent of a footprint is no
change by construction, `SurfaceSettings.min_share`), and the share of buildings whose value
is off its no-change value by more than 0.005: the tail the percentiles hide, where the false
alarms on real data live.

    .venv/bin/python bench/bench_realism.py [--variants clean,realistic] [--no-write]

Simulated cities: a generic town and an L'Aquila-like centre of 64 buildings and the
Rotterdam LoD2 cluster (15 buildings), seeds outside the training set's; the Zurich model is
reserved for evaluation and not used. Writes the table to BENCHMARKS.md (section "realism").
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import machine, peak_rss_mb, table, write_section  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
HALF_SEED = 5
TOLERANCE = 0.30
ZERO = 0.005
ALS_RANGE_NOISE_M = 0.03  # mid-range of quakescan.acquisition.sensor_lidar.ALS_RANGE_NOISE_M
ALS_MISALIGNMENT_M = 0.05  # mid-range of quakescan.acquisition.sensor_lidar.ALS_MISALIGNMENT_M
CITIES = (("generic", 64, 81_001), ("region", 64, 81_002), ("rotterdam", None, 81_003))


def halves(las_path: Path, out: Path) -> tuple[Path, Path]:
    """The cloud split into two random halves (seed 5), written once."""
    import laspy

    out.mkdir(parents=True, exist_ok=True)
    paths = (out / f"{las_path.stem}_a.las", out / f"{las_path.stem}_b.las")
    if all(p.is_file() for p in paths):
        return paths
    las = laspy.read(las_path)
    first = np.random.default_rng(HALF_SEED).random(len(las.points)) < 0.5
    for p, mask in zip(paths, (first, ~first)):
        sub = laspy.LasData(las.header)
        sub.points = las.points[mask]
        tmp = p.with_name(p.name + ".part.las")
        sub.write(tmp)
        tmp.replace(p)
    return paths


def describe(pre: Path, post: Path, footprints: Path, settings, limits) -> dict:
    """{descriptor: values over the assessable buildings} and the buildings' densities."""
    from quakescan.change.pipeline import describe_pair, quality_gate
    from quakescan.formats.pair import load_pair

    data = load_pair(pre, post, footprints)
    rows = [quality_gate(r, limits) for r in describe_pair(data.pre, data.post, settings)]
    rows = [r for r in rows if r.assessable]
    out = {n: np.array([r.descriptors[n] for r in rows]) for n in settings.surface_descriptors}
    out["_density"] = np.array([min(r.quality.get("density_pre", np.nan), r.quality.get("density_post", np.nan))
                                for r in rows])
    return out


def real_values(work: Path, settings, limits) -> tuple[dict, float]:
    from quakescan.acquisition.density import measured_density

    parts, densities = [], []
    for tile in (1, 2):
        src = SHARED / f"ahn3_cropped_{tile}.laz"
        fp = SHARED / "ahn3_footprints_rd.geojson"
        if not src.is_file() or not fp.is_file():
            print(f"skipping {src}: missing", flush=True)
            continue
        a, b = halves(src, work / "real")
        parts.append(describe(a, b, fp, settings, limits))
        densities.append(measured_density(src))
        print(f"real: AHN3 tile {tile}: {len(parts[-1]['_density'])} assessable buildings, "
              f"{densities[-1]:.1f} pts/m² before the split", flush=True)
    return merge(parts), float(np.mean(densities)) if densities else 15.0


def simulated_values(work: Path, variant: str, density: float, settings, limits) -> dict:
    """Undamaged buildings of the simulated cities, scanned once at `density` and halved."""
    from dataclasses import replace

    from quakescan.acquisition.acquire import Acquisition, acquire
    from quakescan.acquisition.survey import als_for_density
    from quakescan.learning.trainset import CitySpec, generate_city, scene_footprints

    look = "typical" if variant == "realistic" else "none"
    survey = replace(als_for_density(density), range_noise_sigma_m=ALS_RANGE_NOISE_M,
                     strip_misalignment_m=ALS_MISALIGNMENT_M)
    parts = []
    for source, n, seed in CITIES:
        city = CitySpec(f"{source}_{variant}", source, "mixed", seed, n, {0: n or 15}, look, look)
        folder = work / "scenes" / city.name
        t = time.perf_counter()
        generate_city(city, folder)
        cloud = work / "clouds" / f"{city.name}.las"
        cloud.parent.mkdir(parents=True, exist_ok=True)
        acquire(folder / "pre", Acquisition("als", survey), cloud, seed=seed)
        a, b = halves(cloud, work / "clouds")
        parts.append(describe(a, b, scene_footprints(folder), settings, limits))
        print(f"simulated {variant}: {source}: {len(parts[-1]['_density'])} assessable buildings, "
              f"median density {np.nanmedian(parts[-1]['_density']):.1f} pts/m² per half "
              f"({time.perf_counter() - t:.0f} s)", flush=True)
    return merge(parts)


def merge(parts: list) -> dict:
    if not parts:
        return {}
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def matches(sim: float, real: float) -> bool:
    return abs(sim - real) <= TOLERANCE * abs(real) or (abs(sim) <= ZERO and abs(real) <= ZERO)


def _share(values) -> str:
    """Share of buildings off the no-change value (0 for shares and lengths, 1 for height ratios):
    the tail a percentile table hides."""
    rest = 1.0 if np.nanmedian(values) > 0.5 else 0.0
    return f"{100 * np.mean(np.abs(values - rest) > ZERO):.1f} %"


def report(real: dict, sims: dict, names: list, seconds: float) -> str:
    q = (50, 90, 99)
    headers = ["descriptor", "real P50 / P90 / P99", "real > 0.005"]
    for v in sims:
        headers += [f"{v} P50 / P90 / P99", f"{v} > 0.005", f"{v} P90 within ±30 %"]
    rows, hits = [], {v: 0 for v in sims}
    for n in names:
        r = np.percentile(real[n], q)
        row = [n, " / ".join(f"{x:.3f}" for x in r), _share(real[n])]
        for v, s in sims.items():
            p = np.percentile(s[n], q)
            ok = matches(p[1], r[1])
            hits[v] += ok
            ratio = f"{p[1] / r[1]:.2f}×" if abs(r[1]) > ZERO else "—"
            row += [" / ".join(f"{x:.3f}" for x in p), _share(s[n]), f"{'yes' if ok else 'no'} ({ratio})"]
        rows.append(row)
    counts = ", ".join(f"{v}: {len(s['_density'])} buildings, {hits[v]} of {len(names)} descriptors within ±30 %"
                       for v, s in sims.items())
    dens = ", ".join(f"{v} {np.nanmedian(s['_density']):.1f}" for v, s in sims.items())
    return (f"Machine: {machine()}; {seconds:.0f} s, peak {peak_rss_mb():.0f} MiB. Command: "
            f"`.venv/bin/python bench/bench_realism.py`.\n\n"
            f"Undamaged buildings of a no-change pair, percentiles over buildings. Real: AHN3 tiles 1 and 2 "
            f"split into random halves, {len(real['_density'])} assessable buildings, median density "
            f"{np.nanmedian(real['_density']):.1f} pts/m² per half. Simulated: the same procedure on generated "
            f"cities scanned by the ALS-like preset at the tile's density (median per half: {dens}); {counts}.\n\n"
            + table(headers, rows))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "out" / "bench_realism"))
    p.add_argument("--model", default=None, help="model whose descriptors and limits to compare (default: shipped)")
    p.add_argument("--variants", default="clean,realistic")
    p.add_argument("--no-write", action="store_true")
    a = p.parse_args(argv)
    from quakescan.learning.default_model import default_model_path
    from quakescan.learning.prediction import model_settings
    from quakescan.learning.model import load_model

    t0 = time.perf_counter()
    work = Path(a.work)
    model = load_model(a.model or default_model_path())
    settings = model_settings(model)
    names = [n for n in model.feature_names if n in settings.surface_descriptors]
    real, density = real_values(work, settings, settings)
    if not real:
        print("no real data: nothing to compare", flush=True)
        return 1
    sims = {v: simulated_values(work, v, density, settings, settings) for v in a.variants.split(",")}
    text = report(real, sims, names, time.perf_counter() - t0)
    print(text)
    if not a.no_write:
        write_section("realism", "## Realism: simulated vs real undamaged buildings (`bench/bench_realism.py`)\n\n"
                      + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
