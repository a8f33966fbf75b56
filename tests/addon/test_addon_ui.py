"""The sidebar panels draw without errors: every property and operator they show exists."""
import pytest

bpy = pytest.importorskip("bpy")


class Layout:
    """Stands in for UILayout; checks what a panel asks for."""

    def __init__(self, calls):
        self.calls = calls

    def _child(self, *a, **k):
        return Layout(self.calls)

    row = column = box = split = _child

    def prop(self, data, name, **k):
        assert name in data.bl_rna.properties.keys(), f"no property {name!r} on {data}"
        self.calls.append(("prop", name))

    def operator(self, idname, **k):
        mod, name = idname.split(".")
        assert name in dir(getattr(bpy.ops, mod)), f"no operator {idname}"
        self.calls.append(("operator", idname))

    def label(self, **k):
        self.calls.append(("label", k.get("text")))

    def separator(self, **k):
        pass


def _draw(panel, context):
    calls = []
    fake = type("P", (), {"layout": Layout(calls)})()
    panel.draw(fake, context)
    return calls


def test_panels_registered_in_sidebar(bpy_registered):
    for name in ("DAMAGE_PT_main", "DAMAGE_PT_damage", "DAMAGE_PT_scene"):
        cls = getattr(bpy.types, name)
        assert cls.bl_space_type == 'VIEW_3D' and cls.bl_region_type == 'UI' and cls.bl_category == "Damage"


def test_panels_draw(blank):
    bpy = blank
    from addon import ems98
    ctx = bpy.context
    calls = _draw(bpy.types.DAMAGE_PT_main, ctx)
    assert ("label", "Select a mesh object") in calls
    bpy.ops.damage.add_building(roof='gable', chimney=True)
    obj = ctx.active_object
    obj.qs_building.grade = 4
    calls = _draw(bpy.types.DAMAGE_PT_main, ctx)
    assert ("prop", "building_id") in calls and ("label", "EMS-98 4: very heavy") in calls
    assert bpy.types.DAMAGE_PT_damage.poll(ctx)
    for pattern in ems98.PATTERN_NAMES:
        obj.qs_building.pattern = pattern
        calls = _draw(bpy.types.DAMAGE_PT_damage, ctx)
        shown = {c[1] for c in calls if c[0] == "prop"}
        assert {f"{pattern}__{k}" for k in ems98.PATTERNS[pattern].params} <= shown
    bpy.ops.damage.apply_pattern(pattern="roof_holes")
    assert ("label", "roof_holes") in _draw(bpy.types.DAMAGE_PT_damage, ctx)
    calls = _draw(bpy.types.DAMAGE_PT_scene, ctx)
    assert ("operator", "damage.export_bundle") in calls and ("operator", "damage.make_post_scene") in calls
