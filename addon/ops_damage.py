"""Operators: apply one damage pattern, apply the damage of a grade."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty

from . import ems98, scene_tools
from .ops_building import _is_building
from .props import PATTERN_ITEMS


class DAMAGE_OT_apply_pattern(bpy.types.Operator):
    """Apply an EMS-98 damage pattern to the active building (parameters from the panel)"""
    bl_idname = "damage.apply_pattern"
    bl_label = "Apply Pattern"
    bl_options = {'REGISTER', 'UNDO'}

    pattern: EnumProperty(name="Pattern", items=[("ACTIVE", "From panel", "The pattern chosen in the panel")]
                          + PATTERN_ITEMS, default="ACTIVE")
    randomize: BoolProperty(name="Randomise", default=False,
                            description="Sample parameters from the catalogue ranges instead of the panel values")

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode")
            return False
        if not _is_building(context.active_object):
            cls.poll_message_set("Active object must be a building with an ID (use Assign IDs)")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        pg = obj.qs_building
        name = pg.pattern if self.pattern == "ACTIVE" else self.pattern
        randomize = self.randomize or pg.randomize
        params = None if randomize else pg.pattern_params(name)
        try:
            rec = scene_tools.apply_pattern_to_object(obj, name, params, randomize=randomize)
        except scene_tools.DamageError as e:
            self.report({'ERROR'}, str(e))
            return {'CANCELLED'}
        grade = max(ems98.PATTERNS[name].grades)
        if pg.grade < grade:
            pg.grade = grade
        self.report({'INFO'}, f"{ems98.PATTERNS[name].label}: {rec['params']}")
        return {'FINISHED'}


class DAMAGE_OT_apply_grade(bpy.types.Operator):
    """Damage the selected buildings as their EMS-98 grade requires (patterns chosen by grade, material and vulnerability class)"""
    bl_idname = "damage.apply_grade"
    bl_label = "Apply Damage for Grade"
    bl_options = {'REGISTER', 'UNDO'}

    grade: IntProperty(name="Grade", min=-1, max=5, default=-1, description="-1: each building's own grade")

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode")
            return False
        if not any(_is_building(o) for o in context.selected_objects):
            cls.poll_message_set("Select building objects (with IDs)")
            return False
        return True

    def execute(self, context):
        n, errors = 0, []
        for obj in sorted(context.selected_objects, key=lambda o: o.name):
            if not _is_building(obj):
                continue
            try:
                scene_tools.apply_grade_to_object(obj, None if self.grade < 0 else self.grade)
                n += 1
            except scene_tools.DamageError as e:
                errors.append(str(e))
        if errors and not n:
            self.report({'ERROR'}, errors[0])
            return {'CANCELLED'}
        for e in errors:
            self.report({'WARNING'}, e)
        self.report({'INFO'}, f"Damaged {n} building(s)")
        return {'FINISHED'}


CLASSES = (DAMAGE_OT_apply_pattern, DAMAGE_OT_apply_grade)
