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
from .pointcloud import (Epoch, HeaderFacts, check_pair, check_pair_headers, epoch_origin, header_facts, read_epoch,
                         set_noise_apart, xy_extents_apart)

log = logging.getLogger(__name__)


@dataclass
class PairData:
    pre: Epoch
    post: Epoch
    footprints: object = None  # quakescan.formats.footprints.Footprints
    footprint_ids_without_points: list = field(default_factory=list)
    noise_points: dict = field(default_factory=dict)  # {"pre": n, "post": n}: ASPRS noise, in no building
    coverage: dict = field(default_factory=dict)  # `quakescan.formats.footprints.coverage`


def load_pair(pre_path, post_path, footprints_path=None, id_field: str | None = None, labels: bool = True) -> PairData:
    """Both epochs in the pre epoch's local frame, with building IDs (and, unless `labels` is
    False, a simulated cloud's per-point grade and surface)."""
    # what the headers and the footprints can refuse is refused before any point is read
    headers = header_facts(pre_path), header_facts(post_path)
    check_pair_headers(*headers)
    fp = None
    if footprints_path is not None:
        from .footprints import read_footprints

        fp = read_footprints(footprints_path, id_field)
        check_footprints_against_headers(footprints_path, fp, *headers)
    origin = epoch_origin(pre_path)
    # both epochs at once, in the pre-event file's frame: decoding and scaling are numpy and
    # file reads, which run side by side (a 2 x 75 M-point pair in 20 s instead of 26-33 s)
    with ThreadPoolExecutor(max_workers=2) as pool:
        pre_job, post_job = (pool.submit(read_epoch, pre_path, origin, labels=labels),
                             pool.submit(read_epoch, post_path, origin, labels=labels))
        pre, post = pre_job.result(), post_job.result()
    check_pair(pre, post)
    if fp is None:
        for e in (pre, post):
            if e.building_id is None:
                raise ClassifyError(f"{e.source}: no building_id dimension; give building footprints "
                                    "(--footprints F.geojson in the clouds' CRS)")
        return PairData(pre, post, noise_points=noise_apart(pre, post))
    from .footprints import assign_buildings, coverage, footprints_without_points, no_footprint_contains_a_point

    if fp.crs and not pre.crs and not post.crs:
        log.info("%s: the point clouds name no CRS; taking the footprints' %s", pre.source, fp.crs)
        pre.crs = post.crs = fp.crs  # footprints that hit the points share their CRS
    for e in (pre, post):
        e.building_id = assign_buildings(e.xyz[:, 0] + e.origin[0], e.xyz[:, 1] + e.origin[1], fp)
    if not (pre.building_id > 0).any():
        raise no_footprint_contains_a_point(footprints_path, fp, pre.bounds_xy()[:, 0])
    noise = noise_apart(pre, post)
    pre_ids, post_ids = set(np.unique(pre.building_id).tolist()), set(np.unique(post.building_id).tolist())
    return PairData(pre, post, fp, footprints_without_points(fp, pre_ids | post_ids), noise,
                    coverage(fp, pre_ids, post_ids))


def noise_apart(pre: Epoch, post: Epoch) -> dict:
    """Both epochs' noise returns in no building (`set_noise_apart`), counted and said."""
    counts = {"pre": set_noise_apart(pre), "post": set_noise_apart(post)}
    for name, e in (("pre", pre), ("post", post)):
        if counts[name]:
            log.info("%s: %d noise returns (ASPRS class 7/18) left out of every building", e.source, counts[name])
    return counts


def check_footprints_against_headers(footprints_path, fp, pre: HeaderFacts, post: HeaderFacts) -> None:
    """Footprints that cannot hold a pre-event point, refused from the headers: another CRS than
    the clouds', or an extent apart from the pre-event cloud's."""
    from .footprints import no_footprint_contains_a_point

    clouds_crs = pre.crs or post.crs
    if fp.crs and clouds_crs and fp.crs != clouds_crs:
        raise ClassifyError(f"{footprints_path}: footprints are in {fp.crs} but the point clouds in {clouds_crs}; "
                            "reproject the footprints")
    if not pre.bounds_known() or not len(fp.ids):
        return
    b = fp.bounds()
    if xy_extents_apart(b[:, :2].min(axis=0), b[:, 2:].max(axis=0), pre.mins, pre.maxs):
        raise no_footprint_contains_a_point(footprints_path, fp, [pre.mins[0], pre.maxs[0]])
