"""Commands on scene bundles: import-cityjson, validate, footprints."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import QuakeScanError
from ..runtime.output_folder import refuse_replacing_inputs
from .reporting import echo


def scene_files(scene_dir) -> list:
    """(path, what) of the files a scene bundle is read from: what no output may replace."""
    import json

    folder = Path(scene_dir)
    mesh = "mesh.ply"
    try:
        mesh = str(json.loads((folder / "scene.json").read_bytes()).get("mesh", mesh))
    except (OSError, ValueError, AttributeError):
        pass  # read_scene names what is wrong with it
    return [(folder / "scene.json", "scene manifest"), (folder / mesh, "scene mesh")]


def cmd_import_cityjson(args) -> int:
    from ..formats.cityjson import import_cityjson
    from ..formats.scene import write_scene

    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise QuakeScanError(f"-o {out}: exists and is not a folder; a scene bundle is a folder (give a new name)")
    refuse_replacing_inputs([out / "scene.json", out / "mesh.ply"], [(args.input, "CityJSON file")],
                            command="import-cityjson")
    if out.is_dir() and any(out.iterdir()) and not (out / "scene.json").is_file():
        raise QuakeScanError(f"-o {out}: a folder that holds other files than a scene bundle; give a new or empty "
                             "folder")
    scene = import_cityjson(args.input, lod=args.lod, terrain_margin=args.buffer, crs=args.crs,
                            material=args.material)
    if args.bbox is not None:
        from ..formats.scene import buildings_in_box, crop_to_buildings

        keep = buildings_in_box(scene, args.bbox)
        if not len(keep):
            raise QuakeScanError(f"--bbox {args.bbox}: no building of {args.input} has its centre inside")
        scene = crop_to_buildings(scene, keep, args.buffer)
    write_scene(scene, args.output)
    b = scene.bounds()
    span = (b[1, :2] - b[0, :2]) / 1e3
    echo(f"{args.output}: {len(scene.buildings)} buildings ({args.material}), {len(scene.faces):,} triangles, "
         f"{span[0]:.2f} × {span[1]:.2f} km, origin {scene.origin.tolist()}, crs {scene.crs}")
    if span.max() > LARGE_SCENE_KM:
        print(f"warning: the scene spans {span[0]:.1f} × {span[1]:.1f} km and a survey flies over all of it; "
              "--bbox X0,Y0,X1,Y1 keeps the buildings of an area (`quakescan scan --dry-run` shows the cost)",
              file=sys.stderr)
    return 0


LARGE_SCENE_KM = 2.0  # a scene wider than this makes every survey a long flight


def _bbox(text: str) -> tuple:
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X0,Y0,X1,Y1 (four numbers), got {text!r}") from None
    if not (x0 < x1 and y0 < y1):
        raise argparse.ArgumentTypeError(f"expected X0 < X1 and Y0 < Y1, got {text!r}")
    return x0, y0, x1, y1


def cmd_validate(args) -> int:
    from ..formats.scene import read_scene

    scene = read_scene(args.scene)
    echo(f"{args.scene}: valid scene bundle ({scene.epoch}), {len(scene.buildings)} buildings, "
         f"{len(scene.faces):,} triangles" + (f", crs {scene.crs}" if scene.crs else ", no crs"))
    return 0


def cmd_footprints(args) -> int:
    from ..formats.footprints import footprints_from_scene, write_footprints
    from ..formats.scene import read_scene

    refuse_replacing_inputs([args.output], scene_files(args.scene), command="footprints")
    fp = footprints_from_scene(read_scene(args.scene))
    write_footprints(fp, args.output)
    print(f"{args.output}: {len(fp)} building footprints (top-view outlines) of {args.scene}"
          + (f" in {fp.crs}" if fp.crs else ""))
    return 0


def add_import_cityjson(sub) -> None:
    from ..formats.scene import MATERIALS

    c = sub.add_parser("import-cityjson", help="convert a CityJSON city model into a scene bundle")
    c.add_argument("input", help="CityJSON file (1.0, 1.1, 2.0)")
    c.add_argument("-o", "--output", required=True, help="scene bundle folder to write")
    c.add_argument("--lod", default=None, help="level of detail to use (default: the highest per building)")
    c.add_argument("--bbox", type=_bbox, default=None, metavar="X0,Y0,X1,Y1",
                   help="keep the buildings whose centre lies in this box (the model's coordinates)")
    c.add_argument("--buffer", type=float, default=20.0,
                   help="terrain around each cluster of buildings, m (default 20; buildings closer than twice "
                   "this share one terrain patch)")
    c.add_argument("--crs", default=None, metavar="EPSG:NNNN",
                   help="CRS of a file whose metadata names none (must agree with the file's when it names one)")
    c.add_argument("--material", choices=MATERIALS, default="masonry",
                   help="material of every imported building (default masonry): damage patterns and the "
                   "scanner's reflectance depend on it")
    c.set_defaults(func=cmd_import_cityjson)


def add_validate(sub) -> None:
    v = sub.add_parser("validate", help="check a scene bundle and report the first problem")
    v.add_argument("scene", help="scene bundle folder (scene.json + mesh.ply)")
    v.set_defaults(func=cmd_validate)


def add_footprints(sub) -> None:
    fo = sub.add_parser("footprints", help="building footprints (top-view outlines) of a scene bundle as GeoJSON, "
                        "to label simulated clouds as real ones are labelled (classify --footprints)")
    fo.add_argument("scene", help="scene bundle folder (the pre-event scene: a cadastre predates the event)")
    fo.add_argument("-o", "--output", required=True, help="GeoJSON file to write")
    fo.set_defaults(func=cmd_footprints)
