#!/usr/bin/env python3
"""Generate labelled pre-/post-event scene bundles of a procedural city, headless.

Run inside Blender or with the bpy module:

    blender -b --factory-startup --python-exit-code 1 -P blender_scripts/generate_scenes.py -- \\
        --set generic --dataset paper --buildings 112 --seed 1 --out out/generic
    python blender_scripts/generate_scenes.py --set region --dataset mixed --buildings 40 --seed 2 --out out/region
    python blender_scripts/generate_scenes.py --set small --dataset mixed --grade-mix 0:20,3:14,4:15,5:15 \
        --seed 3 --out out/small

--set generic is a European town (detached houses to apartment blocks), region an L'Aquila-like
historic centre, small a town of small buildings (garden sheds, garages, Dutch row houses,
small detached houses; most footprints 8-60 m^2, as half the buildings in airborne LiDAR of
Dutch towns); see addon/citygen.py.

--dataset paper writes DIR/pre and DIR/post_heavy, DIR/post_extreme, DIR/post_destruction
(every building at EMS-98 grade 3, 4 and 5: the seed paper's design); --dataset mixed
writes DIR/pre and DIR/post with grades drawn per building (0-5).

--details typical adds roof and facade details to the buildings (dormers, chimneys, skylights,
eaves overhangs, balconies, antennas, solar panels, rooftop structures, annexes, terraces;
frequencies by typology in addon/citygen.py); default none.

--set bundle --source SCENE_DIR takes the buildings and terrain of an existing scene bundle
(e.g. one imported from CityJSON) instead of a procedural city; --buildings then picks a
seeded sample of that many of its buildings (default: all), the others are left out. The
output keeps the source's origin, CRS and float64 coordinates. Imported LoD2 shells are
damaged as box-like buildings (see addon/io_import.py and docs/addon.md for the limits).

--origin X,Y[,Z] and --crs EPSG:n place a procedural (generic, region or small) city in the world: the bundles'
origin and CRS (the mesh stays in local metres around it), e.g. --origin 367000,4690000
--crs EPSG:32633 puts it at L'Aquila in UTM zone 33N, as `quakescan demo` does.

--damage physics|both makes grades 4-5 by rigid-body simulation (addon/physics.py: the
building fractures where the grade removes support and settles under gravity, neighbours and
terrain as colliders), for all or a seeded half of those buildings; recorded in scene.json
as the pattern "physics_collapse" with its parameters and seed. Default patterns: the output
is what it was before the option existed.

--streetscape typical adds trees (porous crowns, some overhanging roofs), hedges, parked
cars and street furniture (addon/streetscape.py); every post-event scene keeps the trees,
hedges and furniture and gets its own mix of parked cars. Default none: no streetscape, the
output is what it was before the option existed.

--jobs N makes the scenes in N processes at once; with --damage physics|both it first shares
out the collapses of every scene (each depends only on its building and its neighbours as
they stand before the event): the N processes claim them one at a time, costliest scene
first, and leave each in DIR/.<scene>.collapses/ (one part file a building), from which the
scenes are then written. Same bytes as --jobs 1; an interrupted run keeps the finished
collapses and redoes only the missing ones.

Each scene is a bundle (scene.json + mesh.ply, docs/DESIGN.md "Scene bundle"). Bundles are
written to a temporary folder and renamed into place, so DIR/<scene> is either complete or
absent. A complete bundle made with the same settings is skipped (resume after an
interruption); one made with other settings stops the run unless --force. The same
settings give the same bytes. Progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PROG = "generate_scenes.py"
# addon/citygen.py's SETS and "bundle" (spelt out: the arguments are parsed before the add-on is importable)
SETS = ("generic", "region", "small", "bundle")


def addon_module(name: str = ""):
    """The add-on, or its submodule `name` ("geometry.shell"): the addon/ folder beside
    blender_scripts/ in a checkout, else the installed add-on `quakescan_damage` (a wheel ships
    this script as quakescan/blender_scripts/, two levels below site-packages)."""
    import importlib

    if (REPO / "addon" / "__init__.py").is_file():
        package = "addon"
        if str(REPO) not in sys.path:
            sys.path.insert(0, str(REPO))
    else:
        package = "quakescan_damage"
        # appended, not prepended: Blender's own Python keeps its own numpy ahead of a venv's
        if str(REPO.parent) not in sys.path:
            sys.path.append(str(REPO.parent))
    return importlib.import_module(f"{package}.{name}" if name else package)


# The add-on's own versions (addon/versions.py: beside the patterns that change them)
GENERATOR_VERSION = addon_module("versions").GENERATOR_VERSION
PHYSICS_VERSION = addon_module("versions").PHYSICS_VERSION


def library_module(name: str):
    """The library's standard-library-only module `name` ("runtime.fingerprint") for Blender's own
    Python, which has no QuakeScan installed: the installed package `quakescan` (a venv's
    bpy module, or this script shipped in a wheel), else the core/ folder beside
    blender_scripts/ in a checkout, loaded under its import name."""
    import importlib
    import importlib.util

    if "quakescan" not in sys.modules:
        init = REPO / "core" / "__init__.py"
        if not init.is_file():  # shipped in a wheel: site-packages/quakescan/blender_scripts/
            if str(REPO.parent) not in sys.path:
                sys.path.append(str(REPO.parent))
        elif importlib.util.find_spec("quakescan") is None:
            spec = importlib.util.spec_from_file_location("quakescan", init,
                                                          submodule_search_locations=[str(init.parent)])
            module = importlib.util.module_from_spec(spec)
            sys.modules["quakescan"] = module
            spec.loader.exec_module(module)
    return importlib.import_module(f"quakescan.{name}")


def log(msg: str) -> None:
    print(f"[{PROG}] {msg}", file=sys.stderr, flush=True)


def _script_argv(argv):
    """Arguments meant for this script: after '--' when Blender runs it."""
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return argv[1:]


def _positive_int(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def _seed(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed, got {text!r}") from None
    if not 0 <= v < 2 ** 32:
        raise argparse.ArgumentTypeError(f"seed must be in 0..2^32-1, got {v}")
    return v


def parse_args(argv):
    p = argparse.ArgumentParser(prog=PROG, description="Generate labelled pre-/post-event scene bundles "
                                "(scene.json + mesh.ply) of a procedural city with EMS-98 damage.")
    p.add_argument("--set", dest="set_name", required=True, choices=SETS,
                   help="generic European town, L'Aquila-like historic centre, small buildings (garden sheds, "
                   "garages, row houses, small houses), or the buildings of an existing scene bundle (--source)")
    p.add_argument("--source", help="--set bundle: scene bundle folder whose buildings and terrain are used "
                   "(e.g. one imported from CityJSON); the output keeps its origin and CRS")
    p.add_argument("--dataset", required=True, choices=("paper", "mixed"),
                   help="paper: pre + one post scene per grade 3/4/5; mixed: pre + post with mixed grades")
    p.add_argument("--buildings", type=_positive_int, default=None,
                   help="number of buildings (default 112); --set bundle: use a seeded sample of this many of "
                   "the source's buildings (default and values >= their number: all)")
    p.add_argument("--grade-mix", type=_grade_mix, default=None,
                   help="--dataset mixed: exact counts per grade instead of random draws, e.g. "
                   "0:35,3:19,4:32,5:35 (the paper's L'Aquila evaluation set); sets --buildings to their sum")
    p.add_argument("--grades", default=None,
                   help="--set bundle --dataset mixed: a JSON file {\"building ID\": grade, ...} giving the post-event "
                   "grade of each listed building (others stay at 0), as `quakescan inject` asks")
    p.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    p.add_argument("--details", choices=("none", "typical"), default="none",
                   help="roof and facade details (dormers, chimneys, skylights, overhangs, balconies, antennas, "
                   "solar panels, rooftop structures, annexes, terraces): none (clean shells, default) or typical "
                   "(frequencies by typology, addon/citygen.py); --set bundle: roof-top details on the roof faces")
    p.add_argument("--origin", type=_origin, default=None,
                   help="procedural sets: world coordinates 'X,Y[,Z]' of the city's local origin, written as the "
                   "bundles' origin (e.g. 367000,4690000 with --crs EPSG:32633: L'Aquila); default 0,0,0")
    p.add_argument("--crs", default=None,
                   help="procedural sets: the CRS the bundles name, e.g. EPSG:32633 (default: none)")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--force", action="store_true", help="regenerate bundles made with other settings")
    p.add_argument("--streetscape", choices=("none", "typical"), default="none",
                   help="typical: trees, hedges, parked cars and street furniture at the set's density; "
                   "post-event scenes keep the trees and get their own cars (default none)")
    p.add_argument("--damage", choices=("patterns", "physics", "both"), default="patterns",
                   help="how grades 4-5 are made: parametric patterns (default), collapse by rigid-body physics "
                   "(addon/physics.py), or both (a seeded half of those buildings each); lower grades always get "
                   "the patterns")
    p.add_argument("--settle-steps", type=_positive_int, default=250,
                   help="--damage physics|both: frames (1/24 s) a collapse may take to come to rest (default 250)")
    p.add_argument("--jobs", type=_positive_int, default=1,
                   help="processes at once (default 1): scenes are made in parallel, and with --damage "
                   "physics|both the collapses of each scene are shared out first (each depends only on its "
                   "building and its neighbours), so --jobs 2 halves a physics run on 2 cores; same bytes as --jobs 1")
    p.add_argument("--only-scenes", default=None, help=argparse.SUPPRESS)  # a --jobs child's share
    p.add_argument("--collapse-claims", default=None, help=argparse.SUPPRESS)  # a --jobs child simulating collapses
    args = p.parse_args(argv)
    args.argv = list(argv)
    if args.set_name == "bundle" and not args.source:
        p.error("--set bundle needs --source SCENE_DIR")
    if args.grade_mix is not None:
        if args.dataset != "mixed":
            p.error("--grade-mix is only used with --dataset mixed")
        total = sum(args.grade_mix.values())
        if args.buildings is not None and args.buildings != total:
            p.error(f"--buildings {args.buildings} disagrees with --grade-mix, which sums to {total}")
        args.buildings = total
    if args.grades is not None:
        if args.set_name != "bundle" or args.dataset != "mixed":
            p.error("--grades is only used with --set bundle --dataset mixed")
        if args.grade_mix is not None:
            p.error("--grades and --grade-mix both set the grades: give one")
    if args.set_name == "bundle" and (args.origin is not None or args.crs):
        p.error("--origin and --crs are not used with --set bundle: the output keeps the source's")
    if args.set_name != "bundle":
        if args.source:
            p.error("--source is only used with --set bundle")
        if args.buildings is None:
            args.buildings = 112
    return args


def _origin(text):
    try:
        v = [float(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y or X,Y,Z in metres, got {text!r}") from None
    if len(v) not in (2, 3) or not all(abs(c) < 1e8 for c in v):  # NaN fails too
        raise argparse.ArgumentTypeError(f"expected X,Y or X,Y,Z, each finite and within 1e8 m, got {text!r}")
    return tuple(v + [0.0] * (3 - len(v)))


def _grade_mix(text):
    try:
        return library_module("grades").parse_grade_counts(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


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
    citygen = addon_module("citygen")
    if dataset == "paper":
        return [("pre", None)] + [(name, g) for name, g in citygen.PAPER_SCENES]
    if grades is not None:
        return [("pre", None), ("post", grades)]
    if grade_mix:
        return [("pre", None), ("post", citygen.exact_grades(ids, grade_mix, seed))]
    return [("pre", None), ("post", citygen.mixed_grades(ids, seed))]


def generator_info(args, scene_name):
    info = {"script": PROG, "version": GENERATOR_VERSION, "set": args.set_name, "dataset": args.dataset,
            "buildings": args.buildings, "seed": args.seed, "scene": scene_name}
    if getattr(args, "details", "none") != "none":  # absent for "none": older bundles stay resumable
        info["details"] = args.details
    if getattr(args, "grade_mix", None):
        info["grade_mix"] = {str(g): n for g, n in sorted(args.grade_mix.items())}
    if getattr(args, "grades_map", None) is not None:  # absent without --grades: older bundles stay valid
        info["grades"] = {str(b): g for b, g in sorted(args.grades_map.items()) if g}
    if args.set_name == "bundle":
        info["source"] = {"name": Path(args.source).resolve().name, "sha256": getattr(args, "source_sha256", None)}
    if getattr(args, "streetscape", "none") != "none":  # absent with none: older bundles stay valid
        info["streetscape"] = args.streetscape
    if getattr(args, "origin", None) is not None:  # absent by default: older bundles stay valid
        info["origin"] = list(args.origin)
    if getattr(args, "crs", None):
        info["crs"] = args.crs
    if getattr(args, "damage", "patterns") != "patterns":  # absent with patterns: older bundles stay valid
        info["damage"] = args.damage
        info["settle_steps"] = args.settle_steps
        info["physics_version"] = PHYSICS_VERSION
    return info


def bundle_state(folder: Path, info: dict) -> str:
    """'missing', 'done' (same settings) or 'different'.

    The resume rule of quakescan.runtime.fingerprint, with the bundle's own record as the fingerprint: the
    generator record in scene.json (settings, GENERATOR_VERSION, the source bundle's digest)
    must be the one this run would write. The add-on's code is versioned by
    GENERATOR_VERSION, not by QuakeScan's version, so that bundles made by an earlier
    QuakeScan with the same generator stay reusable."""
    fingerprint = library_module("runtime.fingerprint")

    manifest = folder / "scene.json"
    if not manifest.is_file():
        return "missing"
    try:
        gen = json.loads(manifest.read_text()).get("generator")
    except (json.JSONDecodeError, OSError, AttributeError):
        return "different"
    if not isinstance(gen, dict):
        return "different"
    stored, wanted = (fingerprint.make("generate", settings=g, code={"quakescan": None}) for g in (gen, info))
    return "done" if stored.digest == wanted.digest else "different"


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


def bundle_ids(args, manifest) -> list:
    """IDs of the source buildings used: all, or a seeded sample of --buildings of them."""
    import numpy as np
    ids = sorted(int(b["id"]) for b in manifest["buildings"])
    if args.buildings is None or args.buildings >= len(ids):
        return ids
    rng = np.random.default_rng([args.seed, 404])
    return sorted(int(i) for i in rng.choice(ids, size=args.buildings, replace=False))


def build_bundle_pre(args, pre, manifest):
    """Import the source's terrain and chosen buildings into `pre` and prepare them for damage
    (labels, storey splits, coarse interiors; a per-building damage seed from --seed)."""
    import numpy as np

    io_import, scene_tools = addon_module("io_import"), addon_module("scene_tools")
    ids = bundle_ids(args, manifest)
    info = io_import.import_bundle(args.source, pre, building_ids=ids)
    for obj in info["buildings"]:
        io_import.prepare_for_damage(obj)
        obj.qs_building.seed = int(np.random.default_rng([args.seed, 505, obj.qs_building.building_id])
                                   .integers(0, 2 ** 31 - 1))
        obj.qs_building.patterns_json = "[]"
        if args.details != "none":
            scene_tools.add_roof_details(obj)
    return ids, info


def add_streetscape(args, pre, plan):
    """Trees, hedges, furniture and cars around the buildings of collection `pre` (a CityPlan's
    footprints, or the xy extents of an imported bundle's buildings on its terrain).
    Returns (streetscape, footprints, bounds, ground_z, density set) for the post scenes."""
    scene_tools, street_objects = addon_module("scene_tools"), addon_module("street_objects")
    streetscape = addon_module("streetscape")
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
    scape = streetscape.plan_streetscape(footprints, bounds, set_name, args.seed, ground_z)
    street_objects.add_objects(pre, scape)
    log(f"pre: streetscape {len(scape.trees)} trees, {len(scape.hedges)} hedges, {len(scape.cars)} cars, "
        f"{len(scape.furniture)} furniture in {time.perf_counter() - t0:.1f} s")
    return scape, footprints, bounds, ground_z, set_name


def run(args) -> int:
    t_start = time.perf_counter()
    out = Path(args.out)
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
    addon = addon_module()
    citygen, io_export, scene_tools = addon_module("citygen"), addon_module("io_export"), addon_module("scene_tools")
    post_scene = addon_module("post_scene")
    ShellSpec = addon_module("geometry.shell").ShellSpec

    if not hasattr(bpy.types.Object, "qs_building"):
        addon.register()

    origin, crs, manifest, plan = (0.0, 0.0, 0.0), None, None, None
    if args.set_name == "bundle":
        io_import = addon_module("io_import")
        try:
            manifest = io_import.read_bundle(args.source)[0]  # the whole bundle is checked up front
            args.source_sha256 = source_sha256(args.source)
        except (io_import.BundleError, OSError) as e:
            log(f"error: --source: {e}")
            return 2
        ids = bundle_ids(args, manifest)
        origin, crs = manifest.get("origin", [0.0, 0.0, 0.0]), manifest.get("crs")
        if args.grades is not None:
            try:
                args.grades_map = read_grades(args.grades, ids)
            except ValueError as e:
                log(f"error: {e}")
                return 2
    else:
        plan = citygen.city_plan(args.set_name, args.buildings, args.seed, details=args.details)
        ids = [b.id for b in plan.buildings]
    scenes = scene_list(args.dataset, ids, args.seed, args.grade_mix, getattr(args, "grades_map", None))
    todo = []
    for name, grades in scenes:
        info = generator_info(args, name)
        state = bundle_state(out / name, info)
        if state == "done":
            log(f"{name}: complete bundle with the same settings exists, skipped")
            continue
        if state == "different" and not args.force:
            log(f"error: {out / name} holds a bundle made with other settings; use another --out or --force")
            return 1
        todo.append((name, grades, info))
    if args.only_scenes is not None:
        share = set(args.only_scenes.split(","))
        todo = [t for t in todo if t[0] in share]
    if not todo:
        log("nothing to do")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    if args.jobs > 1 and args.collapse_claims is None:
        if collapse_scenes(args, todo):
            code = run_collapse_jobs(args, out)
            if code:
                return code
        if len(todo) > 1:
            return run_jobs(args, todo, len(ids))

    scene = bpy.data.scenes.new("quakescan_generate")
    pre = bpy.data.collections.new("pre")
    scene.collection.children.link(pre)
    created_collections = [pre]
    try:
        t0 = time.perf_counter()
        if plan is None:
            build_bundle_pre(args, pre, manifest)
            n = len(ids)
        else:
            x0, y0, x1, y1 = plan.bounds
            scene_tools.create_terrain_object(pre, x0, y0, x1, y1)
            n = len(plan.buildings)
            step = max(1, n // 10)
            for k, b in enumerate(plan.buildings):
                spec = ShellSpec(**b.shell)
                scene_tools.create_building_object(pre, spec, b.id, location=(b.location[0], b.location[1], 0.0),
                                                   rotation_z=b.rotation, vulnerability_class=b.vulnerability_class,
                                                   seed=b.seed)
                if (k + 1) % step == 0 or k + 1 == n:
                    log(f"pre: built {k + 1}/{n} buildings")
        street = None
        if args.streetscape != "none":
            street = add_streetscape(args, pre, plan)
        pre_objs = scene_tools.scene_objects(pre)
        log(f"pre: {n} buildings built in {time.perf_counter() - t0:.1f} s")
        if args.collapse_claims is not None:
            simulate_collapses(args, collapse_scenes(args, todo), pre_objs, out, Path(args.collapse_claims), street)
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
                damage = dict(damage=args.damage, settle_steps=args.settle_steps, on_fallback=fallback)
                if args.damage != "patterns":  # collapses simulated by --jobs children, where they exist
                    collapse_parts = addon_module("collapse_parts")
                    damage["collapses"] = collapse_parts.loader(parts_folder(out, name), info)
                if street is None:
                    post_scene.make_post_scene(pre_objs, coll, grades=grades, on_progress=progress, **damage)
                else:  # trees, hedges, furniture copied; the pre-event cars replaced by this scene's
                    street_objects, streetscape = addon_module("street_objects"), addon_module("streetscape")
                    post_scene.make_post_scene([o for o in pre_objs if not street_objects.is_car_object(o)], coll,
                                                grades=grades, on_progress=progress, **damage)
                    scape, footprints, bounds, ground_z, set_name = street
                    cars = streetscape.post_event_cars(scape, footprints, bounds, set_name, args.seed, name, ground_z)
                    street_objects.add_objects(coll, streetscape.Streetscape(cars=cars), kinds=("cars",),
                                               suffix=".post")
                objs = scene_tools.scene_objects(coll)
            if plan is None:  # keeps the source's float64 coordinates, origin and CRS
                rep = io_import.export_bundle(tmp, objs, epoch="pre" if name == "pre" else "post",
                                              origin=origin, crs=crs, extra={"generator": info})
            else:
                rep = io_export.export_objects(tmp, objs, epoch="pre" if name == "pre" else "post",
                                               origin=getattr(args, "origin", None) or (0.0, 0.0, 0.0),
                                               crs=getattr(args, "crs", None) or None,
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


def _child_command(argv: list) -> list:
    """This script again with `argv`: in Blender's binary when it runs there, else with the
    Python that has the bpy module."""
    import bpy
    binary = bpy.app.binary_path
    if binary and "python" not in Path(binary).name.lower():
        return [binary, "-b", "--factory-startup", "--python-exit-code", "1", "-P", str(Path(__file__).resolve()),
                "--", *argv]
    return [sys.executable, str(Path(__file__).resolve()), *argv]


def run_jobs(args, todo, buildings: int) -> int:
    """Make `todo`'s scenes in args.jobs child processes at once, each its share; every child
    writes its bundles atomically, so an interrupted run resumes as a single process does."""
    import subprocess
    base = _without_jobs(args.argv)
    shares = job_shares(todo, args.jobs, args.damage, buildings)
    log(f"{len(todo)} scenes in {len(shares)} processes: " + "; ".join(",".join(s) for s in shares))
    procs = [subprocess.Popen(_child_command([*base, "--only-scenes", ",".join(s)])) for s in shares]
    codes = [p.wait() for p in procs]
    failed = [",".join(s) for s, c in zip(shares, codes) if c]
    if failed:
        log(f"error: the process making {'; '.join(failed)} failed (see above); finished scenes are kept")
        return 1
    return 0


def parts_folder(out: Path, scene: str) -> Path:
    """Where --jobs children leave a scene's collapses until the scene is written."""
    return out / f".{scene}.collapses"


def collapse_scenes(args, todo) -> list:
    """The scenes of `todo` with buildings that may collapse by physics, costliest first (a
    grade-5 collapse takes about three times a grade-4 one: every storey falls)."""
    if args.damage == "patterns":
        return []

    def cost(grades):
        gs = list(grades.values()) if isinstance(grades, dict) else [int(grades)]
        return sum(3 if g >= 5 else 1 if g == 4 else 0 for g in gs) / len(gs)
    heavy = [t for t in todo if t[1] is not None and cost(t[1]) > 0]
    return sorted(heavy, key=lambda t: -cost(t[1]))


def simulate_collapses(args, scenes, pre_objs, out: Path, claims: Path, street=None):
    """A --jobs child's share of the collapses: every child walks the same list (scenes
    costliest first, buildings in order) and simulates those it claims first (a file created
    exclusively in `claims`), so the processes stay busy until the last collapse; each is
    written to its scene's parts folder (collapse_parts), those already there are skipped."""
    collapse_parts, scene_tools = addon_module("collapse_parts"), addon_module("scene_tools")
    post_scene = addon_module("post_scene")
    DamageError = scene_tools.DamageError
    if street is not None:
        street_objects = addon_module("street_objects")
        pre_objs = [o for o in pre_objs if not street_objects.is_car_object(o)]
    done = 0
    for name, grades, info in scenes:
        colliders = post_scene.PhysicsColliders(pre_objs, grades, args.damage)
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
                obj, rec = post_scene.collapse_copy(src, colliders, settle_steps=args.settle_steps)
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


def run_collapse_jobs(args, out: Path) -> int:
    """Simulate the collapses of the scenes to make in args.jobs child processes at once
    (simulate_collapses); the scenes are written afterwards from their parts."""
    import subprocess
    claims = out / f".collapse-claims-{os.getpid()}"
    shutil.rmtree(claims, ignore_errors=True)
    claims.mkdir(parents=True)
    try:
        base = _without_jobs(args.argv)
        log(f"collapses in {args.jobs} processes")
        procs = [subprocess.Popen(_child_command([*base, "--collapse-claims", str(claims)])) for _ in range(args.jobs)]
        codes = [p.wait() for p in procs]
    finally:
        shutil.rmtree(claims, ignore_errors=True)
    if any(codes):
        log("error: a process simulating collapses failed (see above); finished collapses are kept")
        return 1
    return 0


def _without_jobs(argv) -> list:
    """The command line without --jobs: each child does its share alone."""
    base, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a == "--jobs":
            skip = True
            continue
        if a.startswith("--jobs="):
            continue
        base.append(a)
    return base


def main(argv=None) -> int:
    """`argv`: the script's own arguments (default: from sys.argv, after '--' in Blender)."""
    args = parse_args(_script_argv(sys.argv) if argv is None else list(argv))
    try:
        return run(args)
    except Exception as e:  # report and fail with a non-zero status (also inside Blender)
        log(f"error: {type(e).__name__}: {e}")
        raise


if __name__ == "__main__":
    code = main()
    if code:
        sys.exit(code)
