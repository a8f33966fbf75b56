"""The plan of a procedural city (pure Python + numpy, no bpy): its buildings' shells,
placements and labels, as the layouts (citygen) make them and the detail placers
(building_details) fill them in."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import poly2d


@dataclass
class BuildingPlan:
    id: int
    shell: dict  # keyword arguments of geometry.shell.ShellSpec
    location: tuple  # (x, y) of the local origin
    rotation: float  # radians about z
    vulnerability_class: str
    seed: int
    typology: str
    extent: tuple = field(default=(0.0, 0.0, 0.0, 0.0))  # world bbox x0, y0, x1, y1


@dataclass
class CityPlan:
    buildings: list
    bounds: tuple  # terrain rectangle x0, y0, x1, y1
    set_name: str
    seed: int


def world_polygon(b: BuildingPlan, ccw: bool = False):
    """The footprint in the world (counter-clockwise with `ccw`: the order the shell's edge
    indices refer to, geometry.shell.ShellSpec)."""
    p = np.asarray(b.shell["footprint"], dtype=float)
    if ccw:
        p = poly2d.ccw(p)
    c, s = math.cos(b.rotation), math.sin(b.rotation)
    return p @ np.array([[c, s], [-s, c]]) + np.asarray(b.location)
