"""A COPC file (Cloud Optimized Point Cloud, copc.io 1.0) read by bounds, in file order.

A COPC file is a LAZ file whose compressed chunks are the nodes of an octree, with the
octree's hierarchy (each node's key, byte offset, byte size and point count) in the file:
the points inside a box are read by decompressing only the chunks of the nodes that overlap
it. laspy's `CopcReader.query` does that, but gives neither the points' places in the file
nor a guarantee of their order; a distributed classification needs both, so that a worker
reading a tile's box sees exactly the points, in exactly the order, that a process reading
the whole file sees. Here the hierarchy is read once (laspy's parser), the nodes are sorted
by byte offset (the order `laspy.read` decompresses them in), each node's first point gets
its index in the file, and a box read decompresses its nodes' chunks in that order with
lazrs, laspy's LAZ backend.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .pointcloud import PointCloudError, read_laz_chunks


def is_copc(header) -> bool:
    """True when a laspy header is a COPC file's: its first VLR is the COPC info VLR."""
    vlrs = list(header.vlrs)
    return bool(vlrs) and vlrs[0].user_id == "copc" and vlrs[0].record_id == 1


@dataclass(frozen=True)
class CopcNode:
    offset: int  # byte offset of the node's chunk
    byte_size: int
    count: int
    first: int  # index in the file of the node's first point
    mins: tuple  # the node's cube (world coordinates)
    maxs: tuple


class CopcIndex:
    """The nodes of a COPC file, in file order, and its points read by x/y box."""

    def __init__(self, path):
        import laspy
        from laspy.copc import CopcReader, load_octree_for_query

        self.path = str(path)
        try:
            with CopcReader.open(self.path) as reader:
                nodes = load_octree_for_query(reader.source, reader.copc_info, reader.root_page)
                self.header = reader.header
                self.laszip_record = reader.laszip_vlr.record_data
        except (laspy.LaspyException, OSError, ValueError) as e:
            raise PointCloudError(f"{path}: cannot read as COPC ({e})") from None
        nodes = sorted((n for n in nodes if n.point_count > 0), key=lambda n: n.offset)
        first = np.concatenate([[0], np.cumsum([n.point_count for n in nodes])]).astype(np.int64)
        if int(first[-1]) != int(self.header.point_count):
            raise PointCloudError(f"{path}: the COPC hierarchy holds {int(first[-1])} points, the header says "
                                  f"{self.header.point_count}")
        self.nodes = [CopcNode(int(n.offset), int(n.byte_size), int(n.point_count), int(f),
                               tuple(float(v) for v in n.bounds.mins), tuple(float(v) for v in n.bounds.maxs))
                      for n, f in zip(nodes, first[:-1])]
        self._mins = np.array([n.mins[:2] for n in self.nodes]).reshape(-1, 2)
        self._maxs = np.array([n.maxs[:2] for n in self.nodes]).reshape(-1, 2)

    def nodes_in_box(self, box) -> list[CopcNode]:
        """The nodes whose cube overlaps the x/y box ((2, 2): min, max; world; edges included)."""
        box = np.asarray(box, dtype=np.float64)
        hit = np.all((self._mins <= box[1]) & (self._maxs >= box[0]), axis=1)
        return [self.nodes[i] for i in np.flatnonzero(hit)]

    def points_in_nodes(self, nodes: list[CopcNode], fields: str = "all") -> tuple[np.ndarray, np.ndarray]:
        """(the nodes' point records as the file's structured array, each point's index in
        the file), in file order. `fields` "geometry": only x, y, z, classification and the
        extra dimensions are decompressed (LAZ 1.4 compresses each field in a layer of its
        own); the others are not decoded and hold no meaningful values (a chunk's first
        point's, stored raw)."""
        nodes = sorted(nodes, key=lambda n: n.offset)
        records = read_laz_chunks(self.path, self.laszip_record, self.header.point_format,
                                  [(n.offset, n.count, n.byte_size) for n in nodes], fields == "geometry")
        index = (np.concatenate([np.arange(n.first, n.first + n.count, dtype=np.int64) for n in nodes])
                 if nodes else np.zeros(0, np.int64))
        return records, index

    def points_for_box(self, box) -> tuple[int, float]:
        """(how many points a read of the x/y box decompresses: its nodes' points, how many of
        them lie in the box if each node's points spread evenly over its square)."""
        box = np.asarray(box, dtype=np.float64)
        read, inside = 0, 0.0
        for n in self.nodes_in_box(box):
            lo, hi = np.maximum(box[0], n.mins[:2]), np.minimum(box[1], n.maxs[:2])
            area = float(np.prod(np.subtract(n.maxs[:2], n.mins[:2])))
            read += n.count
            inside += n.count * (float(np.prod(np.maximum(hi - lo, 0.0))) / area if area > 0 else 1.0)
        return read, inside


@lru_cache(maxsize=8)
def _index(path: str, mtime_ns: int, size: int) -> CopcIndex:
    return CopcIndex(path)


def copc_index(path) -> CopcIndex:
    """The file's CopcIndex, made once per process (every tile of a worker asks)."""
    st = Path(path).stat()
    return _index(str(path), st.st_mtime_ns, st.st_size)


__all__ = ["CopcIndex", "CopcNode", "copc_index", "is_copc"]
