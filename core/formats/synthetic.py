"""Small synthetic scenes with known geometry: the built-in default, tests and benchmarks."""
from __future__ import annotations

import numpy as np

from .scene import GROUND, ROOF, VEGETATION, WALL, Building, Scene


def box_mesh(x0, y0, x1, y1, z0, z1):
    """Closed axis-aligned box: vertices, triangles (outward), surface per triangle."""
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    quads = [
        ((0, 3, 2, 1), GROUND),  # bottom (faces down)
        ((4, 5, 6, 7), ROOF),
        ((0, 1, 5, 4), WALL),  # south (y0)
        ((1, 2, 6, 5), WALL),  # east (x1)
        ((2, 3, 7, 6), WALL),  # north (y1)
        ((3, 0, 4, 7), WALL),  # west (x0)
    ]
    tris, surf = [], []
    for (a, b, c, d), s in quads:
        tris += [(a, b, c), (a, c, d)]
        surf += [s, s]
    return v, np.array(tris, np.int64), np.array(surf, np.uint8)


def ground_mesh(x0, y0, x1, y1, z=0.0):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return v, np.array([(0, 1, 2), (0, 2, 3)], np.int64), np.array([GROUND, GROUND], np.uint8)


class _MeshBuilder:
    def __init__(self):
        self.v, self.f, self.b, self.s = [], [], [], []
        self.n = 0

    def add(self, verts, faces, surface, building_id):
        self.v.append(verts)
        self.f.append(faces + self.n)
        self.s.append(surface)
        self.b.append(np.full(len(faces), building_id, np.int32))
        self.n += len(verts)

    def arrays(self):
        return (np.concatenate(self.v), np.concatenate(self.f), np.concatenate(self.b), np.concatenate(self.s))


def box_city(rows: int = 3, cols: int = 3, footprint: float = 12.0, street: float = 10.0,
             height: float | tuple = 9.0, margin: float = 20.0, origin=(0.0, 0.0, 0.0),
             grades=None, epoch: str = "pre", storey_height: float = 3.0) -> Scene:
    """A grid of flat-roofed boxes on a flat ground patch at z = 0 (relative to origin).

    `height` is one number or a sequence cycled over the buildings; building IDs run 1..n
    row by row; `grades` (sequence) labels them (default 0).
    """
    heights = np.atleast_1d(np.asarray(height, dtype=np.float64))
    mb = _MeshBuilder()
    buildings = []
    pitch = footprint + street
    width_x = cols * pitch - street
    width_y = rows * pitch - street
    mb.add(*ground_mesh(-margin, -margin, width_x + margin, width_y + margin), 0)
    k = 0
    for r in range(rows):
        for c in range(cols):
            h = float(heights[k % len(heights)])
            bid = k + 1
            x0, y0 = c * pitch, r * pitch
            mb.add(*box_mesh(x0, y0, x0 + footprint, y0 + footprint, 0.0, h), bid)
            grade = int(grades[k]) if grades is not None else 0
            buildings.append(Building(bid, grade=grade, storeys=max(1, round(h / storey_height)),
                                      typology="box", seed=bid))
            k += 1
    v, f, b, s = mb.arrays()
    return Scene(v, f, b, s, buildings, origin=np.asarray(origin, dtype=np.float64), epoch=epoch)


def flat_ground(size: float = 400.0, z: float = 0.0, origin=(0.0, 0.0, 0.0)) -> Scene:
    """Just a square of ground centred on (0, 0): for closed-form sampling tests."""
    h = size / 2
    v, f, s = ground_mesh(-h, -h, h, h, z)
    return Scene(v, f, np.zeros(len(f), np.int32), s, [], origin=np.asarray(origin, dtype=np.float64))


def ellipsoid_mesh(centre, radii, rings: int = 8, segments: int = 12):
    """Closed UV ellipsoid (outward triangles): a tree crown. Vertices, triangles."""
    cx, cy, cz = centre
    rx, ry, rz = radii
    verts = [(cx, cy, cz + rz)]
    for i in range(1, rings):
        phi = np.pi * i / rings
        for j in range(segments):
            a = 2 * np.pi * j / segments
            verts.append((cx + rx * np.sin(phi) * np.cos(a), cy + ry * np.sin(phi) * np.sin(a), cz + rz * np.cos(phi)))
    verts.append((cx, cy, cz - rz))
    bottom = len(verts) - 1
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments  # noqa: E731
    tris = [(0, ring(1, j), ring(1, j + 1)) for j in range(segments)]
    for i in range(1, rings - 1):
        for j in range(segments):
            tris += [(ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)), (ring(i, j), ring(i + 1, j + 1), ring(i, j + 1))]
    tris += [(ring(rings - 1, j), bottom, ring(rings - 1, j + 1)) for j in range(segments)]
    return np.array(verts, np.float64), np.array(tris, np.int64)


def with_trees(scene: Scene, trees, transmission: float | None = None) -> Scene:
    """`scene` plus trees: each (x, y, trunk_height, crown_radius) gives an opaque square
    trunk (0.3 m) from z = 0 to the crown's centre and a porous spherical crown there
    (surface vegetation, building_id 0)."""
    v, f, b, s = [scene.vertices], [scene.faces], [scene.face_building], [scene.face_surface]
    porous = [np.zeros(len(scene.faces), bool) if scene.face_porous is None else scene.face_porous]
    n = len(scene.vertices)
    for x, y, trunk_h, r in trees:
        tv, tf, _ = box_mesh(x - 0.15, y - 0.15, x + 0.15, y + 0.15, 0.0, trunk_h)
        cv, cf = ellipsoid_mesh((x, y, trunk_h), (r, r, r))
        for verts, faces, is_porous in ((tv, tf, False), (cv, cf, True)):
            v.append(verts)
            f.append(faces + n)
            b.append(np.zeros(len(faces), np.int32))
            s.append(np.full(len(faces), VEGETATION, np.uint8))
            porous.append(np.full(len(faces), is_porous))
            n += len(verts)
    return Scene(np.concatenate(v), np.concatenate(f), np.concatenate(b), np.concatenate(s), scene.buildings,
                 scene.origin.copy(), scene.crs, scene.epoch, scene.units, np.concatenate(porous),
                 scene.transmission if transmission is None else transmission)
