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
frequencies by typology in addon/building_details.py); default none.

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

--spec FILE.json gives the whole job as one JSON document instead of the options above, its
keys the fields of addon/generation_spec.py `GenerationSpec` (one an option: set_name,
dataset, buildings, seed, out, source, grade_mix, grades, details, streetscape, origin, crs,
damage, settle_steps, force, jobs), as `quakescan.generator.generate` writes it. This script
only reads the job and hands it to addon/generation.py, which makes it.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def addon_module(name: str = ""):
    """The add-on, or its submodule `name` ("generation"): the addon/ folder beside
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


# the job's fields and choices: standard library only, so read before Blender's modules load
generation_spec = addon_module("generation_spec")
# a --jobs child's share, given beside --spec (argparse.SUPPRESS: not for users)
CHILD_OPTIONS = ("--only-scenes", "--collapse-claims")


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
    """The checked job of the command line, and a --jobs child's share ({"only_scenes": ...,
    "collapse_claims": ...}); a refused one exits 2 with the reason, as argparse does."""
    p = argparse.ArgumentParser(prog=generation_spec.PROG, description="Generate labelled pre-/post-event scene "
                                "bundles (scene.json + mesh.ply) of a procedural city with EMS-98 damage.")
    p.add_argument("--spec", default=None, help="the whole job as a JSON file (addon/generation_spec.py: its keys "
                   "the fields of GenerationSpec), instead of the options below")
    p.add_argument("--set", dest="set_name", choices=generation_spec.SETS,
                   help="generic European town, L'Aquila-like historic centre, small buildings (garden sheds, "
                   "garages, row houses, small houses), or the buildings of an existing scene bundle (--source)")
    p.add_argument("--source", help="--set bundle: scene bundle folder whose buildings and terrain are used "
                   "(e.g. one imported from CityJSON); the output keeps its origin and CRS")
    p.add_argument("--dataset", choices=generation_spec.DATASETS,
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
    p.add_argument("--details", choices=generation_spec.DETAILS, default="none",
                   help="roof and facade details (dormers, chimneys, skylights, overhangs, balconies, antennas, "
                   "solar panels, rooftop structures, annexes, terraces): none (clean shells, default) or typical "
                   "(frequencies by typology, addon/building_details.py); --set bundle: roof-top details on the roof faces")
    p.add_argument("--origin", type=_origin, default=None,
                   help="procedural sets: world coordinates 'X,Y[,Z]' of the city's local origin, written as the "
                   "bundles' origin (e.g. 367000,4690000 with --crs EPSG:32633: L'Aquila); default 0,0,0")
    p.add_argument("--crs", default=None,
                   help="procedural sets: the CRS the bundles name, e.g. EPSG:32633 (default: none)")
    p.add_argument("--out", help="output folder (created)")
    p.add_argument("--force", action="store_true", help="regenerate bundles made with other settings")
    p.add_argument("--streetscape", choices=generation_spec.STREETSCAPES, default="none",
                   help="typical: trees, hedges, parked cars and street furniture at the set's density; "
                   "post-event scenes keep the trees and get their own cars (default none)")
    p.add_argument("--damage", choices=generation_spec.DAMAGES, default="patterns",
                   help="how grades 4-5 are made: parametric patterns (default), collapse by rigid-body physics "
                   "(addon/physics.py), or both (a seeded half of those buildings each); lower grades always get "
                   "the patterns")
    p.add_argument("--settle-steps", type=_positive_int, default=250,
                   help="--damage physics|both: frames (1/24 s) a collapse may take to come to rest (default 250)")
    p.add_argument("--jobs", type=_positive_int, default=1,
                   help="processes at once (default 1): scenes are made in parallel, and with --damage "
                   "physics|both the collapses of each scene are shared out first (each depends only on its "
                   "building and its neighbours), so --jobs 2 halves a physics run on 2 cores; same bytes as --jobs 1")
    p.add_argument("--only-scenes", default=None, help=argparse.SUPPRESS)
    p.add_argument("--collapse-claims", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    share = {"only_scenes": args.only_scenes, "collapse_claims": args.collapse_claims}
    if args.spec is not None:
        given = sorted({a.split("=")[0] for a in argv if a.startswith("--")} - {"--spec", *CHILD_OPTIONS})
        if given:
            p.error(f"--spec gives the whole job: {', '.join(given)} cannot come with it")
        try:
            return generation_spec.GenerationSpec.read(args.spec), share
        except generation_spec.SpecError as e:
            p.error(str(e))
    missing = [f"--{k.replace('_', '-')}" if k != "set_name" else "--set"
               for k in ("set_name", "dataset", "out") if getattr(args, k) is None]
    if missing:
        p.error(f"the following arguments are required: {', '.join(missing)}")
    try:
        spec = generation_spec.GenerationSpec(**{f: getattr(args, f) for f in generation_spec.FIELDS})
        return spec.checked(), share
    except generation_spec.SpecError as e:
        p.error(str(e))


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


def main(argv=None) -> int:
    """`argv`: the script's own arguments (default: from sys.argv, after '--' in Blender)."""
    spec, share = parse_args(_script_argv(sys.argv) if argv is None else list(argv))
    try:
        return addon_module("generation").run(spec, bundle_state=bundle_state, script=Path(__file__).resolve(),
                                              **share)
    except Exception as e:  # report and fail with a non-zero status (also inside Blender)
        generation_spec.log(f"error: {type(e).__name__}: {e}")
        raise


if __name__ == "__main__":
    code = main()
    if code:
        sys.exit(code)
