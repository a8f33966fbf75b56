"""`buildings.geojson`: one Feature per building, its outline and the CSV's fields.
"""
from __future__ import annotations

import math
import re

from ..runtime.atomic import write_text
from .building_result import in_id_order
from .csv_table import result_fields

def _json_number(v):
    """JSON has no infinity: an opening no size resolves (an epoch without points over the
    building) is null in the GeoJSON, "inf" in the CSV."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _round_coords(c):
    if isinstance(c, (list, tuple)) and c and isinstance(c[0], (int, float)):
        return [round(float(v), 3) for v in c]
    return [_round_coords(x) for x in c]


def geojson_crs_member(crs: str | None) -> dict | None:
    """GeoJSON (2008) named CRS for an EPSG code, None when the CRS has no EPSG code."""
    if not crs:
        return None
    m = re.fullmatch(r"\s*EPSG:(\d+)\s*", str(crs), re.IGNORECASE)
    code = m.group(1) if m else None
    if code is None:
        try:
            import pyproj

            code = pyproj.CRS.from_user_input(crs).to_epsg()
        except Exception:
            code = None
    return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}"}} if code else None


def write_geojson(rows, outlines: dict, path, crs: str | None, classes, attributes: dict | None = None) -> None:
    """A FeatureCollection, one Feature per building (sorted by ID) with the CSV's fields as
    properties (JSON types: assessable true/false, empty → null) plus `outline` (where the
    geometry comes from) and `colour` (the map's hex colour). A building without outline has
    geometry null.

    The coordinates are those of the point cloud, i.e. PROJECTED (metres in `crs`), not the
    WGS 84 longitude/latitude that RFC 7946 assumes; hence the GeoJSON 2008 `crs` member
    ("urn:ogc:def:crs:EPSG::n") when the CRS has an EPSG code, which QGIS/GDAL honour and
    `quakescan.formats.footprints.read_footprints` reads back. Coordinates are rounded to 1 mm.
    `attributes` ({building_id: the footprint's properties}) adds them as `footprint`: the
    cadastre's own ID, address or use stay with the result whatever their types (a number
    JSON cannot hold, NaN or infinity, as null).
    """
    import shapely.geometry

    from ..runtime.text_safety import json_text

    classes = [int(c) for c in classes]
    feats = []
    for r in in_id_order(rows):
        props = {k: _json_number(v) for k, v in result_fields(r, classes).items()}
        o = outlines.get(int(r.building_id))
        geom = None
        if o is not None:
            g = shapely.geometry.mapping(o.geometry)
            geom = {"type": g["type"], "coordinates": _round_coords(g["coordinates"])}
        props["outline"] = o.source if o is not None else None
        props["colour"] = r.colour
        if attributes and int(r.building_id) in attributes:
            props["footprint"] = attributes[int(r.building_id)]
        feats.append({"type": "Feature", "id": int(r.building_id), "properties": props, "geometry": geom})
    doc = {"type": "FeatureCollection"}
    member = geojson_crs_member(crs)
    if member:
        doc["crs"] = member
    doc["features"] = feats
    # strict JSON: a footprint attribute NaN or Infinity (Python's reader takes them) is null
    write_text(path, json_text(doc, separators=(",", ":")) + "\n")


__all__ = ["geojson_crs_member", "write_geojson"]
