"""Point spacing as the paper measures it: mean distance to the nearest neighbour, per surface."""
import numpy as np
from scipy.spatial import cKDTree


def nearest_neighbour_spacing(xyz, building_id, surface, code) -> np.ndarray:
    """Distance of every point on `surface == code` to its nearest neighbour on the same
    surface kind of the same building (so the gap between buildings never counts)."""
    nn = []
    for b in np.unique(building_id[building_id > 0]):
        p = xyz[(building_id == b) & (surface == code)]
        if len(p) > 1:
            d, _ = cKDTree(p).query(p, k=2)
            nn.append(d[:, 1])
    return np.concatenate(nn)
