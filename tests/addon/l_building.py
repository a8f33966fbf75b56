"""An L-shaped building with a gable roof, as a user would model it: faces only, no shell
description. Wing A runs along x (0..20, 8 deep, gable at x = 20), wing B along y (0..18,
8 deep, gable at y = 18); a hip over the outer corner (0, 0), a valley into the inner corner
(8, 8); ridges 4 m from the wings' sides."""
import math

import numpy as np

FOOTPRINT = [(0, 0), (20, 0), (20, 8), (8, 8), (8, 18), (0, 18)]
EAVE = 6.0
PITCH = 35.0
RIDGE = EAVE + 4.0 * math.tan(math.radians(PITCH))
GROUND, ROOF, WALL = 0, 1, 2


def l_building():
    """(vertices (n, 3), faces [index lists], surfaces): outward normals, closed."""
    H, R = EAVE, RIDGE
    verts, faces, surf = [], [], []

    def face(pts, s):
        faces.append(list(range(len(verts), len(verts) + len(pts))))
        verts.extend(pts)
        surf.append(s)
    fp = FOOTPRINT
    face([(x, y, 0.0) for x, y in fp[::-1]], GROUND)  # seen from below: clockwise from above
    for i in range(len(fp)):
        (ax, ay), (bx, by) = fp[i], fp[(i + 1) % len(fp)]
        face([(ax, ay, 0.0), (bx, by, 0.0), (bx, by, H), (ax, ay, H)], WALL)
    face([(20, 0, H), (20, 8, H), (20, 4, R)], WALL)  # gable of wing A
    face([(8, 18, H), (0, 18, H), (4, 18, R)], WALL)  # gable of wing B
    face([(0, 0, H), (20, 0, H), (20, 4, R), (4, 4, R)], ROOF)  # A south
    face([(20, 8, H), (8, 8, H), (4, 4, R), (20, 4, R)], ROOF)  # A north, down to the valley
    face([(0, 18, H), (0, 0, H), (4, 4, R), (4, 18, R)], ROOF)  # B west, up from the hip
    face([(8, 8, H), (8, 18, H), (4, 18, R), (4, 4, R)], ROOF)  # B east
    return np.array(verts, dtype=np.float64), faces, np.array(surf)


def roof_z(x, y):
    """Height of the roof surface over (x, y) inside the footprint."""
    t = math.tan(math.radians(PITCH))
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    a = np.where(y <= 4, y, 8 - y)  # wing A's slopes
    b = np.where(x <= 4, x, 8 - x)
    # where the wings meet: the hip quadrant takes the lower slope, the valley quadrant the
    # higher, the other two the slope of the wing whose ridge runs through them
    hi_x, hi_y = x >= 4, y >= 4
    corner = np.where(hi_x & hi_y, np.maximum(a, b), np.where(~hi_x & ~hi_y, np.minimum(a, b), np.where(hi_x, a, b)))
    in_a, in_b = (y <= 8), (x <= 8)
    h = np.where(in_a & in_b, corner, np.where(in_a, a, b))
    return EAVE + t * np.clip(h, 0, 4)
