"""Speed and completeness of the DIM simulator's knobs, side by side in one run.

    .venv/bin/python bench/bench_dim.py     # prints the table, rewrites its section of BENCHMARKS.md

Scene: the paper's generic pre-event city (112 buildings, generate_scenes.py --set
generic --dataset paper --seed 1; reused from out/default_model/generic when present).
Each row is one `simulate_dim` with the `paper` photo survey and one knob changed. What a
knob costs in accuracy is what it leaves out: points on interiors (seen only through
openings), points per surface, and the roof/facade spacing the paper's clouds set.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._report import machine, peak_rss_mb, table, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "out" / "default_model" / "generic" / "pre"

KNOBS = [
    ("paper preset (probe 0.5 m, 12 views, 1 point / 8 px)", {}),
    ("probe_spacing_m 0.25 (finer visibility probes)", {"probe_spacing_m": 0.25}),
    ("max_candidate_views 24", {"max_candidate_views": 24}),
    ("point_step_px 4 (Metashape 'medium')", {"point_step_px": 4}),
]


def spacing(path: Path) -> tuple[float, float]:
    import laspy

    sys.path.insert(0, str(ROOT))
    from tests.spacing import nearest_neighbour_spacing

    las = laspy.read(path)
    xyz = np.column_stack([las.x, las.y, las.z])
    bid, surf = np.asarray(las["building_id"]), np.asarray(las["surface"])
    return tuple(float(nearest_neighbour_spacing(xyz, bid, surf, code).mean()) for code in (1, 2))


def main():
    from quakescan.acquisition.dim import simulate_dim
    from quakescan.acquisition.dim_settings import preset_dim
    from quakescan.formats.scene import read_scene
    from quakescan.generator import GenerationSpec, generate

    if not (SCENE / "scene.json").is_file():
        generate(GenerationSpec("generic", "paper", 112, 1, SCENE.parent, force=True))
    scene = read_scene(SCENE)
    simulate_dim(scene, preset_dim("paper").replace(oblique_cameras=0), Path(tempfile.gettempdir()) / "warm.las")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, change in KNOBS:
            out = Path(tmp) / "dim.las"
            s = simulate_dim(scene, preset_dim("paper").replace(**change), out, seed=1)
            roof, facade = spacing(out)
            by = s.points_by_surface
            rows.append((label, f"{s.wall_time_s:.1f}", f"{s.points:,}", f"{by.get('roof', 0):,}",
                         f"{by.get('wall', 0):,}", f"{by.get('interior', 0):,}", f"{by.get('debris', 0):,}",
                         f"{roof:.3f}", f"{facade:.3f}"))
            print(rows[-1], flush=True)
            out.unlink()
    text = "\n\n".join([
        "## DIM simulation knobs (`bench/bench_dim.py`)",
        f"Machine: {machine()}. Scene: the generic pre-event city (112 buildings), `paper` photo survey with one "
        "knob changed per row, seed 1. Paper's L'Aquila DIM spacing: roof 0.09 m, facade 0.12 m.",
        table(["setting", "wall s", "points", "roof", "wall", "interior", "debris", "roof spacing m",
               "facade spacing m"], rows),
        f"Peak memory of the run: {peak_rss_mb():.0f} MiB. Command: `.venv/bin/python bench/bench_dim.py`",
    ])
    print("\n" + text)
    write_section("bench_dim", text)


if __name__ == "__main__":
    main()
