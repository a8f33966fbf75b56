"""`post_grades.las`: the post-event points coloured by their building's grade, with the
building ID and grade of each, every attribute of the source file kept.
"""
from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from ..errors import ResultsError
from ..formats.pointcloud import SCALE
from ..runtime.atomic import replacing
from .colours import BACKGROUND_COLOUR, colour_of, rgb8

GRADE_NONE = 255  # `predicted_grade` in the LAS: not a building, or not assessable
SOURCE_CHUNK_POINTS = 2_000_000  # points of the source cloud converted at a time for the graded LAS


def write_grade_las(path, epoch_xyz, origin, crs: str | None, building_id,
                    grade_by_building: dict, source=None) -> None:
    """A LAS 1.4 (point format 7: RGB) of the given points for viewing, e.g. in CloudCompare.

    Extra dimensions `building_id` (uint32, or uint64 when an ID needs it: a national
    register's 15-digit IDs must not wrap) and `predicted_grade` (uint8; 255 = not a building
    or not assessable); RGB as on the map (16-bit = 8-bit × 257): the grade's colour, grey
    for a building not assessed, light grey for points of no building. `epoch_xyz` is float64
    relative to `origin`; stored with scale 0.001 and offset = origin, CRS as WKT when known.
    `source`: the LAS/LAZ file these points were read from, in the same order: every one of
    its attributes (classification, intensity, returns, GPS time, scan angle, point source,
    its extra dimensions) is kept, converted to format 7 as laspy converts formats. `.laz`
    output is compressed."""
    path = _grade_las_path(path)
    xyz = np.asarray(epoch_xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    ids = np.zeros(n, np.int64) if building_id is None else np.asarray(building_id, dtype=np.int64)
    if len(ids) != n:
        raise ResultsError(f"{path}: {len(ids)} building IDs for {n} points")
    max_id = int(ids.max()) if n else 0
    if source is None:
        header = grade_header(path, origin, crs, max_id, None)
        _write_grade_chunks(path, header, origin, grade_by_building, [(xyz, ids, None)])
        return
    import laspy

    # the source streamed a chunk at a time beside the epoch's arrays: a whole copy of a large
    # cloud in both point formats would double the peak of a classification
    with laspy.open(source) as reader:
        if reader.header.point_count != n:
            raise ResultsError(f"{path}: the source {source} has {reader.header.point_count} points, the epoch {n}")
        header = grade_header(path, origin, crs, max_id, source_extra_dims(reader.header))

        def chunks():
            start = 0
            for raw, kept in source_chunks_format7(reader, SOURCE_CHUNK_POINTS):
                stop = start + len(raw)
                yield xyz[start:stop], ids[start:stop], kept
                start = stop

        _write_grade_chunks(path, header, origin, grade_by_building, chunks())


def write_grade_las_streamed(path, chunks, origin, crs: str | None, grade_by_building: dict, *, max_id: int,
                             source_extra_dims: list | None = None) -> None:
    """`write_grade_las` of a cloud that arrives in chunks: (xyz local, building IDs, the
    source's points of the chunk converted to point format 7 or None) each; `max_id` sets the
    ID type; `source_extra_dims` [(name, dtype)] the source's extra dimensions to keep."""
    path = _grade_las_path(path)
    header = grade_header(path, origin, crs, max_id, source_extra_dims)
    _write_grade_chunks(path, header, origin, grade_by_building, chunks)


def source_chunks_format7(reader, chunk_points: int, start: int = 0, stop: int | None = None):
    """The points of an open laspy reader chunk by chunk (points start..stop, all by
    default), converted to point format 7 as `write_grade_las` converts its source (whole
    degrees of a legacy scan angle kept)."""
    import laspy

    from ..formats.pointcloud import read_point_range

    stop = reader.header.point_count if stop is None else stop
    for chunk in read_point_range(reader, start, stop, chunk_points):
        yield chunk, _format7(laspy.LasData(header=reader.header, points=chunk.copy()))


def source_extra_dims(header) -> list:
    """[(name, dtype)] of a source file's extra dimensions, which its graded cloud keeps."""
    return [(name, header.point_format.dimension_by_name(name).dtype)
            for name in header.point_format.extra_dimension_names]


def _grade_las_path(path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise ResultsError(f"{path}: output must end in .las or .laz")
    return path


def grade_header(path: Path, origin, crs, max_id: int, extra):
    """The LAS 1.4 header of a graded cloud (point format 7, the source's extra dimensions
    `extra` [(name, dtype)], building_id of a type that holds `max_id`, predicted_grade)."""
    import laspy

    id_type = np.uint32 if max_id <= np.iinfo(np.uint32).max else np.uint64
    header = laspy.LasHeader(point_format=7, version="1.4")
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=dtype) for name, dtype in extra
                               if name not in ("building_id", "predicted_grade")])
    header.add_extra_dims([
        laspy.ExtraBytesParams(name="building_id", type=id_type, description="building ID, 0 = none"),
        laspy.ExtraBytesParams(name="predicted_grade", type=np.uint8, description="EMS-98 grade, 255 = n.a.")])
    header.offsets = np.asarray(origin, dtype=np.float64)[:3]
    header.scales = np.array([SCALE] * 3)
    header.creation_date = datetime.date.today()
    header.generating_software = "QuakeScan"
    if crs:
        try:
            import pyproj

            header.add_crs(pyproj.CRS.from_user_input(crs))
        except Exception as e:
            raise ResultsError(f"{path}: cannot write CRS {crs!r} to LAS: {e}") from None
    return header


