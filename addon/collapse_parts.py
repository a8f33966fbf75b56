"""A building collapsed by physics in one process, handed to the process that writes the scene.

``generate_scenes.py --jobs N`` simulates a scene's collapses in several processes (each
collapse depends only on its building and its neighbours as they stand before the event:
post_scene.PhysicsColliders) and writes the scene in one. A part file (``.npz``) holds one
collapse: the mesh of the collapsed copy (vertex coordinates as Blender stores them, float32,
polygons in their loop order and every face, corner and point attribute; edges are rebuilt
from the polygons) and its record, or the message of a collapse that did not settle. Restored
onto a fresh copy of the building, the mesh exports to the same bytes as the simulated one.

A part names the settings it was made with (``key``, the generator's scene info); one made
with other settings is not used, so a resumed run redoes exactly the missing collapses.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .scene_tools import DamageError

FORMAT = 1
_DOMAINS = {'POINT': "vertices", 'FACE': "polygons", 'CORNER': "loops"}
_KINDS = {'INT': (np.int32, "value"), 'FLOAT': (np.float32, "value"), 'BOOLEAN': (bool, "value"),
          'INT8': (np.int8, "value")}


def _attributes(me):
    """The mesh's own attributes worth carrying: not positions, topology or edge data."""
    out = []
    for a in me.attributes:
        if a.name == "position" or a.name.startswith(".") or a.domain not in _DOMAINS:
            continue
        if a.data_type not in _KINDS:
            raise ValueError(f"mesh attribute {a.name!r} of type {a.data_type} cannot be carried in a part file")
        out.append(a)
    return out


def mesh_state(obj) -> dict:
    """The object's mesh as arrays (exactly as Blender holds them)."""
    me = obj.data
    co = np.empty(len(me.vertices) * 3, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    total = np.empty(len(me.polygons), dtype=np.int32)
    me.polygons.foreach_get("loop_total", total)
    corners = np.empty(len(me.loops), dtype=np.int32)
    me.loops.foreach_get("vertex_index", corners)
    state = {"co": co, "loop_total": total, "corners": corners}
    names = []
    for a in _attributes(me):
        dtype, prop = _KINDS[a.data_type]
        v = np.empty(len(getattr(me, _DOMAINS[a.domain])), dtype=dtype)
        a.data.foreach_get(prop, v)
        state[f"attr{len(names)}"] = v
        names.append([a.name, a.domain, a.data_type])
    state["attributes"] = np.array(json.dumps(names))
    return state


def restore_mesh(obj, state) -> None:
    """Give the object the mesh `state` (mesh_state) describes."""
    me = obj.data
    me.clear_geometry()
    co, total, corners = state["co"], state["loop_total"], state["corners"]
    me.vertices.add(len(co) // 3)
    me.vertices.foreach_set("co", co)
    me.loops.add(len(corners))
    me.loops.foreach_set("vertex_index", corners)
    me.polygons.add(len(total))
    starts = np.zeros(len(total), dtype=np.int32)
    if len(total):
        starts[1:] = np.cumsum(total)[:-1]
    me.polygons.foreach_set("loop_start", starts)
    for k, (name, domain, data_type) in enumerate(json.loads(str(state["attributes"]))):
        a = me.attributes.get(name)
        if a is None or a.domain != domain or a.data_type != data_type:
            if a is not None:
                me.attributes.remove(a)
            a = me.attributes.new(name, data_type, domain)
        a.data.foreach_set(_KINDS[data_type][1], state[f"attr{k}"])
    me.update(calc_edges=True)


def path_for(folder, building_id: int) -> Path:
    return Path(folder) / f"{int(building_id):08d}.npz"


def save(folder, key: dict, building_id: int, obj=None, record=None, error: str | None = None) -> Path:
    """Write one collapse (the collapsed object and its record, or the error of one that did
    not settle) atomically: a part file is complete or absent."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta = {"format": FORMAT, "key": key, "building_id": int(building_id), "record": record, "error": error}
    arrays = mesh_state(obj) if error is None else {}
    final = path_for(folder, building_id)
    tmp = folder / f".{final.stem}.tmp-{os.getpid()}.npz"
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(tmp, final)
    return final


def _meta(path: Path):
    try:
        with np.load(path) as z:
            return json.loads(str(z["meta"]))
    except (OSError, ValueError, KeyError):
        return None


def is_done(folder, key: dict, building_id: int) -> bool:
    """Whether a part made with these settings exists for the building."""
    meta = _meta(path_for(folder, building_id))
    return meta is not None and meta.get("format") == FORMAT and meta.get("key") == key


def loader(folder, key: dict):
    """building_id -> None (no usable part) or a function that gives a fresh copy of the
    building the stored collapse and returns its records (raising DamageError with the stored
    message for one that did not settle): post_scene.make_post_scene's `collapses`."""
    def find(building_id):
        if not is_done(folder, key, building_id):
            return None

        def apply(obj):
            with np.load(path_for(folder, building_id)) as z:
                meta = json.loads(str(z["meta"]))
                if meta["error"] is not None:
                    raise DamageError(meta["error"])
                restore_mesh(obj, {k: z[k] for k in z.files if k != "meta"})
            obj.qs_building.patterns_json = json.dumps([meta["record"]])  # as collapse_object writes it
            return [meta["record"]]
        return apply
    return find
