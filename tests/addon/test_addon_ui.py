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
    assert ("prop", "building_id") in calls and ("label", "4: very heavy") in calls
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


# The sidebar at Blender 3.4's default width and UI scale 1 leaves its panels' widgets
# 174 px (docs/damage_panel.png: x 329..503). Text is measured with Blender's own UI font
# (blf, 11 px); PAD is the widget's text margin, ARROW a dropdown's arrow, VALUE room for a
# number field's value ("0.650", "3 m"). The margins are on the safe side: "Reset to Intact"
# fits its half-row in the screenshot but not by this measure.
SIDEBAR_PX, PAD, ARROW, VALUE, ICON, CHECKBOX = 174, 10, 18, 36, 20, 20


class Sized:
    """A UILayout stand-in that knows how wide each item is drawn and what text it shows."""

    def __init__(self, width, out, kind="column", factor=None):
        self.width, self.out, self.kind, self.factor = width, out, kind, factor
        self.children = []
        self.use_property_split = False
        self.use_property_decorate = False

    def _add(self, item):
        self.children.append(item)

    def _child(self, kind, factor=None):
        c = Sized(None, self.out, kind, factor)
        c.use_property_split = self.use_property_split
        self._add(c)
        return c

    def row(self, **k):
        return self._child("row")

    def column(self, **k):
        return self._child("column")

    def box(self, **k):
        return self._child("column")

    def split(self, factor=0.5, **k):
        return self._child("split", factor)

    def prop(self, data, name, text=None, expand=False, **k):
        assert name in data.bl_rna.properties.keys(), f"no property {name!r} on {data}"
        self._add(("prop", data, name, text, expand, self.use_property_split))

    def operator(self, idname, text=None, icon='NONE', **k):
        mod, name = idname.split(".")
        op = getattr(getattr(bpy.ops, mod), name)
        self._add(("operator", op.get_rna_type().name if text is None else text, icon != 'NONE'))

    def label(self, text="", icon='NONE', **k):
        self._add(("label", text, icon != 'NONE'))

    def separator(self, **k):
        pass

    def resolve(self, width):
        """(text, needed px, available px) of everything drawn, widths split as Blender does."""
        self.width = width
        items = self.children
        if self.kind == "row" and items:
            widths = [width / len(items)] * len(items)
        elif self.kind == "split" and items:
            rest = (width * (1 - self.factor)) / max(1, len(items) - 1)
            widths = [width * self.factor] + [rest] * (len(items) - 1)
        else:
            widths = [width] * len(items)
        for item, w in zip(items, widths):
            if isinstance(item, Sized):
                item.resolve(w)
            else:
                self.out.extend(_needs(item, w))


def _px(text):
    import blf

    blf.size(0, 11)
    return blf.dimensions(0, text)[0]


def _needs(item, w):
    kind = item[0]
    if kind == "label":
        _, text, icon = item
        return [(text, _px(text) + PAD + (ICON if icon else 0), w)]
    if kind == "operator":
        _, text, icon = item
        return [(text, _px(text) + PAD + (ICON if icon else 0), w)]
    _, data, name, text, expand, split = item
    p = data.bl_rna.properties[name]
    label = p.name if text is None else text
    if p.type == 'ENUM':
        names = [e.name for e in p.enum_items]
        if expand:  # one button per item across the width
            return [(n, _px(n) + PAD, w / len(names)) for n in names]
        out = [(n, _px(n) + PAD + ARROW, w * (0.6 if split and label else 1.0) - (0 if split or not label
                                                                                 else _px(label + ":") + PAD))
               for n in names]
        return out + ([(label, _px(label) + PAD, 0.4 * w)] if split and label else [])
    if split and label:
        return [(label, _px(label) + PAD, 0.4 * w)]
    if p.type in ('INT', 'FLOAT'):
        return [(label, _px(label) + PAD + VALUE, w)]
    if p.type == 'BOOLEAN':
        return [(label, _px(label) + PAD + CHECKBOX, w)]
    return [(label, _px(label + ":") + PAD + 40, w)] if label else []  # a text field beside its name


