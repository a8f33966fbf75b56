"""A job of the headless scene generator made (`run`): the city or the source bundle's
buildings built once as the pre-event scene, each post-event scene damaged from it, every
bundle written to a temporary folder and renamed into place, bundles made with the same
settings kept (blender_scripts/generate_scenes.py runs it; its module doc is the user's guide).

No bpy at module level: `run` says what is missing when Blender's modules are not there.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path

from .generation_jobs import collapse_scenes, parts_folder, run_collapse_jobs, run_jobs, simulate_collapses
from .generation_spec import PROG, log
from .versions import GENERATOR_VERSION, PHYSICS_VERSION


def read_grades(path, ids) -> dict:
    """{building ID: grade} of a --grades file, every source building present (0 where unlisted).
    Raises ValueError naming the file and what is wrong."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"--grades {path}: cannot read it as JSON ({e})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"--grades {path}: expected an object {{\"building ID\": grade}}, got {type(raw).__name__}")
    grades = {int(i): 0 for i in ids}
    for key, g in raw.items():
        try:
            bid = int(key)
        except ValueError:
            raise ValueError(f"--grades {path}: {key!r} is not a building ID") from None
        if bid not in grades:
            raise ValueError(f"--grades {path}: building {bid} is not in the --source bundle")
        if isinstance(g, bool) or not isinstance(g, int) or not 0 <= g <= 5:
            raise ValueError(f"--grades {path}: building {bid}: grade must be an integer 0-5, got {g!r}")
        grades[bid] = g
    return grades


def scene_list(dataset, ids, seed, grade_mix=None, grades=None):
    from . import citygen

    if dataset == "paper":
        return [("pre", None)] + [(name, g) for name, g in citygen.PAPER_SCENES]
    if grades is not None:
        return [("pre", None), ("post", grades)]
    if grade_mix:
        return [("pre", None), ("post", citygen.exact_grades(ids, grade_mix, seed))]
    return [("pre", None), ("post", citygen.mixed_grades(ids, seed))]


def generator_info(spec, scene_name, source_sha256=None, grades=None) -> dict:
    """The generator record of a bundle (scene.json "generator"): the settings that made it,
    which a rerun must match to keep it. `source_sha256`: the source bundle's digest (set
    "bundle"); `grades`: {building ID: grade} of a --grades file."""
    info = {"script": PROG, "version": GENERATOR_VERSION, "set": spec.set_name, "dataset": spec.dataset,
            "buildings": spec.buildings, "seed": spec.seed, "scene": scene_name}
    if spec.details != "none":  # absent for "none": older bundles stay resumable
        info["details"] = spec.details
    if spec.grade_mix:
        info["grade_mix"] = {str(g): n for g, n in sorted(spec.grade_mix.items())}
    if grades is not None:  # absent without --grades: older bundles stay valid
        info["grades"] = {str(b): g for b, g in sorted(grades.items()) if g}
    if spec.set_name == "bundle":
        info["source"] = {"name": Path(spec.source).resolve().name, "sha256": source_sha256}
    if spec.streetscape != "none":  # absent with none: older bundles stay valid
        info["streetscape"] = spec.streetscape
    if spec.origin is not None:  # absent by default: older bundles stay valid
        info["origin"] = list(spec.origin)
    if spec.crs:
        info["crs"] = spec.crs
    if spec.damage != "patterns":  # absent with patterns: older bundles stay valid
        info["damage"] = spec.damage
        info["settle_steps"] = spec.settle_steps
        info["physics_version"] = PHYSICS_VERSION
    return info


def _swap_into_place(tmp: Path, final: Path):
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def source_sha256(folder) -> str:
    """Digest of a source bundle's scene.json and mesh (resume only when the source is the same)."""
    import hashlib
    h = hashlib.sha256()
    folder = Path(folder)
    manifest = folder / "scene.json"
    h.update(manifest.read_bytes())
    try:
        mesh = json.loads(manifest.read_text()).get("mesh", "mesh.ply")
    except (json.JSONDecodeError, AttributeError):
        mesh = "mesh.ply"
    if isinstance(mesh, str) and (folder / mesh).is_file():
        h.update((folder / mesh).read_bytes())
    return h.hexdigest()


def bundle_ids(spec, manifest) -> list:
    """IDs of the source buildings used: all, or a seeded sample of --buildings of them."""
    import numpy as np
    ids = sorted(int(b["id"]) for b in manifest["buildings"])
    if spec.buildings is None or spec.buildings >= len(ids):
        return ids
    rng = np.random.default_rng([spec.seed, 404])
    return sorted(int(i) for i in rng.choice(ids, size=spec.buildings, replace=False))


