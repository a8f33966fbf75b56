"""Screenshot of the add-on's "Damage" sidebar for docs/addon.md (needs a GUI Blender).

    Xvfb :99 -screen 0 1600x1350x24 &
    DISPLAY=:99 QS_SHOT_DELAY=24 blender --factory-startup -P blender_scripts/screenshot_panel.py -- docs/damage_panel.png &
    sleep 8; export DISPLAY=:99
    for k in 1 2 3; do xdotool mousemove 700 500; sleep 0.4; xdotool mousemove 1300 250; sleep 0.4
                       xdotool mousemove 1309 250; sleep 0.4; xdotool click 1; sleep 1; done   # the "Damage" tab

Registers the add-on from this repository, adds a building, opens the sidebar, saves a
screenshot of the 3D viewport area after QS_SHOT_DELAY seconds and quits. (docs/addon.md's
picture is that screenshot cropped to its right 540 px and top 1110 px.) Blender takes the
click only after the pointer has moved over the viewport, and not always at the first try:
hence the moves and the repeats.
"""
import os
import sys

import bpy

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
OUT = os.path.abspath(sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else os.path.join(ROOT, "docs",
                                                                                                "damage_panel.png"))


def setup():
    import addon

    bpy.context.preferences.view.show_splash = False

    addon.register()
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    bpy.ops.damage.add_building()
    obj = bpy.context.active_object
    obj.qs_building.grade = 4
    for area in bpy.context.screen.areas:
        if area.type == 'VIEW_3D':
            space = area.spaces.active
            space.show_region_ui = True
            for region in area.regions:
                if region.type == 'UI':
                    try:
                        region.active_panel_category = "Damage"
                    except (AttributeError, TypeError):
                        pass
            region = next(r for r in area.regions if r.type == 'WINDOW')
            with bpy.context.temp_override(area=area, region=region):
                bpy.ops.view3d.view_all()
    return 1.0


def shoot():
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == 'VIEW_3D':
                with bpy.context.temp_override(window=window, area=area):
                    bpy.ops.screen.screenshot_area(filepath=OUT)
                break
    print(f"screenshot: {OUT}")
    bpy.ops.wm.quit_blender()
    return None


bpy.app.timers.register(setup, first_interval=1.0)
# Blender 3.4 cannot switch the sidebar tab from Python (Region.active_panel_category came
# later): the driver script clicks the "Damage" tab with xdotool in between.
bpy.app.timers.register(shoot, first_interval=float(os.environ.get("QS_SHOT_DELAY", "4")))
