"""A streamed epoch read back by block or by box, in file order.

A point is stored as its file's integers (X, Y, Z), its classification, building ID and its
index in the file. Reading a box turns the integers into the same float64 coordinates
`quakescan.formats.pointcloud.read_epoch` makes (integers × scale + (offset − origin), one
operation per element) and sorts the points by their index: a worker sees exactly the
values, in exactly the order, that a single process sees, so its descriptors are equal to
the last bit.

A COPC epoch has no block files: its points are read back by bounds from the file itself, by
the nodes of its octree, and kept to the box as the block files are.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..grid.density import DENSITY_CELL_M
from .block_store import RECORD, block_of, block_runs, blocks_in_box, epoch_json, read_runs
from .streaming import EpochFile, worker_footprints


def read_records(folder: Path, keys, buildings_only: bool = False, in_file_order: bool = True) -> np.ndarray:
    """The stored points of the given blocks (`buildings_only`: those with a building ID), in
    file order (their `index` ascending; `in_file_order=False`: in no particular order, for
    what does not depend on it, as the densities: a sort of every point less)."""
    epoch = epoch_json(folder)
    if epoch.get("file", {}).get("copc"):
        return _copc_block_records(Path(folder), epoch, keys, buildings_only)
    rec, _ = read_runs(folder, block_runs(folder, keys, buildings_only))
    return rec[np.argsort(rec["index"], kind="stable")] if in_file_order and len(rec) else rec


# what a tile reads of its points besides the coordinates
BOX_FIELDS = np.dtype([("index", "<i8"), ("classification", "u1"), ("building_id", "<i8")])


def read_box(folder: Path, f: EpochFile, origin, box, block_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """(BOX_FIELDS records, local float64 coordinates) of the stored points inside the x/y
    `box` ((2, 2): min, max; local frame, edges included), in file order: the blocks the box
    touches, each run cut to the box (a tile's box covers about half of the blocks it
    touches), the coordinates made once. Each run's points lie in file order: merging the
    runs (`_record_kernels.merged_order`) puts them in file order."""
    from ._record_kernels import gather_box, keep_in_box, merged_order

    box = np.asarray(box, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if f.copc:
        rec, xyz = _copc_box(Path(folder), f, origin, box)
        return _box_fields(rec["index"], rec["classification"], rec["building_id"]), xyz
    records, runs = read_runs(folder, block_runs(folder, blocks_in_box(box, block_cells)))
    capacity = len(records)
    index, cls = np.empty(capacity, np.int64), np.empty(capacity, np.uint8)
    bid, xyz = np.empty(capacity, np.int64), np.empty((capacity, 3))
    scales, shifts = f.frame(origin)
    starts = [0]
    for a, b in zip(runs[:-1].tolist(), runs[1:].tolist()):
        starts.append(keep_in_box(records[a:b], scales, shifts, box, index, cls, bid, xyz, starts[-1]))
    n = starts[-1]
    order = merged_order(index[:n], np.asarray(starts, dtype=np.int64))
    out, out_xyz = np.empty(n, BOX_FIELDS), np.empty((n, 3))
    gather_box(order, index, cls, bid, xyz, out, out_xyz)
    return out, out_xyz


def _box_fields(index, classification, building_id) -> np.ndarray:
    out = np.empty(len(index), BOX_FIELDS)
    out["index"], out["classification"], out["building_id"] = index, classification, building_id
    return out


def _copc_box(folder: Path, f: EpochFile, origin: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`read_box` of a COPC epoch: the nodes the box overlaps, decompressed from the file, kept
    to the box as the block files are (local coordinates, edges included), in file order."""
    from ..formats.copc import copc_index

    margin = np.array([[-1.0], [1.0]])  # nodes chosen in world coordinates, points kept in local ones
    index = copc_index(f.path)
    # a record keeps x, y, z, class and building ID: the other fields are not decompressed
    packed, where = index.points_in_nodes(index.nodes_in_box(box + origin[:2] + margin), fields="geometry")
    xyz = f.local_xyz(packed["X"], packed["Y"], packed["Z"], origin)
    inside = np.all((xyz[:, :2] >= box[0]) & (xyz[:, :2] <= box[1]), axis=1)
    return _copc_records(folder, f, origin, packed[inside], where[inside], xyz[inside]), xyz[inside]


def _copc_block_records(folder: Path, epoch: dict, keys, buildings_only: bool) -> np.ndarray:
    """`read_records` of a COPC epoch: the points of the blocks `keys`, read by their box."""
    keys = [(int(k[0]), int(k[1])) for k in keys]
    if not keys:
        return np.zeros(0, RECORD)
    f = EpochFile(**epoch["file"])
    origin = np.asarray(epoch["origin"], dtype=np.float64)
    side = float(epoch.get("block_cells", 0)) * DENSITY_CELL_M
    k = np.asarray(keys, dtype=np.int64)
    lo, hi = k.min(axis=0), k.max(axis=0)
    rec, xyz = _copc_box(folder, f, origin, np.array([lo * side, (hi + 1) * side]))
    span = int(hi[1] - lo[1]) + 1
    b = block_of(xyz[:, :2], int(epoch["block_cells"])) - lo  # every point's block lies in the keys' box
    wanted = (k[:, 0] - lo[0]) * span + (k[:, 1] - lo[1])
    keep = np.isin(b[:, 0] * span + b[:, 1], wanted)
    if buildings_only:
        keep &= rec["building_id"] > 0
    return rec[keep]


def _copc_records(folder: Path, f: EpochFile, origin: np.ndarray, packed: np.ndarray, index: np.ndarray,
                  xyz: np.ndarray) -> np.ndarray:
    """RECORDs of a COPC file's points, building IDs given as `stream_epoch` gives them (the
    footprint holding the point, or the file's building_id)."""
    import laspy

    from ..formats.copc import copc_index

    points = laspy.PackedPointRecord(packed, copc_index(f.path).header.point_format)
    rec = np.empty(len(packed), RECORD)
    rec["index"], rec["X"], rec["Y"], rec["Z"] = index, packed["X"], packed["Y"], packed["Z"]
    rec["classification"] = np.asarray(points["classification"], dtype=np.uint8)
    footprints = epoch_json(folder).get("footprints")
    if footprints:
        from ..formats.footprints import assign_buildings

        rec["building_id"] = assign_buildings(xyz[:, 0] + origin[0], xyz[:, 1] + origin[1],
                                              worker_footprints(footprints["path"], footprints.get("id_field")))
    else:
        rec["building_id"] = np.asarray(points["building_id"], dtype=np.int64)
    return rec


__all__ = ["BOX_FIELDS", "read_box", "read_records"]
