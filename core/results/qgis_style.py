"""`buildings.qml`: the QGIS layer style of `buildings.geojson`, written beside it.

QGIS applies a `.qml` of the same base name when it loads a layer, so the GeoJSON opens
with the map's colours: a categorised renderer on `predicted_grade`, one category per
EMS-98 grade named as on the maps (`quakescan.grades`), and the catch-all category (empty
value, which takes the null grade of a building not assessable) in grey; building IDs as
labels.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

from ..grades import GRADE_NAMES, long_label
from ..runtime.atomic import write_text
from .building_result import NOT_ASSESSABLE
from .colours import NOT_ASSESSABLE_COLOUR, colour_of, rgb8

GRADE_FIELD = "predicted_grade"
LABEL_FIELD = "building_id"
OUTLINE = "#333333"


def _qgis_colour(hex_colour: str) -> str:
    return ",".join(str(v) for v in rgb8(hex_colour)) + ",255"


def _fill_symbol(parent, name: str, hex_colour: str):
    sym = ET.SubElement(parent, "symbol", {"type": "fill", "name": name, "alpha": "1", "clip_to_extent": "1",
                                           "force_rhr": "0"})
    layer = ET.SubElement(sym, "layer", {"class": "SimpleFill", "enabled": "1", "locked": "0", "pass": "0"})
    props = {"color": _qgis_colour(hex_colour), "outline_color": _qgis_colour(OUTLINE), "outline_style": "solid",
             "outline_width": "0.26", "outline_width_unit": "MM", "style": "solid", "joinstyle": "bevel"}
    opts = ET.SubElement(layer, "Option", {"type": "Map"})
    for k, v in props.items():  # QGIS ≥ 3.26 reads these ...
        ET.SubElement(opts, "Option", {"type": "QString", "name": k, "value": v})
    for k, v in props.items():  # ... older QGIS 3 these
        ET.SubElement(layer, "prop", {"k": k, "v": v})
    return sym


def style_document(grades=tuple(GRADE_NAMES)) -> ET.Element:
    """The <qgis> element: one category per grade in `grades`, then not assessable."""
    root = ET.Element("qgis", {"version": "3.28.0", "styleCategories": "Symbology|Labeling", "labelsEnabled": "1"})
    renderer = ET.SubElement(root, "renderer-v2", {"type": "categorizedSymbol", "attr": GRADE_FIELD,
                                                   "symbollevels": "0", "enableorderby": "0", "forceraster": "0"})
    cats = ET.SubElement(renderer, "categories")
    symbols = ET.SubElement(renderer, "symbols")
    for k, g in enumerate(grades):
        ET.SubElement(cats, "category", {"render": "true", "symbol": str(k), "value": str(int(g)),
                                         "label": long_label(g), "type": "integer"})
        _fill_symbol(symbols, str(k), colour_of(int(g)))
    k = len(grades)
    ET.SubElement(cats, "category", {"render": "true", "symbol": str(k), "value": "", "label": NOT_ASSESSABLE,
                                     "type": "string"})
    _fill_symbol(symbols, str(k), NOT_ASSESSABLE_COLOUR)
    labeling = ET.SubElement(root, "labeling", {"type": "simple"})
    settings = ET.SubElement(labeling, "settings", {"calloutType": "simple"})
    ET.SubElement(settings, "text-style", {"fieldName": LABEL_FIELD, "isExpression": "0", "fontSize": "8",
                                           "fontSizeUnit": "Point", "textColor": "0,0,0,255", "textOpacity": "1"})
    ET.SubElement(settings, "text-buffer", {"bufferDraw": "1", "bufferSize": "0.8", "bufferSizeUnits": "MM",
                                            "bufferColor": "255,255,255,255", "bufferOpacity": "0.8"})
    ET.SubElement(settings, "placement", {"placement": "1", "offsetType": "0"})  # around the centroid
    ET.SubElement(settings, "rendering", {"obstacle": "1", "scaleVisibility": "0"})
    ET.SubElement(root, "layerGeometryType").text = "2"  # polygons
    return root


def write_qml(path, grades=tuple(GRADE_NAMES)) -> None:
    """Write the style (put it beside the GeoJSON with the same base name)."""
    root = style_document(grades)
    ET.indent(root, space=" ")
    text = ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
            + ET.tostring(root, encoding="unicode") + "\n")
    write_text(path, text)


__all__ = ["GRADE_FIELD", "style_document", "write_qml"]