def build_bundle_pre(spec, pre, manifest):
    """Import the source's terrain and chosen buildings into `pre` and prepare them for damage
    (labels, storey splits, coarse interiors; a per-building damage seed from --seed)."""
    import numpy as np

    from . import io_import, scene_tools

    ids = bundle_ids(spec, manifest)
    info = io_import.import_bundle(spec.source, pre, building_ids=ids)
    for obj in info["buildings"]:
        io_import.prepare_for_damage(obj)
        obj.qs_building.seed = int(np.random.default_rng([spec.seed, 505, obj.qs_building.building_id])
                                   .integers(0, 2 ** 31 - 1))
        obj.qs_building.patterns_json = "[]"
        if spec.details != "none":
            scene_tools.add_roof_details(obj)
    return ids, info


def add_streetscape(spec, pre, plan):
    """Trees, hedges, furniture and cars around the buildings of collection `pre` (a CityPlan's
    footprints, or the xy extents of an imported bundle's buildings on its terrain).
    Returns (streetscape, footprints, bounds, ground_z, density set) for the post scenes."""
    from . import scene_tools, street_objects, streetscape

    objs = scene_tools.scene_objects(pre)
    if plan is not None:
        footprints, bounds, ground_z, set_name = streetscape.plan_footprints(plan), plan.bounds, None, plan.set_name
    else:
        footprints = street_objects.building_footprints(objs)
        terrain = street_objects.terrain_mesh(objs)
        if terrain is None:
            raise RuntimeError("--streetscape needs a terrain in the --source bundle (faces with building_id 0)")
        bounds = street_objects.terrain_bounds(terrain[0])
        ground_z = streetscape.terrain_height_function(*terrain)
        set_name = "bundle"
    t0 = time.perf_counter()
    scape = streetscape.plan_streetscape(footprints, bounds, set_name, spec.seed, ground_z)
    street_objects.add_objects(pre, scape)
    log(f"pre: streetscape {len(scape.trees)} trees, {len(scape.hedges)} hedges, {len(scape.cars)} cars, "
        f"{len(scape.furniture)} furniture in {time.perf_counter() - t0:.1f} s")
    return scape, footprints, bounds, ground_z, set_name


