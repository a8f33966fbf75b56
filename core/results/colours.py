"""The grade colours every output shares: the PNG and HTML maps, the graded LAS, the QGIS style.
"""
from __future__ import annotations

# Map / LAS colours (hex RGB). Green → yellow → orange → red with the grade; grades 1 and 2
# (geometrically "no damage" at UAV resolution) get the greens between, should a model predict them.
GRADE_COLOURS = {0: "#1a9641", 1: "#a6d96a", 2: "#d9ef8b", 3: "#ffd700", 4: "#fd8d3c", 5: "#d7191c"}
NOT_ASSESSABLE_COLOUR = "#8c8c8c"  # grey
BACKGROUND_COLOUR = "#d9d9d9"  # light grey: points that belong to no building (map scatter, LAS)


def colour_of(grade: int | None) -> str:
    """Hex colour of a grade; grey for None (not assessable)."""
    if grade is None:
        return NOT_ASSESSABLE_COLOUR
    return GRADE_COLOURS.get(int(grade), NOT_ASSESSABLE_COLOUR)


def rgb8(hex_colour: str) -> tuple[int, int, int]:
    """(red, green, blue) 0-255 of a hex colour "#rrggbb"."""
    h = hex_colour.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


__all__ = ["BACKGROUND_COLOUR", "GRADE_COLOURS", "NOT_ASSESSABLE_COLOUR", "colour_of", "rgb8"]
