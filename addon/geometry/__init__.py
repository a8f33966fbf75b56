"""Pure bmesh geometry: building shells and EMS-98 damage patterns (no bpy.context)."""
