"""The post-event scene: copies of the buildings (and terrain) damaged by their grades, by the
catalogue's patterns or, for grades 4-5, by rigid-body collapse (physics.py) with the
neighbours and the terrain as they stand when the collapses start (PhysicsColliders).

Above scene_tools (the building objects and their patterns) and physics (one collapse),
which never import it.
"""
from __future__ import annotations

import bpy
import numpy as np

from . import physics
from .scene_tools import DamageError, apply_grade_to_object


DAMAGE_METHODS = ("patterns", "physics", "both")


def uses_physics(obj, grade: int, damage: str) -> bool:
    """Whether `damage` ('patterns', 'physics' or 'both') makes this building's grade by
    physics: only grades 4-5 collapse; 'both' tosses a coin seeded by the building's seed."""
    if damage == "patterns" or grade < 4:
        return False
    if damage == "physics":
        return True
    return bool(np.random.default_rng([int(obj.qs_building.seed) & 0xFFFFFFFF, 14]).random() < 0.5)


def make_post_scene(source_objects, target, grades=None, seed_salt=0, on_progress=None, damage="patterns",
                    settle_steps=None, on_fallback=None, collapses=None):
    """Copy the buildings (and terrain) into collection `target` keeping their IDs, and
    damage each copy by its grade (`grades`: optional {building_id: grade} or one int for
    all). Returns [(object, records)]; raises DamageError naming the building on failure.

    `damage` 'physics' collapses grade-4/5 buildings by rigid-body simulation (physics.py)
    once every copy is in place, with its neighbours and the terrain as colliders; 'both'
    does so for a seeded half of them. A simulation that does not settle is reported through
    `on_fallback(object, message)` and the building gets the patterns instead. Debris lands
    on the terrain and on neighbours as they stand when the collapses start
    (PhysicsColliders), so no collapse depends on another's outcome. `collapses`: optional
    building_id -> None (simulate here) or a function that gives the copy a collapse made
    elsewhere (collapse_copy in another process) and returns its records, or raises
    DamageError for one that did not settle there."""
    if damage not in DAMAGE_METHODS:
        raise DamageError(f"unknown damage method {damage!r}; known: {', '.join(DAMAGE_METHODS)}")
    if damage != "patterns":
        return _make_post_scene_physics(source_objects, target, grades, seed_salt, on_progress, damage,
                                        settle_steps, on_fallback, collapses)
    out = []
    objs = [o for o in source_objects if o.type == 'MESH' and o.qs_building.role in ("BUILDING", "TERRAIN")]
    for k, src in enumerate(objs):
        new = src.copy()
        new.data = src.data.copy()
        new.name = src.name + ".post"
        target.objects.link(new)
        if src.qs_building.role == "BUILDING":
            pg = new.qs_building
            if isinstance(grades, int):
                g = grades
            elif isinstance(grades, dict):
                g = int(grades.get(pg.building_id, pg.grade))
            else:
                g = int(pg.grade)
            pg.grade = g
            pg.patterns_json = "[]"
            records = apply_grade_to_object(new, g, seed_salt)
            out.append((new, records))
        if on_progress:
            on_progress(k + 1, len(objs))
    return out


def _grade_for(pg, grades):
    if isinstance(grades, int):
        return grades
    if isinstance(grades, dict):
        return int(grades.get(pg.building_id, pg.grade))
    return int(pg.grade)


def _make_post_scene_physics(source_objects, target, grades, seed_salt, on_progress, damage, settle_steps,
                             on_fallback, collapses=None):
    objs = [o for o in source_objects if o.type == 'MESH' and o.qs_building.role in ("BUILDING", "TERRAIN")]
    copies = []
    for src in objs:
        new = src.copy()
        new.data = src.data.copy()
        new.name = src.name + ".post"
        target.objects.link(new)
        copies.append(new)
    colliders = PhysicsColliders(objs, grades, damage, seed_salt)
    out = []
    for k, new in enumerate(copies):
        if new.qs_building.role == "BUILDING":
            pg = new.qs_building
            g = _grade_for(pg, grades)
            pg.grade = g
            pg.patterns_json = "[]"
            records = None
            if uses_physics(new, g, damage):
                try:
                    done = collapses(pg.building_id) if collapses is not None else None
                    if done is None:
                        records = [physics.collapse_object(new, g, seed=(pg.seed + seed_salt) if seed_salt else None,
                                                           settle_steps=settle_steps or physics.DEFAULT_SETTLE_STEPS,
                                                           colliders=colliders.of(objs[k]))]
                    else:
                        records = done(new)
                except DamageError as e:
                    if on_fallback:
                        on_fallback(new, str(e))
            if records is None:
                records = apply_grade_to_object(new, g, seed_salt)
            out.append((new, records))
        if on_progress:
            on_progress(k + 1, len(copies))
    return out


def collapse_copy(src, colliders, settle_steps=None):
    """Collapse a copy of building `src` by physics as `_make_post_scene_physics` does in the
    scene `colliders` (a PhysicsColliders) describes: the same grade, seed and colliders, so
    the same bytes. The copy is in no collection (the caller removes it: remove_object);
    returns it and its record, or raises DamageError (nothing left behind)."""
    new = src.copy()
    new.data = src.data.copy()
    new.name = src.name + ".post"
    pg = new.qs_building
    g = _grade_for(pg, colliders.grades)
    pg.grade = g
    pg.patterns_json = "[]"
    salt = colliders.seed_salt
    try:
        rec = physics.collapse_object(new, g, seed=(pg.seed + salt) if salt else None,
                                      settle_steps=settle_steps or physics.DEFAULT_SETTLE_STEPS,
                                      colliders=colliders.of(src))
    except BaseException:
        remove_object(new)
        raise
    return new, rec


def remove_object(obj):
    me = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if me is not None and me.users == 0:
        bpy.data.meshes.remove(me)


class PhysicsColliders:
    """What debris may land on in a scene whose buildings collapse by physics: the terrain
    and the neighbours (within REACH) as they stand when the collapses start: a neighbour
    that collapses by physics too as its standing part (physics.standing_part), any other
    as it was before the event. Computed once per building and scene."""

    REACH = 10.0  # m between xy bounding boxes

    def __init__(self, sources, grades, damage, seed_salt=0):
        self.sources = [o for o in sources if o.type == 'MESH' and o.qs_building.role in ("BUILDING", "TERRAIN")]
        self.grades, self.damage, self.seed_salt = grades, damage, seed_salt
        self._standing = {}

    def grade_of(self, o) -> int:
        return _grade_for(o.qs_building, self.grades)

    def collapses(self, o) -> bool:
        """Whether source building `o` collapses by physics in this scene."""
        return o.qs_building.role == "BUILDING" and uses_physics(o, self.grade_of(o), self.damage)

    def _as_collider(self, o):
        if not self.collapses(o):
            return o
        pg = o.qs_building
        g = self.grade_of(o)
        if o.name not in self._standing:
            seed = (pg.seed + self.seed_salt) if self.seed_salt else None
            self._standing[o.name] = physics.standing_part(o, g, seed)
        return self._standing[o.name]

    def of(self, src) -> list:
        """Colliders for the collapse of building `src` (one of the sources)."""
        near = physics.neighbours(src, [o for o in self.sources if o is not src], self.REACH)
        return [self._as_collider(o) for o in near]
