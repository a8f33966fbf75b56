"""Operators: apply one damage pattern, apply the damage of a grade, collapse by physics."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty

from . import ems98, post_scene, scene_tools
from .ops_building import _is_building
from .props import PATTERN_ITEMS


# neighbours within this distance of a collapsing building are its passive colliders
COLLIDER_REACH_M = 10.0


def _active_building_poll(cls, context) -> bool:
    """Object mode and an active add-on building: what the single-building operators need."""
    if context.mode != 'OBJECT':
        cls.poll_message_set("Switch to Object Mode")
        return False
    if not _is_building(context.active_object):
        cls.poll_message_set("Active object must be a building with an ID (use Assign IDs)")
        return False
    return True


def _collapse(context, obj, grade: int, settle_steps: int, seed: int | None = None) -> dict:
    """Collapse `obj` by physics with the scene's other objects near it as colliders."""
    from . import physics

    others = [o for o in context.scene.objects if o is not obj]
    return physics.collapse_object(obj, grade, seed=seed, settle_steps=settle_steps,
                                   colliders=physics.neighbours(obj, others, COLLIDER_REACH_M))


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
        return _active_building_poll(cls, context)

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
    method: EnumProperty(name="Method", default="patterns", items=[
        ("patterns", "Patterns", "Parametric damage patterns chosen by grade, material and vulnerability class"),
        ("physics", "Physics", "Grades 4-5 collapse by rigid-body simulation (Collapse by Physics); lower grades "
         "get the patterns")])
    settle_steps: IntProperty(name="Settle steps", min=10, max=5000, default=250,
                              description="Physics: frames (1/24 s) the simulation may run before it must rest")

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
                g = obj.qs_building.grade if self.grade < 0 else self.grade
                if post_scene.uses_physics(obj, g, self.method):
                    _collapse(context, obj, g, self.settle_steps)
                else:
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


class DAMAGE_OT_collapse_by_physics(bpy.types.Operator):
    """Collapse the active building as EMS-98 grade 4 or 5 by rigid-body simulation: its elements fracture where the grade removes support and settle under gravity; neighbours and terrain are colliders"""
    bl_idname = "damage.collapse_by_physics"
    bl_label = "Collapse by Physics"
    bl_options = {'REGISTER', 'UNDO'}

    grade: IntProperty(name="Grade", min=-1, max=5, default=-1,
                       description="4 or 5; -1: the building's own grade (raised to 4 when lower)")
    seed: IntProperty(name="Seed", min=-1, default=-1, description="-1: the building's seed")
    settle_steps: IntProperty(name="Settle steps", min=10, max=5000, default=250,
                              description="Frames (1/24 s) the simulation may run before it must rest")

    @classmethod
    def poll(cls, context):
        return _active_building_poll(cls, context)

    def execute(self, context):
        obj = context.active_object
        g = self.grade if self.grade >= 0 else max(4, obj.qs_building.grade)
        try:
            rec = _collapse(context, obj, g, self.settle_steps, seed=None if self.seed < 0 else self.seed)
        except scene_tools.DamageError as e:
            self.report({'ERROR'}, str(e))
            return {'CANCELLED'}
        p = rec["params"]
        self.report({'INFO'}, f"{p['mode']}: {p['shards']} shards, {p['debris_shards']} debris, "
                              f"{p['frames']} frames{'' if p['settled'] else ' (some still creeping)'}")
        return {'FINISHED'}


CLASSES = (DAMAGE_OT_apply_pattern, DAMAGE_OT_apply_grade, DAMAGE_OT_collapse_by_physics)
