"""Sidebar panel "Damage" in the 3D viewport."""
from __future__ import annotations

import json

import bpy

from . import ems98
from .props import param_prop_name


# Short material names for one-line summaries in the narrow sidebar.
MATERIAL_SHORT = {ems98.MASONRY: "masonry", ems98.RC: "RC"}
LINE_CHARS = 28  # a label line at the default sidebar width (Blender 3.4, UI scale 1: ~174 px)


def _wrapped(words, first="", chars=LINE_CHARS) -> list:
    """Lines of comma-separated words, none longer than `chars` (labels do not wrap)."""
    lines, cur, n = [], first, 0
    for w in words:
        sep = ", " if n else ""
        if n and len(cur) + len(sep) + len(w) > chars:
            lines.append(cur + ",")
            cur, n = w, 1
        else:
            cur, n = cur + sep + w, n + 1
    return lines + [cur] if n else lines


def _stacked(layout, data, name, text=None):
    """The property's name on a line of its own, the field under it across the full width:
    a dropdown or text field beside its label leaves each half of the narrow sidebar."""
    layout.label(text=text or data.bl_rna.properties[name].name)
    layout.prop(data, name, text="")


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
        layout.row(align=True).prop(pg, "role", expand=True)
        if pg.role != "BUILDING":
            return
        col = layout.column(align=True)
        col.prop(pg, "building_id")
        col.prop(pg, "grade")
        layout.label(text=f"{pg.grade}: {ems98.grade_label(pg.grade)}")
        col = layout.column(align=True)
        _stacked(col, pg, "material")
        _stacked(col, pg, "vulnerability_class")
        col = layout.column(align=True)
        col.prop(pg, "storeys")
        col.prop(pg, "storey_height")
        col.prop(pg, "seed")
        _stacked(layout.column(align=True), pg, "typology")
        kinds = _detail_kinds(pg.shell_json)
        if kinds:
            col = layout.column(align=True)
            for line in _wrapped(kinds, "Details: "):
                col.label(text=line)
        col = layout.column(align=True)
        col.operator("damage.add_interior")
        col.operator("damage.reset_building")


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
        _stacked(layout, pg, "pattern")
        pat = ems98.PATTERNS[pg.pattern]
        layout.label(text=f"grade {'/'.join(map(str, pat.grades))}, "
                          f"{', '.join(MATERIAL_SHORT[m] for m in pat.materials)}")
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
        _stacked(col, sc, "post_collection")
        col.prop(sc, "seed")
        layout.operator("damage.make_post_scene", icon='DUPLICATE')
        col = layout.column(align=True)
        _stacked(col, sc, "origin")
        _stacked(col, sc, "crs")
        layout.row(align=True).prop(sc, "epoch", expand=True)
        _stacked(layout.column(align=True), sc, "export_dir")
        layout.operator("damage.export_bundle", icon='EXPORT')


CLASSES = (DAMAGE_PT_main, DAMAGE_PT_damage, DAMAGE_PT_scene)
