"""Operator: export a collection as a scene bundle."""
from __future__ import annotations

import os

import bpy

from . import io_export, scene_tools


class DAMAGE_OT_export_bundle(bpy.types.Operator):
    """Export the active collection's buildings and terrain as a QuakeScan scene bundle (scene.json + mesh.ply)"""
    bl_idname = "damage.export_bundle"
    bl_label = "Export Scene Bundle"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        if context.collection is None:
            cls.poll_message_set("No active collection")
            return False
        return True

    def execute(self, context):
        sc = context.scene.qs_scene
        folder = bpy.path.abspath(sc.export_dir) if sc.export_dir else ""
        if not folder:
            self.report({'ERROR'}, "Set the export folder first (Damage panel > Scene)")
            return {'CANCELLED'}
        if os.path.isfile(folder.rstrip("/\\")):
            self.report({'ERROR'}, f"Export folder {folder!r} is a file")
            return {'CANCELLED'}
        objs = scene_tools.scene_objects(context.collection)
        try:
            rep = io_export.export_objects(folder, objs, epoch=sc.epoch, origin=sc.origin, crs=sc.crs.strip() or None,
                                           depsgraph=context.evaluated_depsgraph_get())
        except (io_export.ExportError, OSError) as e:
            self.report({'ERROR'}, f"Export failed: {e}")
            return {'CANCELLED'}
        self.report({'INFO'}, f"Wrote {rep['buildings']} buildings, {rep['faces']} faces to {folder}")
        return {'FINISHED'}


CLASSES = (DAMAGE_OT_export_bundle,)
