"""QuakeScan damage modelling: EMS-98 damage patterns, building IDs and grades, and export of
labelled scene bundles (scene.json + mesh.ply) for virtual UAV scanning."""

bl_info = {
    "name": "QuakeScan Damage",
    "author": "QuakeScan project",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "View3D > Sidebar > Damage",
    "description": "EMS-98 damage patterns, building IDs/grades and scene-bundle export",
    "category": "Object",
}


def _classes():
    from . import ops_building, ops_damage, ops_export, ops_scene, ui
    return (*ops_building.CLASSES, *ops_damage.CLASSES, *ops_scene.CLASSES, *ops_export.CLASSES, *ui.CLASSES)


def _require_numpy():
    try:
        import numpy  # noqa: F401
    except ImportError:
        raise ImportError("QuakeScan Damage needs numpy in Blender's Python: Blender's own builds bundle it; "
                          "for Debian's blender package install python3-numpy") from None


def register():
    _require_numpy()
    import bpy
    from . import props
    props.register()
    for c in _classes():
        bpy.utils.register_class(c)


def unregister():
    import bpy
    from . import props
    for c in reversed(_classes()):
        bpy.utils.unregister_class(c)
    props.unregister()
