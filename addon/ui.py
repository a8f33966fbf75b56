"""Sidebar panel "Damage" in the 3D viewport."""
from __future__ import annotations

import json

import bpy

from . import ems98
from .props import param_prop_name


def _detail_kinds(shell_json: str) -> list:
    """Kinds of the roof and facade details of an add-on shell (none for user meshes)."""
    try:
        found = json.loads(shell_json).get("details", []) if shell_json else []
    except (json.JSONDecodeError, AttributeError):
        return []
    return sorted({d.get("kind", "?") for d in found})


class DAMAGE_PT_main(bpy.types.Panel):
    bl_idname = "DAMAGE_PT_main"
    bl_label = "Building"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Damage"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        layout.operator("damage.add_building", icon='HOME')
        layout.operator("damage.assign_ids", icon='LINENUMBERS_ON')
        if obj is None or obj.type != 'MESH':
            layout.label(text="Select a mesh object", icon='INFO')
            return
        pg = obj.qs_building
        col = layout.column(align=True)
        col.prop(pg, "role")
        if pg.role != "BUILDING":
            return
        col.prop(pg, "building_id")
        col.prop(pg, "grade")
        col.label(text=f"EMS-98 {pg.grade}: {ems98.grade_label(pg.grade)}")
        col.prop(pg, "material")
        col.prop(pg, "vulnerability_class")
        col.prop(pg, "storeys")
        col.prop(pg, "storey_height")
        col.prop(pg, "typology")
        col.prop(pg, "seed")
        kinds = _detail_kinds(pg.shell_json)
        if kinds:
            col.label(text="Details: " + ", ".join(kinds))
        row = layout.row(align=True)
        row.operator("damage.add_interior")
        row.operator("damage.reset_building")


class DAMAGE_PT_damage(bpy.types.Panel):
    bl_idname = "DAMAGE_PT_damage"
    bl_label = "Damage Patterns"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Damage"
    bl_parent_id = "DAMAGE_PT_main"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH' and obj.qs_building.role == "BUILDING"

    def draw(self, context):
        layout = self.layout
        pg = context.active_object.qs_building
        layout.prop(pg, "pattern")
        pat = ems98.PATTERNS[pg.pattern]
        layout.label(text=f"grade {'/'.join(map(str, pat.grades))}, "
                          f"{', '.join(ems98.MATERIAL_LABELS[m] for m in pat.materials)}")
        col = layout.column(align=True)
        names = list(pat.params)
        for g in pat.grade_params.values():
            names += [k for k in g if k not in names]
        for k in names:
            col.prop(pg.params, param_prop_name(pg.pattern, k))
        layout.prop(pg, "randomize")
        layout.operator("damage.apply_pattern", icon='MOD_EXPLODE')
        layout.separator()
        layout.operator("damage.apply_grade", icon='ERROR')
        layout.operator("damage.collapse_by_physics", icon='PHYSICS')
        if len(pg.patterns_json) > 2:
            box = layout.box()
            box.label(text="Applied:")
            for rec in json.loads(pg.patterns_json):
                box.label(text=rec.get("name", "?"))


class DAMAGE_PT_scene(bpy.types.Panel):
    bl_idname = "DAMAGE_PT_scene"
    bl_label = "Scene and Export"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Damage"
    bl_parent_id = "DAMAGE_PT_main"

    def draw(self, context):
        layout = self.layout
        sc = context.scene.qs_scene
        col = layout.column(align=True)
        col.prop(sc, "post_collection")
        col.prop(sc, "seed")
        layout.operator("damage.make_post_scene", icon='DUPLICATE')
        col = layout.column(align=True)
        col.prop(sc, "origin")
        col.prop(sc, "crs")
        col.prop(sc, "epoch")
        col.prop(sc, "export_dir")
        layout.operator("damage.export_bundle", icon='EXPORT')


CLASSES = (DAMAGE_PT_main, DAMAGE_PT_damage, DAMAGE_PT_scene)
