"""A tour of QuakeScan's Python API (`import quakescan as qs`), end to end on a small city.

Run it from a checkout after the README's set-up (about a minute on 2 cores):

    .venv/bin/python docs/examples/api_tour.py [OUT_DIR]

It generates a 12-building mixed city (the add-on's generator, headless), acquires it with
the UAV laser scanner before and with the photogrammetry simulator after the event (two
sensors: what responders often have), grades its buildings with the model QuakeScan ships,
scores them against the generator's grades, looks at one building's change descriptors and
trains a small model of its own on the pair. The tests run it (tests/test_api.py).
"""
import sys
from pathlib import Path

import quakescan as qs
from quakescan.generator import GenerationSpec, generate


def main(out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    # 1. a damaged city: scene bundles city/pre and city/post (mesh + labels + grades)
    generate(GenerationSpec("region", "mixed", 12, 7, out / "city"))
    city = qs.read_scene(out / "city" / "post")
    print(f"{len(city.buildings)} buildings, grades {sorted(b.grade for b in city.buildings)}")

    # 2. two acquisitions: the paper's UAV laser scan before, its photo flight after
    print("sensors:", ", ".join(qs.sensor_kinds()))
    pre = qs.acquire(out / "city" / "pre", out / "pre.las", kind="uls", seed=1).path
    post = qs.acquire(out / "city" / "post", out / "post.las", kind="dim", seed=2).path
    epoch = qs.read_epoch(pre)
    print(f"pre-event epoch: {len(epoch.xyz)} points, origin {epoch.origin.round(1).tolist()}")

    # 3. grade every building with the shipped model, and score against the known grades
    summary = qs.classify(pre, post, out / "result", write_las=False)
    report = qs.evaluate(out / "result" / "buildings.csv", out / "city" / "post")
    print(f"shipped model: {summary['by_label']}; overall accuracy {100 * report.overall_accuracy:.0f} % "
          f"on {report.n} buildings")

    # 4. what the model read: change descriptors per building (shares of the footprint or surface)
    rows = qs.describe(pre, post)
    most = max((r for r in rows if r.assessable), key=lambda r: r.descriptors["s_lowered_1m"])
    print(f"building {most.building_id}: {100 * most.descriptors['s_lowered_1m']:.0f} % of its footprint "
          f"lowered by more than 1 m")

    # 5. a model of one's own (on this one pair only: a toy; the shipped one learnt from 36 cities)
    model, evaluation, table = qs.train([(pre, post)], descriptors="surface", test_size=0)
    qs.save_model(model, out / "own_model.skops")
    print(f"own model: {table.x.shape[0]} buildings x {table.x.shape[1]} descriptors")
    return {"buildings": len(city.buildings), "overall_accuracy": report.overall_accuracy, "rows": len(rows),
            "trained_rows": int(table.x.shape[0])}


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/api_tour"))