def _write_grade_chunks(path: Path, header, origin, grade_by_building: dict, chunks) -> None:
    records = (grade_records(path, header, origin, grade_by_building, xyz, ids, kept) for xyz, ids, kept in chunks)
    write_grade_records(path, header, origin, records)


def write_grade_records(path, header, origin, records) -> None:
    """A graded LAS/LAZ (`path`, written atomically) of `header` (`grade_header`) and its point
    records, arriving in chunks (laspy point records of the header's format, or None)."""
    import laspy

    path = Path(path)
    origin = np.asarray(origin, dtype=np.float64)[:3]
    compress = path.suffix.lower() == ".laz"
    written = 0
    with replacing(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compress) as w:
            for points in records:
                if points is None or not len(points):
                    continue
                w.write_points(points)
                written += len(points)
            if not written:  # laspy leaves an empty file's bounds at ±inf
                w.header.mins = origin
                w.header.maxs = origin


def grade_records(path, header, origin, grade_by_building: dict, xyz, ids, kept):
    """The point records (laspy, `header`'s format) of one chunk of a graded cloud: `xyz` local
    to `origin`, building IDs, the source's points in format 7 or None; None when empty.
    `path` names the output in errors."""
    import laspy

    n = len(xyz)
    if not n:
        return None
    lim = np.iinfo(np.int32)
    id_type = header.point_format.dimension_by_name("building_id").dtype
    g, rgb = _grade_colours(ids, grade_by_building)
    ints = np.rint(xyz / SCALE)
    if ints.min() < lim.min or ints.max() > lim.max:
        raise ResultsError(f"{path}: coordinates lie more than 2 147 km from the offset "
                           f"{np.asarray(origin, dtype=np.float64)[:3].tolist()}")
    points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    a = points.array
    if kept is not None:  # every attribute of the input first; coordinates, colours and ours below
        for name in kept.array.dtype.names:
            if name in a.dtype.names and name not in ("X", "Y", "Z", "building_id", "predicted_grade"):
                a[name] = kept.array[name]
    else:
        a["bit_fields"] = 1 | (1 << 4)  # return 1 of 1
    a["X"], a["Y"], a["Z"] = ints[:, 0], ints[:, 1], ints[:, 2]
    a["red"], a["green"], a["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    a["building_id"] = np.maximum(ids, 0).astype(id_type)
    a["predicted_grade"] = g
    return points


def _grade_colours(ids: np.ndarray, grade_by_building: dict):
    """Grade (uint8) and 16-bit RGB per point through a lookup over the unique IDs."""
    uniq, inv = np.unique(ids, return_inverse=True)
    g_u = np.full(len(uniq), GRADE_NONE, np.uint8)
    rgb_u = np.tile(np.array(rgb8(BACKGROUND_COLOUR), np.uint16), (len(uniq), 1))
    for k, b in enumerate(uniq):
        b = int(b)
        if b <= 0 or b not in grade_by_building:
            continue
        g = grade_by_building[b]
        if g is not None:
            g_u[k] = int(g)
        rgb_u[k] = rgb8(colour_of(g))
    rgb_u = rgb_u * 257
    return g_u[inv], rgb_u[inv]


def _format7(src):
    """The points of a LasData in point format 7."""
    import laspy

    if src.point_format.id != 7:
        legacy = "scan_angle_rank" in src.point_format.dimension_names
        rank = np.asarray(src.scan_angle_rank, dtype=np.float64) if legacy else None
        src = laspy.convert(src, point_format_id=7, file_version="1.4")
        if legacy:  # laspy copies fields by name: whole degrees become 0.006° steps (LAS 1.4)
            src.points.array["scan_angle"] = np.rint(rank / 0.006).astype(np.int16)
    return src.points


__all__ = ["GRADE_NONE", "SOURCE_CHUNK_POINTS", "grade_header", "grade_records", "source_chunks_format7",
           "source_extra_dims", "write_grade_las", "write_grade_las_streamed", "write_grade_records"]
