"""Property groups: per object (building ID, grade, material, ..., pattern parameters) and
per scene (origin, CRS, export folder, post-event collection)."""
from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)
from bpy.types import PropertyGroup

from . import ems98

ROLE_ITEMS = [
    ("NONE", "None", "Not part of the exported scene"),
    ("BUILDING", "Building", "One building: exported with its building ID"),
    ("TERRAIN", "Terrain", "Ground and anything that is not a building (building ID 0)"),
]
MATERIAL_ITEMS = [(m, ems98.MATERIAL_LABELS[m], "") for m in ems98.MATERIALS]
CLASS_ITEMS = [(c, ems98.VULNERABILITY_SHORT[c], f"EMS-98 vulnerability class {ems98.VULNERABILITY_LABELS[c]}")
               for c in ems98.VULNERABILITY_CLASSES]
PATTERN_ITEMS = [(n, p.label, p.description or p.label) for n, p in ems98.PATTERNS.items()]
DETAIL_ITEMS = [("none", "None", "A clean shell"),
                ("typical", "Typical", "Roof and facade details drawn with the city generator's frequencies for "
                 "this kind of building (dormers, chimneys, skylights, overhangs, balconies, antennas, solar "
                 "panels, rooftop structures, terraces)")]
EPOCH_ITEMS = [("pre", "Pre-event", "Intact buildings (grades written as 0)"),
               ("post", "Post-event", "Damaged buildings with their grades")]


def param_prop_name(pattern: str, param: str) -> str:
    return f"{pattern}__{param}"


def _make_param_group():
    """A PropertyGroup with one property per (pattern, parameter), built from ems98."""
    ann = {}
    for pname, pat in ems98.PATTERNS.items():
        specs = dict(pat.params)
        for g in pat.grade_params.values():
            for k, v in g.items():
                specs.setdefault(k, v)
        for k, s in specs.items():
            name = param_prop_name(pname, k)
            desc = f"{s.description} [{s.lo:g}-{s.hi:g}{' ' + s.unit if s.unit else ''}]".strip()
            if s.kind == "int":
                ann[name] = IntProperty(name=k.replace("_", " ").capitalize(), description=desc,
                                        default=int(s.default), min=0, soft_min=int(s.lo), soft_max=int(max(s.hi, s.lo)))
            else:
                ann[name] = FloatProperty(name=k.replace("_", " ").capitalize(), description=desc,
                                          default=float(s.default), min=0.0, soft_min=float(s.lo),
                                          soft_max=float(s.hi), precision=3)
    return type("DAMAGE_PG_pattern_params", (PropertyGroup,), {"__annotations__": ann})


DAMAGE_PG_pattern_params = _make_param_group()


class DAMAGE_PG_building(PropertyGroup):
    role: EnumProperty(name="Role", items=ROLE_ITEMS, default="NONE")
    building_id: IntProperty(name="Building ID", min=0, default=0,
                             description="Shared by the pre- and post-event versions of a building (> 0)")
    grade: IntProperty(name="EMS-98 grade", min=0, max=5, default=0,
                       description="EMS-98 damage grade: " + ", ".join(f"{g} {n}" for g, n in ems98.GRADE_NAMES.items()))
    material: EnumProperty(name="Material", items=MATERIAL_ITEMS, default=ems98.MASONRY)
    vulnerability_class: EnumProperty(name="Vulnerability", items=CLASS_ITEMS, default="B")
    storeys: IntProperty(name="Storeys", min=1, max=80, default=2)
    storey_height: FloatProperty(name="Storey height", min=2.0, max=8.0, default=3.0, unit='LENGTH')
    typology: StringProperty(name="Typology", default="generic")
    seed: IntProperty(name="Seed", min=0, default=0, description="Seed of this building's damage patterns")
    pattern: EnumProperty(name="Pattern", items=PATTERN_ITEMS, default="roof_holes")
    randomize: BoolProperty(name="Randomise parameters", default=False,
                            description="Sample the parameters from the catalogue ranges (seeded)")
    params: PointerProperty(type=DAMAGE_PG_pattern_params)
    patterns_json: StringProperty(name="Applied patterns", default="[]",
                                  description="Patterns applied so far, with their realised parameters (JSON)")
    shell_json: StringProperty(name="Shell", default="",
                               description="How the add-on built this shell (JSON); empty for user meshes")

    def pattern_params(self, pattern: str) -> dict:
        """The UI parameters of `pattern` as a dict (names as in ems98)."""
        out = {}
        prefix = pattern + "__"
        for key in self.params.bl_rna.properties.keys():
            if key.startswith(prefix):
                out[key[len(prefix):]] = getattr(self.params, key)
        return out


class DAMAGE_PG_scene(PropertyGroup):
    origin: StringProperty(name="Origin", default="0, 0, 0",
                           description="World coordinates of Blender's origin, 'x, y, z' (kept in double precision)")
    crs: StringProperty(name="CRS", default="", description="e.g. EPSG:32633; empty = unknown")
    export_dir: StringProperty(name="Folder", default="", subtype='DIR_PATH',
                               description="Scene bundle folder (scene.json + mesh.ply)")
    epoch: EnumProperty(name="Epoch", items=EPOCH_ITEMS, default="pre")
    post_collection: StringProperty(name="Post collection", default="post",
                                    description="Collection that 'Make post-event scene' fills")
    seed: IntProperty(name="Scene seed", min=0, default=0)


CLASSES = (DAMAGE_PG_pattern_params, DAMAGE_PG_building, DAMAGE_PG_scene)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.qs_building = PointerProperty(type=DAMAGE_PG_building)
    bpy.types.Scene.qs_scene = PointerProperty(type=DAMAGE_PG_scene)


def unregister():
    del bpy.types.Scene.qs_scene
    del bpy.types.Object.qs_building
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
