"""COPC files for tests: a LAS file's points rewritten as a Cloud Optimized Point Cloud.

Nothing in this project's dependencies writes COPC (laspy reads it; PDAL's writers.copc and
untwine are not Python packages), so the tests make their own from the format's
specification (copc.io, version 1.0): a LAS 1.4 file with point format 6-8, compressed by
LASzip in variable-size chunks, one chunk an octree node; the COPC info VLR first of the
VLRs; the hierarchy (one page: a node's key, byte offset, byte size and point count) in an
EVLR. Each point goes to the node of its level (drawn at random, as a real writer keeps a
subsample at each level) that holds it, so a box query touches several levels and nodes;
`max_level` sets the depth (a real writer stops at ~100 k points a node).
The file's point order is the nodes' order: what `laspy.read` returns.
"""
from __future__ import annotations

import io
import struct
from pathlib import Path

import laspy
import numpy as np

HIERARCHY_ENTRY = struct.Struct("<iiiiQii")  # key (level, x, y, z), offset, byte size, point count


def write_copc(source: Path, out: Path, max_level: int = 2, seed: int = 0) -> Path:
    """`source` (LAS/LAZ, any point format) rewritten as a COPC file of point format 6 (7
    with colours) with its extra dimensions and CRS; returns `out`."""
    import lazrs

    las = laspy.read(source)
    fmt = 7 if "red" in las.point_format.dimension_names else 6
    if las.point_format.id != fmt:
        las = laspy.convert(las, point_format_id=fmt, file_version="1.4")
    X, Y, Z = (np.asarray(las.points.array[c], dtype=np.int64) for c in "XYZ")
    scales, offsets = np.asarray(las.header.scales), np.asarray(las.header.offsets)
    xyz = np.column_stack([X, Y, Z]) * scales + offsets
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    centre = (lo + hi) / 2
    halfsize = float((hi - lo).max() / 2) * 1.001 + 1e-6
    rng = np.random.default_rng(seed)
    # a real writer keeps a subsample at each level, as dense as the level's spacing: a city
    # (2.5-D) fills about 4^level nodes of a level, so a level holds points in that proportion
    share = 4.0 ** np.arange(max_level + 1)
    level = rng.choice(max_level + 1, size=len(xyz), p=share / share.sum())
    cell = (2 * halfsize) / (2.0 ** level)
    key = np.floor((xyz - (centre - halfsize)) / cell[:, None]).astype(np.int64)
    key = np.minimum(key, (2 ** level)[:, None] - 1)
    nodes = np.column_stack([level, key])
    order = np.lexsort((nodes[:, 3], nodes[:, 2], nodes[:, 1], nodes[:, 0]))
    nodes = nodes[order]
    packed = las.points.array[order]
    starts = np.flatnonzero(np.r_[True, np.any(nodes[1:] != nodes[:-1], axis=1)])
    ends = np.r_[starts[1:], len(nodes)]

    header = laspy.LasHeader(version="1.4", point_format=las.point_format)
    header.scales, header.offsets = scales, offsets
    header.mins, header.maxs = lo, hi
    header.point_count = len(xyz)
    n_extra = las.point_format.num_extra_bytes
    laz_vlr = lazrs.LazVlr.new_for_compression(fmt, n_extra, use_variable_size_chunks=True)
    crs = [v for v in las.header.vlrs if v.user_id == "LASF_Projection"]
    header.vlrs = [laspy.VLR("copc", 1, "copc info", bytes(160)), *crs]
    if n_extra:
        header.vlrs.append(laspy.vlrs.known.ExtraBytesVlr())
        for info in las.point_format.extra_dimensions:
            header.vlrs[-1].extra_bytes_structs.append(_extra_bytes_struct(info))
    header.vlrs.append(laspy.VLR("laszip encoded", 22204, "lazrs", laz_vlr.record_data()))
    header.set_compressed(True)

    buf = io.BytesIO()
    header.write_to(buf)
    data_start = buf.tell()
    compressor = lazrs.LasZipCompressor(buf, laz_vlr)
    compressor.reserve_offset_to_chunk_table()
    for s, t in zip(starts, ends):
        compressor.compress_many(packed[s:t].tobytes())
        compressor.finish_current_chunk()
    compressor.done()
    buf.seek(data_start)
    table = lazrs.read_chunk_table(buf, laz_vlr)
    sizes = [int(size) for _, size in table]
    offsets_b = data_start + 8 + np.r_[0, np.cumsum(sizes)[:-1]]

    buf.seek(0, io.SEEK_END)
    evlr_at = buf.tell()
    entries = b"".join(HIERARCHY_ENTRY.pack(*(int(v) for v in nodes[s]), int(o), int(b), int(t - s))
                       for s, t, o, b in zip(starts, ends, offsets_b, sizes))
    evlr_header = struct.pack("<H16sHQ32s", 0, b"copc", 1000, len(entries), b"copc hierarchy")
    buf.write(evlr_header + entries)

    info = struct.pack("<3dddQQdd", *centre, halfsize, halfsize / 64, evlr_at + len(evlr_header), len(entries),
                       0.0, 0.0) + bytes(8 * 11)
    header.vlrs[0] = laspy.VLR("copc", 1, "copc info", info)
    header.start_of_first_evlr, header.number_of_evlrs = evlr_at, 1
    buf.seek(0)
    header.write_to(buf, ensure_same_size=True)
    Path(out).write_bytes(buf.getvalue())
    return Path(out)


def _extra_bytes_struct(info):
    from laspy.vlrs.known import ExtraBytesStruct

    s = ExtraBytesStruct(data_type=_EXTRA_TYPE[np.dtype(info.dtype).str.lstrip("<|")],
                         name=info.name.encode(), description=(info.description or "").encode())
    return s


_EXTRA_TYPE = {"u1": 1, "i1": 2, "u2": 3, "i2": 4, "u4": 5, "i4": 6, "u8": 7, "i8": 8, "f4": 9, "f8": 10}
