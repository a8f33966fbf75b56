"""Blender objects of a streetscape (addon/streetscape.py): one Terrain-role object per kind
(building ID 0), so they export with the terrain and are copied into post-event scenes.

Objects carry the custom property ``qs_street`` = "trees" | "hedges" | "furniture" |
"cars": the generator copies everything but the cars into a post-event scene and gives it
its own cars (`streetscape.post_event_cars`).
"""
from __future__ import annotations

import bmesh
import numpy as np

from . import io_export, scene_tools
from .geometry import mesh as gm
from .geometry import vegetation as gv

STREET_PROP = "qs_street"
KINDS = ("trees", "hedges", "furniture", "cars")
_BUILDERS = {"trees": gv.add_tree, "hedges": gv.add_hedge, "furniture": gv.add_furniture, "cars": gv.add_car}


def add_objects(collection, scape, kinds=KINDS, suffix=""):
    """One object per non-empty kind of `scape` in `collection`; returns the objects."""
    out = []
    for kind in kinds:
        items = getattr(scape, kind)
        if not items:
            continue
        bm = bmesh.new()
        lab = gm.Labels(bm)
        if kind == "trees":  # crowns mark the layer 1, so every tree object has it
            bm.faces.layers.int.get(gm.POROUS_LAYER) or bm.faces.layers.int.new(gm.POROUS_LAYER)
        for item in items:
            _BUILDERS[kind](bm, lab, item)
        obj = scene_tools.new_mesh_object(collection, f"street_{kind}{suffix}", bm)
        bm.free()
        obj.qs_building.role = "TERRAIN"
        obj[STREET_PROP] = kind
        out.append(obj)
    return out


def is_car_object(obj) -> bool:
    return obj.get(STREET_PROP) == "cars"


def building_footprints(objects):
    """World xy extent rectangles (4, 2) of Building objects (imported bundles have no plan)."""
    out = []
    for obj in objects:
        if obj.type != 'MESH' or obj.qs_building.role != "BUILDING" or not len(obj.data.vertices):
            continue
        co = np.empty(len(obj.data.vertices) * 3, np.float32)
        obj.data.vertices.foreach_get("co", co)
        M = io_export.world_matrix(obj)
        xy = (co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3])[:, :2]
        (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
        out.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
    return out


def terrain_mesh(objects):
    """World vertices and ground triangles (surface 0, or all when unlabelled) of the
    Terrain objects that are not streetscape (None when there is none): a source bundle's
    own trees or cars are no ground to stand on."""
    vs, ts, off = [], [], 0
    for obj in objects:
        if obj.type != 'MESH' or obj.qs_building.role != "TERRAIN" or obj.get(STREET_PROP):
            continue
        me = obj.data
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        M = io_export.world_matrix(obj)
        world = co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]
        me.calc_loop_triangles()
        tris = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", tris)
        tris = tris.reshape(-1, 3).astype(np.int64)
        attr = me.attributes.get(gm.SURFACE_LAYER)
        if attr is not None and attr.domain == 'FACE' and attr.data_type == 'INT':
            surf = np.empty(len(me.polygons), np.int32)
            attr.data.foreach_get("value", surf)
            poly = np.empty(len(me.loop_triangles), np.int32)
            me.loop_triangles.foreach_get("polygon_index", poly)
            tris = tris[surf[poly] == gm.GROUND]
        vs.append(world)
        ts.append(tris + off)
        off += len(world)
    if not vs:
        return None
    return np.concatenate(vs), np.concatenate(ts)


def terrain_bounds(vertices) -> tuple:
    (x0, y0), (x1, y1) = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    return float(x0), float(y0), float(x1), float(y1)

