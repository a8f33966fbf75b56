"""The built-in default run (`quakescan demo`): the whole chain on a small simulated city.

generate (the add-on's headless generator: a mixed city, a grade drawn per building, placed
in L'Aquila, EPSG:32633)
→ scan both epochs with the paper's survey → classify with the shipped model → evaluate
against the generator's grades → map. Every step writes atomically and is skipped when its
output is there and current (`quakescan.runtime.fingerprint`; the clouds by
`quakescan.acquisition.acquire`'s rule), so an interrupted demo continues where it stopped.

The generator needs Blender's Python: the `bpy` module in this environment (set-up
installs it) or a `blender` binary on PATH. `quakescan` itself never imports bpy; it runs the
generator as a separate process.
"""
from __future__ import annotations

import json
from pathlib import Path

from .errors import QuakeScanError
from .generator import GenerationSpec, generate
from .runtime.progress import ProgressCallback, in_stage, stage_log

# The demo city stands in L'Aquila (the paper's test region), in UTM zone 33N: its
# GeoJSON, maps and clouds land there in QGIS or CloudCompare.
DEMO_CRS = "EPSG:32633"
DEMO_ORIGIN = (367000.0, 4690000.0, 0.0)


class DemoError(QuakeScanError):
    """The demo cannot run on this machine as installed."""


def scan_scene(scene_dir: Path, out: Path, seed: int, progress: ProgressCallback | None = None) -> None:
    """Scan with the paper's survey unless `out` is current (`quakescan.acquisition.acquire`'s rule: the
    record beside the cloud holds the same scene, survey and seed, and the cloud is the file
    it recorded)."""
    from .acquisition import sensors
    from .acquisition.acquire import Acquisition, acquire

    acquire(scene_dir, Acquisition("uls", sensors.get("uls").default()), out, seed=seed, progress=progress)


def las_is_complete(path: Path) -> bool:
    """An uncompressed LAS whose size is what its header says (a cut copy is not): its point
    records end the file (the scanner writes no extended VLRs)."""
    import laspy

    if path.suffix.lower() != ".las":
        return True  # a LAZ's chunk table would tell; the demo writes LAS
    try:
        with laspy.open(path) as f:
            h = f.header
            expected = h.offset_to_point_data + h.point_count * h.point_format.size
    except Exception:  # an unreadable header: scan again
        return False
    return path.stat().st_size == expected


# The demo is a small city; larger ones are generated with blender_scripts/generate_scenes.py.
MAX_DEMO_BUILDINGS = 500


def check_demo_options(seed, buildings) -> None:
    """Refuse what the generator would refuse, in `quakescan demo`'s words (its own errors
    name generate_scenes.py, which the user never called)."""
    if isinstance(buildings, bool) or not isinstance(buildings, int) or not 1 <= buildings <= MAX_DEMO_BUILDINGS:
        raise DemoError(f"demo --buildings: expected 1..{MAX_DEMO_BUILDINGS} buildings, got {buildings!r}")
    # the scans use 2·seed + 1 and 2·seed + 2, the generator seeds below 2^32
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 31 - 1:
        raise DemoError(f"demo --seed: expected an integer in 0..{2 ** 31 - 2}, got {seed!r}")


def run_demo(out_dir, seed: int = 0, buildings: int = 30, progress: ProgressCallback | None = None) -> dict:
    """The whole chain into out_dir (module doc). `progress` counts three stages: "scan pre",
    "scan post" and "classify"; stage messages go to the logger `quakescan.stages`."""
    check_demo_options(seed, buildings)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    city = out / "city"
    stage_log.info(f"demo 1/5: generating a mixed city of {buildings} buildings (seed {seed}) -> {city}")
    # force: a demo folder from an older QuakeScan (its city at another place) is regenerated, then rescanned
    generate(GenerationSpec("generic", "mixed", buildings, seed, city, origin=DEMO_ORIGIN, crs=DEMO_CRS, force=True))
    stage_log.info("demo 2/5: scanning the pre- and post-event scenes with the paper's UAV survey")
    scan_scene(city / "pre", out / "pre.las", seed=seed * 2 + 1, progress=in_stage(progress, "scan pre"))
    scan_scene(city / "post", out / "post.las", seed=seed * 2 + 2, progress=in_stage(progress, "scan post"))
    stage_log.info("demo 3/5: classifying every building with the shipped model")
    from .assessment.run import classify

    result = out / "result"
    summary = classify(out / "pre.las", out / "post.las", result, progress=in_stage(progress, "classify"))
    stage_log.info("demo 4/5: evaluating against the grades the generator assigned")
    from .results.evaluation import evaluate_files, plot_confusion

    ev = evaluate_files(result / "buildings.csv", city / "post")
    plot_confusion(ev, result / "confusion.png", title="Demo city: truth vs prediction")
    from .runtime.atomic import write_text

    write_text(result / "evaluation.json", json.dumps(ev.to_json(), indent=1))
    stage_log.info(f"demo 5/5: maps -> {result / 'damage_map.png'}, {result / 'damage_map.html'} (opens offline)")
    return {"summary": summary, "evaluation": ev, "result": result}

