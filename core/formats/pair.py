"""A pre-/post-event pair read whole into one local frame, with building IDs.

Both epochs are read in the pre-event file's frame; a building's ID comes from the clouds'
`building_id` dimension (a simulated pair) or from footprints (a real one). ASPRS noise
returns belong to no building. The classify run (`quakescan.assessment`), training and the
experiments read their pairs here.
"""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..errors import ClassifyError
from .pointcloud import Epoch, check_pair, check_point_cloud_path, epoch_origin, read_epoch, set_noise_apart

log = logging.getLogger(__name__)


@dataclass
class PairData:
    pre: Epoch
    post: Epoch
    footprints: object = None  # quakescan.formats.footprints.Footprints
    footprint_ids_without_points: list = field(default_factory=list)
    noise_points: dict = field(default_factory=dict)  # {"pre": n, "post": n}: ASPRS noise, in no building


def load_pair(pre_path, post_path, footprints_path=None, id_field: str | None = None, labels: bool = True) -> PairData:
    """Both epochs in the pre epoch's local frame, with building IDs (and, unless `labels` is
    False, a simulated cloud's per-point grade and surface)."""
    # both epochs at once, in the pre-event file's frame: decoding and scaling are numpy and
    # file reads, which run side by side (a 2 x 75 M-point pair in 20 s instead of 26-33 s)
    origin = epoch_origin(pre_path)
    check_point_cloud_path(post_path)  # before the pre-event epoch is read, not after
    with ThreadPoolExecutor(max_workers=2) as pool:
        pre_job, post_job = (pool.submit(read_epoch, pre_path, origin, labels=labels),
                             pool.submit(read_epoch, post_path, origin, labels=labels))
        pre, post = pre_job.result(), post_job.result()
    check_pair(pre, post)
    if footprints_path is None:
        for e in (pre, post):
            if e.building_id is None:
                raise ClassifyError(f"{e.source}: no building_id dimension; give building footprints "
                                    "(--footprints F.geojson in the clouds' CRS)")
        return PairData(pre, post, noise_points=noise_apart(pre, post))
    from .footprints import assign_buildings, footprints_without_points, no_footprint_contains_a_point, read_footprints

    fp = read_footprints(footprints_path, id_field)
    if fp.crs and pre.crs and fp.crs != pre.crs:
        raise ClassifyError(f"{footprints_path}: footprints are in {fp.crs} but the point clouds in {pre.crs}; "
                            "reproject the footprints")
    if fp.crs and not pre.crs and not post.crs:
        log.info("%s: the point clouds name no CRS; taking the footprints' %s", pre.source, fp.crs)
        pre.crs = post.crs = fp.crs  # footprints that hit the points share their CRS
    for e in (pre, post):
        e.building_id = assign_buildings(e.xyz[:, 0] + e.origin[0], e.xyz[:, 1] + e.origin[1], fp)
    if not (pre.building_id > 0).any():
        raise no_footprint_contains_a_point(footprints_path, fp, pre.bounds_xy()[:, 0])
    noise = noise_apart(pre, post)
    hit = set(np.unique(pre.building_id).tolist()) | set(np.unique(post.building_id).tolist())
    return PairData(pre, post, fp, footprints_without_points(fp, hit), noise)


def noise_apart(pre: Epoch, post: Epoch) -> dict:
    """Both epochs' noise returns in no building (`set_noise_apart`), counted and said."""
    counts = {"pre": set_noise_apart(pre), "post": set_noise_apart(post)}
    for name, e in (("pre", pre), ("post", post)):
        if counts[name]:
            log.info("%s: %d noise returns (ASPRS class 7/18) left out of every building", e.source, counts[name])
    return counts
