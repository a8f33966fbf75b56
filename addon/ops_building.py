"""Operators: building IDs, procedural shells, interiors, reset."""
from __future__ import annotations

import json

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty

from . import building_details, ems98, scene_tools
from .geometry.details import DetailError
from .geometry.shell import ROOF_TYPES, ShellSpec, rect_footprint
from .props import CLASS_ITEMS, DETAIL_ITEMS, MATERIAL_ITEMS


def _is_building(obj):
    return obj is not None and obj.type == 'MESH' and obj.qs_building.role == "BUILDING" \
        and obj.qs_building.building_id > 0


class DAMAGE_OT_assign_ids(bpy.types.Operator):
    """Make the selected meshes buildings with consecutive IDs and label their faces"""
    bl_idname = "damage.assign_ids"
    bl_label = "Assign Building IDs"
    bl_options = {'REGISTER', 'UNDO'}

    start_id: IntProperty(name="First ID", min=0, default=0,
                          description="0: continue after the highest ID in the file")
    storeys: IntProperty(name="Storeys", min=0, max=80, default=0,
                         description="0: estimate from each object's height (about 3 m a storey)")

    @classmethod
    def poll(cls, context):
        if not any(o.type == 'MESH' for o in context.selected_objects):
            cls.poll_message_set("Select one or more mesh objects")
            return False
        return True

    def execute(self, context):
        existing = [o.qs_building.building_id for o in bpy.data.objects
                    if o.qs_building.role == "BUILDING" and not o.select_get()]
        try:
            ids = scene_tools.assign_ids(context.selected_objects, self.start_id or None, existing, self.storeys)
        except scene_tools.DamageError as e:
            self.report({'ERROR'}, str(e))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Assigned building IDs {ids[0]}..{ids[-1]}")
        return {'FINISHED'}


class DAMAGE_OT_add_building(bpy.types.Operator):
    """Add a procedural building shell (walls, slabs, inner walls, roof) at the 3D cursor"""
    bl_idname = "damage.add_building"
    bl_label = "Add Building"
    bl_options = {'REGISTER', 'UNDO'}

    length: FloatProperty(name="Length", min=3.0, default=12.0, unit='LENGTH')
    width: FloatProperty(name="Width", min=3.0, default=9.0, unit='LENGTH')
    storeys: IntProperty(name="Storeys", min=1, max=60, default=3)
    storey_height: FloatProperty(name="Storey height", min=2.0, max=8.0, default=3.0, unit='LENGTH')
    roof: EnumProperty(name="Roof", items=[(r, r.capitalize(), "") for r in ROOF_TYPES], default="gable")
    roof_pitch: FloatProperty(name="Roof pitch", min=5.0, max=60.0, default=30.0)
    parapet_height: FloatProperty(name="Parapet", min=0.0, max=2.0, default=0.0, unit='LENGTH')
    chimney: BoolProperty(name="Chimney", default=False)
    material: EnumProperty(name="Material", items=MATERIAL_ITEMS, default=ems98.MASONRY)
    vulnerability_class: EnumProperty(name="Vulnerability", items=CLASS_ITEMS, default="B")
    details: EnumProperty(name="Details", items=DETAIL_ITEMS, default="none")
    details_seed: IntProperty(name="Details seed", min=0, default=0,
                              description="Seed of the details (0: the building ID)")

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode")
            return False
        return True

    def execute(self, context):
        spec = ShellSpec(rect_footprint(self.length, self.width), storeys=self.storeys,
                         storey_height=self.storey_height, roof=self.roof, roof_pitch=self.roof_pitch,
                         parapet_height=self.parapet_height if self.roof == "flat" else 0.0,
                         chimney=[self.length * 0.2, self.width * 0.15, 0.6, 1.2]
                         if self.chimney and self.roof != "flat" else None,
                         bay_width=4.5 if self.material == ems98.RC else 0.0, material=self.material)
        existing = [o.qs_building.building_id for o in bpy.data.objects if o.qs_building.role == "BUILDING"]
        bid = max(existing, default=0) + 1
        if self.details != "none":
            spec.typology = building_details.typology_for(spec.material, spec.storeys)
            spec.details = building_details.draw_details(json.loads(spec.to_json()), spec.typology,
                                                         self.details_seed or bid)
        try:
            obj = scene_tools.create_building_object(context.collection, spec, bid,
                                                     location=context.scene.cursor.location,
                                                     vulnerability_class=self.vulnerability_class, seed=bid)
        except DetailError as e:
            self.report({'ERROR'}, f"Details do not fit this building: {e}")
            return {'CANCELLED'}
        for o in context.selected_objects:
            o.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        self.report({'INFO'}, f"Added building {bid}")
        return {'FINISHED'}


class DAMAGE_OT_add_interior(bpy.types.Operator):
    """Add floor slabs and coarse inner walls so that holes reveal an interior"""
    bl_idname = "damage.add_interior"
    bl_label = "Add Shell Interior"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not _is_building(context.active_object):
            cls.poll_message_set("Active object must be a building with an ID")
            return False
        return context.mode == 'OBJECT'

    def execute(self, context):
        try:
            n = scene_tools.add_interior(context.active_object)
        except scene_tools.DamageError as e:
            self.report({'ERROR'}, str(e))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Added {n} interior faces")
        return {'FINISHED'}


class DAMAGE_OT_reset_building(bpy.types.Operator):
    """Rebuild the selected add-on buildings intact (drops applied patterns)"""
    bl_idname = "damage.reset_building"
    bl_label = "Reset to Intact"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not any(_is_building(o) for o in context.selected_objects):
            cls.poll_message_set("Select building objects")
            return False
        return context.mode == 'OBJECT'

    def execute(self, context):
        done, errors = 0, []
        for o in context.selected_objects:
            if not _is_building(o):
                continue
            try:
                scene_tools.reset_building(o)
                done += 1
            except scene_tools.DamageError as e:
                errors.append(str(e))
        if errors and not done:
            self.report({'ERROR'}, errors[0])
            return {'CANCELLED'}
        for e in errors:
            self.report({'WARNING'}, e)
        self.report({'INFO'}, f"Reset {done} building(s)")
        return {'FINISHED'}


CLASSES = (DAMAGE_OT_assign_ids, DAMAGE_OT_add_building, DAMAGE_OT_add_interior, DAMAGE_OT_reset_building)
