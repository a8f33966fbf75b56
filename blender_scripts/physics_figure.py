#!/usr/bin/env python3
"""docs/addon.md's picture of collapse by physics: one building intact, after a grade-4 corner
failure and after a grade-5 total collapse (bpy module; matplotlib renders the meshes).

    .venv/bin/python blender_scripts/physics_figure.py [-o docs/physics_collapse.png]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("-o", "--out", default=str(REPO / "docs" / "physics_collapse.png"))
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    import bpy
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    import addon
    from addon import physics, scene_tools
    from addon.geometry import mesh as gm
    from addon.geometry.shell import ShellSpec, rect_footprint
    if not hasattr(bpy.types.Object, "qs_building"):
        addon.register()
    colours = {gm.ROOF: "#b5533c", gm.WALL: "#d9cbb0", gm.DEBRIS: "#7a7a7a", gm.INTERIOR: "#9fb3c8"}
    spec = ShellSpec(footprint=rect_footprint(12, 9), storeys=3, storey_height=3.0, roof="gable", chimney=None)
    cases = [("intact", None, None), ("grade 4: corner fails", 4, "corner"), ("grade 5: total collapse", 5, "everything")]
    fig = plt.figure(figsize=(15, 5.5))
    for k, (title, grade, mode) in enumerate(cases):
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        coll = bpy.data.collections.new("c")
        bpy.context.scene.collection.children.link(coll)
        obj = scene_tools.create_building_object(coll, spec, 1, seed=7)
        if grade:
            physics.collapse_object(obj, grade, mode=mode)
        bm = scene_tools.read_bmesh(obj)
        v, t, surf, _, _ = gm.arrays(bm)
        bm.free()
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        pc = Poly3DCollection(v[t], facecolors=[colours.get(int(s), "#cccccc") for s in surf],
                              edgecolors="#333333", linewidths=0.15)
        ax.add_collection3d(pc)
        ax.set_xlim(-9, 9)
        ax.set_ylim(-9, 9)
        ax.set_zlim(0, 12)
        ax.set_box_aspect((18, 18, 12))
        ax.view_init(elev=28, azim=125)
        ax.set_axis_off()
        ax.set_title(title, y=0.95)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