def _truncated(panel, context):
    out = []
    root = Sized(SIDEBAR_PX, out)
    panel.draw(type("P", (), {"layout": root})(), context)
    root.resolve(SIDEBAR_PX)
    assert out, "the panel drew nothing"
    return [(text, round(need), round(have)) for text, need, have in out if need > have]


def test_no_label_is_truncated_at_the_default_sidebar_width(blank):
    """Every label, property name, dropdown item (each one of them, not only the one shown)
    and button text fits its share of the default sidebar, for every pattern and with
    details listed; the measure catches the cuts a layout too wide for it makes ("Mate…",
    "Vuln…", "Add Shell Int…", "B: simple stone, u…")."""
    bpy = blank
    from addon import ems98

    ctx = bpy.context
    bpy.ops.damage.add_building(roof='gable', chimney=True, details='typical', details_seed=3)
    obj = ctx.active_object
    problems = []
    for grade in range(6):
        obj.qs_building.grade = grade
        problems += _truncated(bpy.types.DAMAGE_PT_main, ctx)
    for pattern in ems98.PATTERN_NAMES:
        obj.qs_building.pattern = pattern
        problems += _truncated(bpy.types.DAMAGE_PT_damage, ctx)
    problems += _truncated(bpy.types.DAMAGE_PT_scene, ctx)
    assert not problems, problems
    # the measure can fail: it flags two buttons in a row and the long class names, which a sidebar cuts
    row = Sized(SIDEBAR_PX, [], kind="row")
    row.operator("damage.add_interior")
    row.operator("damage.reset_building")
    row.resolve(SIDEBAR_PX)
    assert "Add Shell Interior" in [t for t, need, have in row.out if need > have]
    assert _px(ems98.VULNERABILITY_LABELS["B"]) + PAD + ARROW > SIDEBAR_PX


def _addon_page_section(title):
    from conftest import REPO

    text = (REPO / "docs" / "addon.md").read_text()
    start = text.index(f"## {title}\n")
    end = text.index("\n## ", start + 1)
    return text[start:end]


def test_addon_page_lists_the_registered_operators_and_properties(blank, tmp_path):
    """docs/addon.md's "Scripting the add-on" names every operator with every option, and every property
    of obj.qs_building and scene.qs_scene, no more and no fewer; its example runs."""
    import re

    import addon

    bpy = blank
    section = _addon_page_section("Scripting the add-on")
    documented = {}
    for line in section.splitlines():
        m = re.match(r"\| `bpy\.ops\.damage\.(\w+)\(\)` \|\s*([^|]*?)\s*\|", line)
        if m:
            documented[m.group(1)] = set(re.findall(r"`(\w+)`(?: \(|,|\s*$)", m.group(2).strip()))
    registered = {}
    for cls in addon._classes():
        if "." in getattr(cls, "bl_idname", "") and cls.bl_idname.startswith("damage."):
            name = cls.bl_idname.split(".")[1]
            rna = getattr(bpy.ops.damage, name).get_rna_type()
            registered[name] = {p.identifier for p in rna.properties if p.identifier != "rna_type"}
    assert documented == registered

    def props(owner):
        return {p.identifier for p in owner.fixed_type.properties if p.identifier not in ("rna_type", "name")}

    assert set(re.findall(r"\| `obj\.qs_building\.(\w+)`", section)) == props(
        bpy.types.Object.bl_rna.properties["qs_building"])
    assert set(re.findall(r"\| `scene\.qs_scene\.(\w+)`", section)) == props(
        bpy.types.Scene.bl_rna.properties["qs_scene"])
    # every `params.<pattern>__<parameter>` the page names exists
    for name in re.findall(r"params\.(\w+__\w+)", section):
        assert name in bpy.types.Object.bl_rna.properties["qs_building"].fixed_type.properties["params"] \
            .fixed_type.properties.keys(), name
    example = section.split("```python\n")[1].split("```")[0]
    assert '"/tmp/scene_pre"' in example
    exec(example.replace('"/tmp/scene_pre"', repr(str(tmp_path / "scene_pre"))), {})
    import json

    manifest = json.loads((tmp_path / "scene_pre" / "scene.json").read_text())
    assert manifest["crs"] == "EPSG:32633" and len(manifest["buildings"]) == 2
    assert len(bpy.data.collections["post"].objects) == 2
