"""Operator: make the post-event scene from the pre-event buildings."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty

from . import post_scene, scene_tools


class DAMAGE_OT_make_post_scene(bpy.types.Operator):
    """Copy the buildings and terrain of the active collection into the post-event collection (same IDs) and damage each by its grade"""
    bl_idname = "damage.make_post_scene"
    bl_label = "Make Post-event Scene"
    bl_options = {'REGISTER', 'UNDO'}

    replace: BoolProperty(name="Replace", default=True, description="Empty the post collection first")

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode")
            return False
        if context.collection is None:
            cls.poll_message_set("No active collection")
            return False
        return True

    def execute(self, context):
        src = context.collection
        name = context.scene.qs_scene.post_collection.strip() or "post"
        if src.name == name:
            self.report({'ERROR'}, f"The active collection is the post collection {name!r}: "
                                   "activate the pre-event collection")
            return {'CANCELLED'}
        objs = scene_tools.scene_objects(src)
        if not any(o.qs_building.role == "BUILDING" for o in objs):
            self.report({'ERROR'}, f"Collection {src.name!r} has no building objects (use Assign IDs)")
            return {'CANCELLED'}
        target = scene_tools.ensure_collection(context.scene, name, clear=self.replace)
        try:
            out = post_scene.make_post_scene(objs, target, seed_salt=context.scene.qs_scene.seed)
        except scene_tools.DamageError as e:
            self.report({'ERROR'}, str(e))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Post-event scene {target.name!r}: {len(out)} buildings")
        return {'FINISHED'}


CLASSES = (DAMAGE_OT_make_post_scene,)