def run(spec, *, bundle_state, script: Path, only_scenes=None, collapse_claims=None) -> int:
    """Make the checked `spec`'s bundles; the exit status (0 done, 1 failed, 2 refused).

    `bundle_state(folder, info)`: the library's resume rule, 'missing', 'done' (a bundle with
    this generator record) or 'different' (the add-on never imports the library, so the script
    that runs it hands it over). `script`: the generator script, which the --jobs children run.
    `only_scenes` (names joined by commas) and `collapse_claims` (a folder): a --jobs child's share."""
    t_start = time.perf_counter()
    out = Path(spec.out)
    if out.exists() and not out.is_dir():
        log(f"error: --out {out} exists and is not a folder")
        return 2
    try:
        import bpy  # noqa: F401
    except ImportError:
        log("error: bpy is not available: run inside Blender (blender -b --factory-startup "
            "--python-exit-code 1 -P blender_scripts/generate_scenes.py -- ...) or install the bpy module "
            "(pip install bpy==5.0.1)")
        return 1
    try:
        import numpy  # noqa: F401
    except ImportError:
        import bpy
        log(f"error: numpy is not available to the Python {sys.version.split()[0]} of Blender "
            f"{bpy.app.version_string}: Blender's own builds bundle it; for Debian's blender install "
            "python3-numpy (apt-get install python3-numpy)")
        return 1
    import bpy

    from . import citygen, io_export, post_scene, register, scene_tools
    from .geometry.shell import ShellSpec

    if not hasattr(bpy.types.Object, "qs_building"):
        register()

    origin, crs, manifest, plan = (0.0, 0.0, 0.0), None, None, None
    source_digest, grades_map = None, None
    if spec.set_name == "bundle":
        from . import io_import
        try:
            manifest = io_import.read_bundle(spec.source)[0]  # the whole bundle is checked up front
            source_digest = source_sha256(spec.source)
        except (io_import.BundleError, OSError) as e:
            log(f"error: --source: {e}")
            return 2
        ids = bundle_ids(spec, manifest)
        origin, crs = manifest.get("origin", [0.0, 0.0, 0.0]), manifest.get("crs")
        if spec.grades is not None:
            try:
                grades_map = read_grades(spec.grades, ids)
            except ValueError as e:
                log(f"error: {e}")
                return 2
    else:
        plan = citygen.city_plan(spec.set_name, spec.buildings, spec.seed, details=spec.details)
        ids = [b.id for b in plan.buildings]
    scenes = scene_list(spec.dataset, ids, spec.seed, spec.grade_mix, grades_map)
    todo = []
    for name, grades in scenes:
        info = generator_info(spec, name, source_digest, grades_map)
        state = bundle_state(out / name, info)
        if state == "done":
            log(f"{name}: complete bundle with the same settings exists, skipped")
            continue
        if state == "different" and not spec.force:
            log(f"error: {out / name} holds a bundle made with other settings; use another --out or --force")
            return 1
        todo.append((name, grades, info))
    if only_scenes is not None:
        share = set(only_scenes.split(","))
        todo = [t for t in todo if t[0] in share]
    if not todo:
        log("nothing to do")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    if spec.jobs > 1 and collapse_claims is None:
        if collapse_scenes(spec, todo):
            code = run_collapse_jobs(spec, out, script)
            if code:
                return code
        if len(todo) > 1:
            return run_jobs(spec, todo, len(ids), script)

    scene = bpy.data.scenes.new("quakescan_generate")
    pre = bpy.data.collections.new("pre")
    scene.collection.children.link(pre)
    created_collections = [pre]
    try:
        t0 = time.perf_counter()
        if plan is None:
            build_bundle_pre(spec, pre, manifest)
            n = len(ids)
        else:
            x0, y0, x1, y1 = plan.bounds
            scene_tools.create_terrain_object(pre, x0, y0, x1, y1)
            n = len(plan.buildings)
            step = max(1, n // 10)
            for k, b in enumerate(plan.buildings):
                shell = ShellSpec(**b.shell)
                scene_tools.create_building_object(pre, shell, b.id, location=(b.location[0], b.location[1], 0.0),
                                                   rotation_z=b.rotation, vulnerability_class=b.vulnerability_class,
                                                   seed=b.seed)
                if (k + 1) % step == 0 or k + 1 == n:
                    log(f"pre: built {k + 1}/{n} buildings")
        street = None
        if spec.streetscape != "none":
            street = add_streetscape(spec, pre, plan)
        pre_objs = scene_tools.scene_objects(pre)
        log(f"pre: {n} buildings built in {time.perf_counter() - t0:.1f} s")
        if collapse_claims is not None:
            simulate_collapses(spec, collapse_scenes(spec, todo), pre_objs, out, Path(collapse_claims), street)
            todo = []
        for name, grades, info in todo:
            t0 = time.perf_counter()
            tmp = out / f".{name}.tmp-{os.getpid()}"
            shutil.rmtree(tmp, ignore_errors=True)
            if name == "pre":
                objs = pre_objs
                coll = None
            else:
                coll = bpy.data.collections.new(name)
                scene.collection.children.link(coll)
                created_collections.append(coll)

                def progress(i, total, name=name):
                    if i % max(1, total // 10) == 0 or i == total:
                        log(f"{name}: damaged {i}/{total} objects")
                def fallback(obj, message, name=name):
                    log(f"{name}: {message}; {obj.name} gets the patterns instead")
                damage = dict(damage=spec.damage, settle_steps=spec.settle_steps, on_fallback=fallback)
                if spec.damage != "patterns":  # collapses simulated by --jobs children, where they exist
                    from . import collapse_parts
                    damage["collapses"] = collapse_parts.loader(parts_folder(out, name), info)
                if street is None:
                    post_scene.make_post_scene(pre_objs, coll, grades=grades, on_progress=progress, **damage)
                else:  # trees, hedges, furniture copied; the pre-event cars replaced by this scene's
                    from . import street_objects, streetscape
                    post_scene.make_post_scene([o for o in pre_objs if not street_objects.is_car_object(o)], coll,
                                                grades=grades, on_progress=progress, **damage)
                    scape, footprints, bounds, ground_z, set_name = street
                    cars = streetscape.post_event_cars(scape, footprints, bounds, set_name, spec.seed, name, ground_z)
                    street_objects.add_objects(coll, streetscape.Streetscape(cars=cars), kinds=("cars",),
                                               suffix=".post")
                objs = scene_tools.scene_objects(coll)
            if plan is None:  # keeps the source's float64 coordinates, origin and CRS
                rep = io_import.export_bundle(tmp, objs, epoch="pre" if name == "pre" else "post",
                                              origin=origin, crs=crs, extra={"generator": info})
            else:
                rep = io_export.export_objects(tmp, objs, epoch="pre" if name == "pre" else "post",
                                               origin=spec.origin or (0.0, 0.0, 0.0), crs=spec.crs or None,
                                               extra={"generator": info})
            _swap_into_place(tmp, out / name)
            shutil.rmtree(parts_folder(out, name), ignore_errors=True)  # in the bundle now
            log(f"{name}: wrote {out / name} ({rep['buildings']} buildings, {rep['faces']} faces) "
                f"in {time.perf_counter() - t0:.1f} s")
            if coll is not None:
                scene_tools.remove_collection_objects(coll)
    finally:
        for coll in created_collections:
            scene_tools.remove_collection_objects(coll)
            bpy.data.collections.remove(coll)
        bpy.data.scenes.remove(scene)
        for p in out.glob(f".*.tmp-{os.getpid()}"):
            shutil.rmtree(p, ignore_errors=True)
    log(f"done in {time.perf_counter() - t_start:.1f} s")
    return 0
