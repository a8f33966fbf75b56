"""BMesh builders for the streetscape (addon/streetscape.py): trees, hedges, parked cars and
street furniture as low-poly closed shapes.

Labels: building ID 0 everywhere; surface VEGETATION for trees and hedges, OBJECT for cars
and furniture. Tree crowns (closed ellipsoids, one to three merged blobs) get the
``qs_porous`` face layer = 1: the scanner lets a ray pass such a face with the scene's
transmission probability (core/acquisition/vegetation.py). Trunks and hedges are opaque vegetation
(layer 0): trunks are thin and solid, hedges dense.
"""
from __future__ import annotations

import math

import numpy as np

from . import mesh as gm

CROWN_RINGS, CROWN_SEGMENTS = 6, 10  # 50 vertices, 100 triangles a blob
TRUNK_SIDES = 6
TRUNK_FOOT_M = 0.3  # trunks start this far below the ground so none floats on a slope


def ellipsoid(centre, radii, rings=CROWN_RINGS, segments=CROWN_SEGMENTS):
    """Closed UV ellipsoid with outward triangles: vertices (n, 3), triangles."""
    cx, cy, cz = centre
    rx, ry, rz = radii
    verts = [(cx, cy, cz + rz)]
    for i in range(1, rings):
        phi = math.pi * i / rings
        for j in range(segments):
            a = 2 * math.pi * j / segments
            verts.append((cx + rx * math.sin(phi) * math.cos(a), cy + ry * math.sin(phi) * math.sin(a),
                          cz + rz * math.cos(phi)))
    verts.append((cx, cy, cz - rz))
    bottom = len(verts) - 1

    def ring(i, j):
        return 1 + (i - 1) * segments + j % segments
    tris = [(0, ring(1, j), ring(1, j + 1)) for j in range(segments)]
    for i in range(1, rings - 1):
        for j in range(segments):
            tris += [(ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)), (ring(i, j), ring(i + 1, j + 1), ring(i, j + 1))]
    tris += [(ring(rings - 1, j), bottom, ring(rings - 1, j + 1)) for j in range(segments)]
    return np.array(verts, np.float64), tris


def prism(xy, z0, z1):
    """Closed vertical prism over a counter-clockwise polygon xy (k, 2): vertices, faces
    (bottom, top, sides as polygons)."""
    xy = np.asarray(xy, np.float64)
    k = len(xy)
    verts = np.vstack([np.column_stack([xy, np.full(k, z0)]), np.column_stack([xy, np.full(k, z1)])])
    faces = [tuple(range(k - 1, -1, -1)), tuple(range(k, 2 * k))]
    faces += [(i, (i + 1) % k, k + (i + 1) % k, k + i) for i in range(k)]
    return verts, faces


def oriented_rect(x, y, heading, length, width):
    c, s = math.cos(heading), math.sin(heading)
    local = [(-length / 2, -width / 2), (length / 2, -width / 2), (length / 2, width / 2), (-length / 2, width / 2)]
    return [(x + c * px - s * py, y + s * px + c * py) for px, py in local]


def _porous_layer(bm):
    ints = bm.faces.layers.int
    return ints.get(gm.POROUS_LAYER) or ints.new(gm.POROUS_LAYER)


def add_tree(bm, lab, tree):
    """Trunk (opaque) and crown blobs (porous) of a streetscape.Tree; returns the crown faces."""
    por = _porous_layer(bm)
    ang = np.linspace(0, 2 * math.pi, TRUNK_SIDES, endpoint=False)
    ring = np.column_stack([tree.x + tree.trunk_radius * np.cos(ang), tree.y + tree.trunk_radius * np.sin(ang)])
    v, f = prism(ring, tree.z - TRUNK_FOOT_M, tree.z + tree.trunk_top)
    for face in gm.add_mesh(bm, lab, v, f, gm.VEGETATION, 0):
        face[por] = 0
    crown = []
    for cx, cy, cz, rx, ry, rz in tree.blobs:
        v, t = ellipsoid((cx, cy, tree.z + cz), (rx, ry, rz))
        crown += gm.add_mesh(bm, lab, v, t, gm.VEGETATION, 0)
    for face in crown:
        face[por] = 1
    return crown


def add_hedge(bm, lab, hedge):
    length = math.hypot(hedge.x1 - hedge.x0, hedge.y1 - hedge.y0)
    rect = oriented_rect((hedge.x0 + hedge.x1) / 2, (hedge.y0 + hedge.y1) / 2,
                         math.atan2(hedge.y1 - hedge.y0, hedge.x1 - hedge.x0), length, hedge.width)
    v, f = prism(rect, hedge.z - 0.1, hedge.z + hedge.height)
    return gm.add_mesh(bm, lab, v, f, gm.VEGETATION, 0)


def add_car(bm, lab, car):
    """Body (lower 55 % of the height, 0.2 m above the ground) and a shorter, narrower cabin."""
    z0 = car.z + 0.2
    body_top = car.z + 0.55 * car.height
    v, f = prism(oriented_rect(car.x, car.y, car.heading, car.length, car.width), z0, body_top)
    faces = gm.add_mesh(bm, lab, v, f, gm.OBJECT, 0)
    c, s = math.cos(car.heading), math.sin(car.heading)
    back = -0.08 * car.length  # cabin set back a little from the centre
    v, f = prism(oriented_rect(car.x + c * back, car.y + s * back, car.heading, 0.55 * car.length, 0.9 * car.width),
                 body_top, car.z + car.height)
    return faces + gm.add_mesh(bm, lab, v, f, gm.OBJECT, 0)


def add_furniture(bm, lab, item):
    x, y, h, z = item.x, item.y, item.heading, item.z
    parts = []
    if item.kind == "lamp":
        parts.append((oriented_rect(x, y, h, 0.16, 0.16), z - 0.1, z + item.height))
        parts.append((oriented_rect(x + 0.5 * math.cos(h + math.pi / 2), y + 0.5 * math.sin(h + math.pi / 2),
                                    h, 0.3, 1.1), z + item.height - 0.15, z + item.height))
    elif item.kind == "bench":
        parts.append((oriented_rect(x, y, h, 1.8, 0.45), z + 0.4, z + 0.48))
        for side in (-0.8, 0.8):
            parts.append((oriented_rect(x + side * math.cos(h), y + side * math.sin(h), h, 0.08, 0.45), z, z + 0.4))
        parts.append((oriented_rect(x - 0.22 * math.sin(h), y + 0.22 * math.cos(h), h, 1.8, 0.06), z + 0.48,
                      z + item.height))
    elif item.kind == "bin":
        parts.append((oriented_rect(x, y, h, 0.5, 0.5), z, z + item.height))
    else:  # bollard
        parts.append((oriented_rect(x, y, h, 0.2, 0.2), z, z + item.height))
    faces = []
    for rect, z0, z1 in parts:
        v, f = prism(rect, z0, z1)
        faces += gm.add_mesh(bm, lab, v, f, gm.OBJECT, 0)
    return faces
