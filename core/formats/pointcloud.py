"""Epoch point clouds as LAS 1.4 / LAZ (laspy + lazrs), per the contract in docs/DESIGN.md.

Point format 6 (gps_time, scan angle, up to 15 returns) with extra dimensions
`building_id` (uint32), `grade` (uint8, 255 = unknown) and `surface` (uint8).
Coordinates are stored with scale 0.001 m and offset = scene origin.
"""
from __future__ import annotations

import dataclasses
import datetime
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from ..errors import PointCloudError, check_input_file
from ..runtime.atomic import Temporary, check_output_name, commit, is_write_failure, replacing, write_failure_message

log = logging.getLogger(__name__)

SCALE = 0.001
POINT_FORMAT = 6
GRADE_UNKNOWN = 255
# ASPRS classes
UNCLASSIFIED, GROUND_CLASS, BUILDING_CLASS = 1, 2, 6
LOW_VEGETATION_CLASS, HIGH_VEGETATION_CLASS = 3, 5
VEGETATION_CLASSES = (3, 4, 5)  # low, medium, high vegetation
# low and high noise: a return off no surface (a bird, multipath, a dust cloud) is no roof
NOISE_CLASSES = (7, 18)
EXTRA_DIMS = (("building_id", np.uint32, "building ID, 0 = none"),
              ("grade", np.uint8, "EMS-98 grade, 255 = unknown"),
              ("surface", np.uint8, "0grd1roof2wall3deb4int5veg6obj"))
_INT32 = np.iinfo(np.int32)


@dataclass
class PointChunk:
    """Columns of a batch of points; xyz in the world frame minus `offset` (float64)."""

    xyz: np.ndarray  # (n, 3) float64, relative to the writer's offset
    gps_time: np.ndarray
    scan_angle_deg: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    classification: np.ndarray
    building_id: np.ndarray
    grade: np.ndarray
    surface: np.ndarray
    point_source_id: np.ndarray
    scan_direction: np.ndarray | None = None
    edge_of_flight_line: np.ndarray | None = None
    intensity: np.ndarray | None = None  # uint16; None = 0 (photogrammetry has none)

    def __len__(self):
        return len(self.xyz)


def make_header(offset, crs: str | None, date: str = "2020-01-01",
                software: str = "QuakeScan") -> laspy.LasHeader:
    header = laspy.LasHeader(point_format=POINT_FORMAT, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=t, description=d) for n, t, d in EXTRA_DIMS])
    header.offsets = np.asarray(offset, dtype=np.float64)
    header.scales = np.array([SCALE] * 3)
    header.creation_date = datetime.date.fromisoformat(date)
    header.generating_software = software[:32]
    header.system_identifier = "QuakeScan virtual ULS"
    # adjusted standard GPS time
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    if crs:
        try:
            import pyproj

            header.add_crs(pyproj.CRS.from_user_input(crs))
        except Exception as e:  # an unknown CRS is the input's problem, not a crash
            raise PointCloudError(f"cannot write CRS {crs!r} to LAS: {e}") from None
    return header


class LasChunkWriter:
    """Streams chunks into a LAS/LAZ file; the file appears under its name only on success."""

    def __init__(self, path: str | os.PathLike, offset, crs: str | None = None, date: str = "2020-01-01",
                 software: str = "QuakeScan", temporary: str | os.PathLike | None = None):
        """`temporary`: where the points are written until the file is complete, inside a folder
        of QuakeScan's own (a resumable scan's checkpoint, which finds a killed run's file
        there); None: a private temporary of `runtime.atomic`, made when writing starts."""
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in (".las", ".laz"):
            raise PointCloudError(f"{self.path}: output must end in .las or .laz")
        self.header = make_header(offset, crs, date, software)
        self.offset = np.asarray(offset, dtype=np.float64)
        self._temporary: Temporary | None = None
        self.tmp = None if temporary is None else Path(temporary)
        self._writer = None
        self._compress = suffix == ".laz"
        self.count = 0
        # Where the temporary file goes when writing stops with an error (None: it is removed);
        # a resumable scan keeps its points this way (quakescan.acquisition.scan_checkpoint).
        self.keep_partial_as: Path | None = None

    @property
    def compressed(self) -> bool:
        return self._compress

    def __enter__(self):
        kwargs = {}
        if self._compress:
            kwargs["laz_backend"] = laspy.LazBackend.LazrsParallel
        check_output_name(self.path, PointCloudError)
        if self.tmp is None:
            self._temporary = Temporary(self.path, PointCloudError)
            self.tmp = self._temporary.path
        else:  # laspy opens by name: whatever is there (a link planted in the folder) is not opened
            self.tmp.unlink(missing_ok=True)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = laspy.open(self.tmp, mode="w", header=self.header, do_compress=self._compress, **kwargs)
        except Exception as e:
            self._drop_temporary()
            if is_write_failure(e):
                raise PointCloudError(write_failure_message(self.path, e)) from e
            raise
        return self

    def write(self, chunk: PointChunk) -> None:
        """Pack and write a chunk of points (xyz relative to the offset)."""
        rec = pack_points(self.header, chunk, self.path)
        if rec is not None:
            self.write_record(rec, record_bounds(rec))

    def write_record(self, rec, bounds) -> None:
        """Write a packed record whose `record_bounds` the caller computed (a worker can).

        laspy's write_points would recompute them here, on the one thread that writes;
        this updates the header with the given bounds and hands the bytes to its writer."""
        if rec is None or len(rec) == 0:
            return
        w = self._writer
        point_writer = getattr(w, "point_writer", None)
        if point_writer is None or bounds is None:  # another laspy: take the documented path
            w.write_points(rec)
            self.count += len(rec)
            return
        mins, maxs, by_return = bounds
        h = w.header
        h.mins = np.minimum(h.mins, mins)
        h.maxs = np.maximum(h.maxs, maxs)
        h.number_of_points_by_return[: len(by_return)] += by_return.astype(np.uint64)
        h.point_count += len(rec)
        point_writer.write_points(rec)
        self.count += len(rec)

    def __exit__(self, exc_type, exc, tb):
        try:
            if self.count == 0 and exc_type is None:
                # laspy leaves inf/-inf bounds in an empty file's header
                self._writer.header.mins = self.offset
                self._writer.header.maxs = self.offset
            self._writer.close()  # flushes the last chunk: a full disk may show only here
        except BaseException as e:
            exc = exc or e
        if exc is None:
            try:
                commit(self.tmp, self.path)
                self._drop_temporary()
                return False
            except OSError as e:
                exc = e
        # never a cut file under the final name; a resumable scan keeps it under its own
        if self.keep_partial_as is not None and self.tmp.is_file():
            os.replace(self.tmp, self.keep_partial_as)
        self._drop_temporary()
        if is_write_failure(exc) and not isinstance(exc, PointCloudError):
            raise PointCloudError(write_failure_message(self.path, exc)) from exc
        if exc_type is None:
            raise exc
        return False

    def _drop_temporary(self) -> None:
        if self._temporary is not None:
            self._temporary.discard()
        elif self.tmp is not None:
            self.tmp.unlink(missing_ok=True)


def record_bounds(rec):
    """(mins, maxs, points by return 1..15) of a packed record, in world units."""
    a = rec.array
    scales, offsets = np.asarray(rec.scales), np.asarray(rec.offsets)
    mins = np.array([a[c].min() for c in "XYZ"]) * scales + offsets
    maxs = np.array([a[c].max() for c in "XYZ"]) * scales + offsets
    by_return = np.bincount(a["bit_fields"] & 15, minlength=16)[1:16]
    return mins, maxs, by_return


def pack_points(header, chunk: PointChunk, name="point cloud"):
    """Fill a format-6 record straight through its numpy fields (bit fields packed here:
    an order of magnitude faster than laspy's per-dimension setters)."""
    n = len(chunk)
    if n == 0:
        return None
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    a = rec.array
    ints = np.rint(chunk.xyz / SCALE)
    if ints.min() < _INT32.min or ints.max() > _INT32.max:
        raise PointCloudError(f"{name}: coordinates lie more than 2 147 km from the LAS offset "
                              f"{list(header.offsets)} at scale {SCALE} m")
    a["X"], a["Y"], a["Z"] = ints[:, 0], ints[:, 1], ints[:, 2]
    a["gps_time"] = chunk.gps_time
    if chunk.intensity is not None:
        a["intensity"] = chunk.intensity
    # LAS 1.4 scan angle: int16 in units of 0.006°
    a["scan_angle"] = np.rint(chunk.scan_angle_deg / 0.006)
    # bit_fields: return number (bits 0-3), number of returns (bits 4-7)
    a["bit_fields"] = (chunk.return_number & 15) | ((chunk.number_of_returns & 15) << 4)
    flags = np.zeros(n, np.uint8)
    if chunk.scan_direction is not None:  # bit 6
        flags |= (chunk.scan_direction.astype(np.uint8) & 1) << 6
    if chunk.edge_of_flight_line is not None:  # bit 7
        flags |= (chunk.edge_of_flight_line.astype(np.uint8) & 1) << 7
    a["classification_flags"] = flags
    a["classification"] = chunk.classification
    a["point_source_id"] = chunk.point_source_id
    a["building_id"] = chunk.building_id
    a["grade"] = chunk.grade
    a["surface"] = chunk.surface
    return rec


def read_point_range(reader, start: int, stop: int, chunk_points: int, geometry_only: bool = False):
    """Points start..stop of an open laspy reader, chunk by chunk (at most `chunk_points`
    each): a part of a file streamed without reading the rest (LAZ seeks by its chunk table).

    A LAZ file of variable-size chunks (every COPC file) is not seeked by the LAZ backend:
    lazrs 0.8 lands on the wrong points (measured: a COPC file's points 52,148.. read from
    another place). Its chunks are found in its chunk table and decompressed here.
    `geometry_only`: a caller that reads only x, y, z, classification and the extra
    dimensions says so; such a file's other fields are then not decompressed
    (`read_laz_chunks`) and hold no meaningful values. Other files are read whole."""
    if (start or geometry_only) and _variable_size_chunks(reader):
        yield from _variable_chunk_range(reader, start, stop, chunk_points, geometry_only)
        return
    if start:
        reader.seek(start)
    yield from _read_on(reader, start, stop, chunk_points)


def _read_on(reader, start: int, stop: int, chunk_points: int):
    """The reader's points from where it stands (point `start`) to `stop`, chunk by chunk."""
    while start < stop:
        chunk = reader.read_points(min(chunk_points, stop - start))
        if not len(chunk):
            return
        start += len(chunk)
        yield chunk


def _variable_size_chunks(reader) -> bool:
    vlr = getattr(getattr(reader, "point_source", None), "vlr", None)
    try:
        return bool(vlr is not None and vlr.uses_variable_size_chunks())
    except AttributeError:
        return False


def _variable_chunk_range(reader, start: int, stop: int, chunk_points: int, geometry_only: bool = False):
    """`read_point_range` of a LAZ file of variable-size chunks: the chunks holding points
    start..stop, located by the chunk table and decompressed a few at a time (lazrs), so that
    memory holds about `chunk_points` points at once."""
    import lazrs

    vlr = reader.point_source.vlr
    name = getattr(getattr(reader, "_source", None), "name", None)
    fmt = reader.header.point_format
    if not isinstance(name, (str, os.PathLike)) or not Path(name).is_file():
        # no file to read the chunks from: decompress from the start and drop the points before it
        reader.seek(0)
        for _ in _read_on(reader, 0, start, chunk_points):
            pass
        yield from _read_on(reader, start, stop, chunk_points)
        return
    with open(name, "rb") as fh:
        fh.seek(reader.header.offset_to_point_data)
        table = [(int(n), int(b)) for n, b in lazrs.read_chunk_table(fh, vlr)]
    firsts = np.concatenate([[0], np.cumsum([n for n, _ in table])]).astype(np.int64)
    offsets = reader.header.offset_to_point_data + 8 + np.concatenate([[0], np.cumsum([b for _, b in table])])
    chunks = [(int(o), n, b) for o, (n, b) in zip(offsets, table)]
    c = int(np.searchsorted(firsts, start, side="right")) - 1
    while start < stop and c < len(table):
        c_end = c + 1
        while c_end < len(table) and firsts[c_end + 1] - firsts[c] <= chunk_points and firsts[c_end] < stop:
            c_end += 1
        points = read_laz_chunks(name, vlr.record_data(), fmt, chunks[c:c_end], geometry_only)
        points = points[start - firsts[c]:min(stop, firsts[c_end]) - firsts[c]].copy()
        start = int(min(stop, firsts[c_end]))
        c = c_end
        if len(points):
            yield laspy.ScaleAwarePointRecord(points, fmt, reader.header.scales, reader.header.offsets)


def read_laz_chunks(path, laszip_record: bytes, point_format, chunks, geometry_only: bool = False) -> np.ndarray:
    """The points of some compressed chunks of a LAZ file, as its structured point records:
    `chunks` (byte offset, point count, byte size) in the order wanted, each read and
    decompressed by lazrs. `geometry_only`: only x, y, z, classification and the extra
    dimensions are decoded (LAZ 1.4 keeps each field in a layer of its own); the other
    fields then hold no meaningful values (a chunk's first point's, stored raw)."""
    import lazrs

    out = np.zeros(sum(n for _, n, _ in chunks) * point_format.size, dtype=np.uint8)
    if len(out):
        compressed = bytearray(sum(b for _, _, b in chunks))
        view, at = memoryview(compressed), 0
        with open(path, "rb") as fh:
            for offset, _, size in chunks:
                fh.seek(offset)
                if fh.readinto(view[at:at + size]) != size:
                    raise PointCloudError(f"{path}: a LAZ chunk at byte {offset} is cut short")
                at += size
        which = lazrs.SELECTIVE_DECOMPRESS_ALL if not geometry_only else (
            lazrs.SELECTIVE_DECOMPRESS_XY_RETURNS_CHANNEL | lazrs.SELECTIVE_DECOMPRESS_Z
            | lazrs.SELECTIVE_DECOMPRESS_CLASSIFICATION | lazrs.SELECTIVE_DECOMPRESS_ALL_EXTRA_BYTES)
        lazrs.decompress_points_with_chunk_table(bytes(compressed), laszip_record, out,
                                                 [(n, b) for _, n, b in chunks], lazrs.DecompressionSelection(which))
    return out.view(point_format.dtype())


def check_point_cloud_path(path: str | os.PathLike) -> Path:
    """`path` as a Path, refused with its reason when it is a folder, a device or FIFO (a read
    would never end or never start) or does not exist."""
    path = Path(path)
    if path.is_dir():
        raise PointCloudError(f"{path}: is a folder, not a LAS/LAZ point cloud file")
    check_input_file(path, "point cloud file", PointCloudError)
    return path


def read_las(path: str | os.PathLike) -> laspy.LasData:
    path = check_point_cloud_path(path)
    try:
        return laspy.read(path)
    except Exception as e:
        raise PointCloudError(f"{path}: cannot read as LAS/LAZ ({e})") from None


def write_with_float_dims(las: laspy.LasData, out: str | os.PathLike, columns: dict, descriptions: dict) -> None:
    """Write `las` with every array of `columns` (name → one value per point) added as a
    float32 extra dimension (what CloudCompare shows as scalar fields) to `out`, LAZ when its
    suffix is .laz; the file appears only when complete. A description is cut to the 32 bytes
    LAS gives it."""
    out = Path(out)
    clash = [n for n in columns if n in set(las.point_format.dimension_names)]
    if clash:
        raise PointCloudError(f"{out}: the point cloud already has dimensions {clash}")
    las.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.float32, description=descriptions.get(n, n)[:31])
                        for n in columns])
    for n, values in columns.items():
        las[n] = np.asarray(values).astype(np.float32)
    with replacing(out) as tmp:
        las.write(tmp, do_compress=out.suffix.lower() == ".laz")


@dataclass
class Epoch:
    """One epoch's points in a local frame: world = origin + xyz (float64 throughout)."""

    xyz: np.ndarray  # (n, 3) float64, relative to origin
    origin: np.ndarray  # (3,) float64
    classification: np.ndarray  # (n,) uint8
    building_id: np.ndarray | None = None  # (n,) int32 or int64, from the file or from footprints
    grade: np.ndarray | None = None  # (n,) uint8, simulated data only
    surface: np.ndarray | None = None
    crs: str | None = None
    source: str = "epoch"

    def __len__(self):
        return len(self.xyz)

    def bounds_xy(self) -> np.ndarray:
        """(2, 2) world min/max of x and y."""
        if len(self.xyz) == 0:
            return np.full((2, 2), np.nan)
        from ..grid.cells import row_bounds  # one pass: numpy's took 3 s over a 75 M-point epoch

        return np.array(row_bounds(self.xyz[:, :2])) + self.origin[:2]


def crs_of(header, path) -> str | None:
    """The CRS a LAS header names ("EPSG:n" where it has an EPSG code, else its WKT), or None;
    an unreadable one is said on the log, not raised: the footprints or the other epoch may name it."""
    try:
        crs = header.parse_crs()
    except Exception as e:
        log.warning("%s: CRS in the header cannot be read (%s)", path, e)
        return None
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_wkt()


def check_coordinates_fit_crs(crs: str | None, mins, maxs, what: str, error=PointCloudError) -> None:
    """Refuse coordinates that cannot be in `crs`: beyond ±180 / ±90 in a geographic CRS
    (projected metres labelled as degrees: EPSG:4326 on Dutch RD coordinates)."""
    if not crs:
        return
    try:
        import pyproj

        geographic = pyproj.CRS.from_user_input(crs).is_geographic
    except Exception:
        return  # a CRS pyproj does not know: the pair's CRS comparison still applies
    if not geographic:
        return
    (x0, y0), (x1, y1) = np.asarray(mins, dtype=np.float64)[:2], np.asarray(maxs, dtype=np.float64)[:2]
    if max(abs(x0), abs(x1)) > 180 or max(abs(y0), abs(y1)) > 90:
        raise error(f"{what}: labelled {crs} (longitude/latitude in degrees) but its coordinates span x "
                    f"{x0:.1f}..{x1:.1f}, y {y0:.1f}..{y1:.1f}: projected coordinates with a wrong CRS? "
                    "Give the file its real CRS")


def _id_buffer_dtype(file_dtype) -> np.dtype:
    """Where a file's building IDs are read: in 4 bytes when the file stores them in 4 or
    fewer (QuakeScan writes uint32: a city-size epoch holds 4 bytes a point less than int64)."""
    file_dtype = np.dtype(file_dtype)
    if file_dtype.kind in "iu" and file_dtype.itemsize <= 4:
        return np.dtype(np.uint32) if file_dtype.kind == "u" else np.dtype(np.int32)
    return np.dtype(np.int64)


def checked_building_ids(values, path) -> np.ndarray:
    """A chunk of a file's `building_id` values as integers, refused where they cannot be
    building IDs: a float dimension with values that are not whole numbers (casting truncated
    a cloud of 1.5, 2.7, ... into a building per value), or above 2^63 (int64, every ID's type).
    Integer dimensions of 4 bytes or fewer come back as they are."""
    values = np.asarray(values)
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values) | (values != np.floor(values))
        if bad.any():
            first = values[np.argmax(bad)]
            raise PointCloudError(f"{path}: the building_id dimension is a float type ({values.dtype}) and "
                                  f"{int(bad.sum())} of {len(values)} values read are not whole numbers "
                                  f"(first: {first!r}); building IDs must be integers")
        if len(values) and (values.min() < -2.0 ** 63 or values.max() >= 2.0 ** 63):
            raise PointCloudError(f"{path}: building_id values reach {values.max()!r}, beyond the integers "
                                  "QuakeScan keeps IDs in (below 2^63)")
        return values.astype(np.int64)
    if values.dtype == np.uint64 and len(values) and int(values.max()) >= 2 ** 63:
        raise PointCloudError(f"{path}: building_id {int(values.max())} is 2^63 or more; QuakeScan keeps IDs in "
                              "signed 64-bit integers (below 2^63)")
    return values


def _signed_ids(ids: np.ndarray) -> np.ndarray:
    """Building IDs as a signed integer array (code takes differences and -1 marks): unsigned
    4-byte IDs below 2^31 are the same bits as int32 (a view, no copy), larger ones go to int64."""
    if ids.dtype == np.uint32:
        return ids.view(np.int32) if len(ids) == 0 or int(ids.max()) < 2 ** 31 else ids.astype(np.int64)
    return ids


def _header_origin(h) -> np.ndarray:
    origin = np.asarray(h.offsets, dtype=np.float64)
    if not np.any(origin) and int(h.point_count):
        origin = np.floor(np.asarray(h.mins, dtype=np.float64))
    return origin


def epoch_origin(path: str | os.PathLike) -> np.ndarray:
    """The local frame `read_epoch` gives the file when no origin is asked (from its header
    alone): a pair's second epoch can be read with it while the first is still being read."""
    path = check_point_cloud_path(path)
    try:
        with laspy.open(path) as reader:
            return _header_origin(reader.header)
    except Exception as e:
        raise PointCloudError(f"{path}: cannot read as LAS/LAZ ({e})") from None


def read_epoch(path: str | os.PathLike, origin=None, chunk_points: int = 4_000_000, labels: bool = True) -> Epoch:
    """Read a LAS/LAZ epoch of any point format. Coordinates go from the file's integers to
    float64 relative to `origin` (default: the file's offset, or its minimum corner when
    the offset is zero) without passing through large absolute values in float32.

    The file is read `chunk_points` records at a time into the epoch's own arrays: a whole
    file's raw records (36 bytes a point and more) are never held beside them, which halves
    the peak of a city-size pair. `labels=False` leaves out the simulator's per-point grade and
    surface (what only training and evaluation read)."""
    path = check_point_cloud_path(path)
    try:
        with laspy.open(path) as reader:
            h = reader.header
            n = int(h.point_count)
            origin = _header_origin(h) if origin is None else np.asarray(origin, dtype=np.float64)
            names = set(h.point_format.dimension_names)
            xyz = np.empty((n, 3))
            classification = np.empty(n, np.uint8)
            extras = {}
            if "building_id" in names:
                extras["building_id"] = np.empty(n, _id_buffer_dtype(h.point_format.dimension_by_name("building_id").dtype))
            for name in ("grade", "surface") if labels else ():
                if name in names:
                    extras[name] = np.empty(n, np.uint8)
            at = 0
            for chunk in reader.chunk_iterator(chunk_points):
                m = len(chunk)
                if at + m > n:
                    raise PointCloudError(f"{path}: holds more points than its header's {n}")
                for k, c in enumerate("XYZ"):
                    # integers × scale + (offset − origin): the large terms cancel before any rounding
                    xyz[at:at + m, k] = np.asarray(chunk[c], dtype=np.float64) * h.scales[k] + (h.offsets[k]
                                                                                                 - origin[k])
                classification[at:at + m] = chunk.classification
                for name, arr in extras.items():
                    arr[at:at + m] = checked_building_ids(chunk[name], path) if name == "building_id" else chunk[name]
                at += m
    except PointCloudError:
        raise
    except Exception as e:
        raise PointCloudError(f"{path}: cannot read as LAS/LAZ ({e})") from None
    if at != n:
        raise PointCloudError(f"{path}: holds {at} points, its header says {n} (the file is cut short?)")
    if "building_id" in extras:
        extras["building_id"] = _signed_ids(extras["building_id"])
    crs = crs_of(h, path)
    if n:
        from ..grid.cells import column_bounds  # one pass, where numpy's min and max read it six times

        lo, hi = column_bounds(xyz)
        check_coordinates_fit_crs(crs, lo + origin, hi + origin, str(path))
    return Epoch(xyz, origin, classification, building_id=extras.get("building_id"), grade=extras.get("grade"),
                 surface=extras.get("surface"), crs=crs, source=str(path))


ORDER_SAMPLE_POINTS = 10_000  # a flight's first returns date its start
# a post-event flight starting less than this before the pre-event one is not called early:
# two halves of one survey, or a photo flight's first images, start within seconds either way
ORDER_MARGIN_S = 600.0


def acquisition_start(path) -> dict:
    """When the epoch in `path` was acquired, as far as its file says: {"date": the header's
    creation date (ISO) or None, "gps_start": the earliest adjusted-standard GPS time of its
    first ORDER_SAMPLE_POINTS returns or None (GPS week time repeats every week: no order)}.
    Reads the header and one small chunk."""
    try:
        with laspy.open(path) as reader:
            h = reader.header
            date = h.creation_date.isoformat() if h.creation_date else None
            gps = None
            standard = h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
            if standard and "gps_time" in h.point_format.dimension_names and h.point_count:
                times = np.asarray(reader.read_points(min(ORDER_SAMPLE_POINTS, int(h.point_count))).gps_time)
                times = times[np.isfinite(times)]
                gps = float(times.min()) if len(times) else None
    except Exception:  # the reader proper says what is wrong with the file
        return {"date": None, "gps_start": None}
    return {"date": date, "gps_start": gps}


def epoch_order_warning(pre_path, post_path) -> str | None:
    """A sentence when the files say the post-event epoch was acquired before the pre-event
    one (its creation date earlier, or its flight's start in GPS time more than
    ORDER_MARGIN_S earlier): swapped epochs turn collapse into construction. None when they
    do not say so."""
    pre, post = acquisition_start(pre_path), acquisition_start(post_path)
    said = []
    if pre["date"] and post["date"] and post["date"] < pre["date"]:
        said.append(f"dated {post['date']}, the pre-event file {pre['date']}")
    if pre["gps_start"] is not None and post["gps_start"] is not None and \
            post["gps_start"] < pre["gps_start"] - ORDER_MARGIN_S:
        said.append(f"its GPS time starts {pre['gps_start'] - post['gps_start']:.0f} s before the pre-event file's")
    if not said:
        return None
    return (f"{post_path}: the post-event epoch was acquired before the pre-event epoch {pre_path} "
            f"({'; '.join(said)}): are --pre and --post swapped? Graded as given")


def noise_mask(classification) -> np.ndarray:
    """The points classified as ASPRS noise (`NOISE_CLASSES`)."""
    return np.isin(np.asarray(classification), NOISE_CLASSES)


def without_noise(epoch: Epoch) -> Epoch:
    """`epoch` without its noise returns (the same object when it has none): noise is left
    out of every surface, point feature and count."""
    noise = noise_mask(epoch.classification)
    if not noise.any():
        return epoch
    keep = ~noise
    return dataclasses.replace(epoch, xyz=epoch.xyz[keep], classification=epoch.classification[keep],
                               **{name: getattr(epoch, name)[keep] for name in ("building_id", "grade", "surface")
                                  if getattr(epoch, name) is not None})


def check_not_all_noise(n_noise: int, n: int, source) -> None:
    """Refuse a cloud whose `n` points are all noise: grading it would grade nothing as if it
    were a survey."""
    if n and n_noise == n:
        raise PointCloudError(f"{source}: every one of its {n} points is classified as noise "
                              f"(ASPRS class {' or '.join(map(str, NOISE_CLASSES))}): no surface to grade")


def set_noise_apart(epoch: Epoch) -> int:
    """Give the epoch's noise returns building ID 0 (none), so no building counts them and the
    graded cloud draws them as no building; the number of them. A cloud of nothing but noise
    is refused (`check_not_all_noise`)."""
    noise = noise_mask(epoch.classification)
    n = int(noise.sum())
    check_not_all_noise(n, len(epoch), epoch.source)
    if n and epoch.building_id is not None:
        epoch.building_id[noise] = 0
    return n


@dataclass
class HeaderFacts:
    """What a LAS/LAZ header says of its cloud without a point read."""

    path: Path
    crs: str | None
    point_count: int
    mins: np.ndarray  # x, y, z as the header gives them
    maxs: np.ndarray

    def bounds_known(self) -> bool:
        """Whether the header's extent can be trusted: some writers leave it at zero."""
        return bool(np.all(np.isfinite(self.mins[:2])) and np.all(np.isfinite(self.maxs[:2]))
                    and np.all(self.maxs[:2] >= self.mins[:2]) and np.any(self.maxs[:2] != self.mins[:2]))


def header_facts(path: str | os.PathLike) -> HeaderFacts:
    """The header of a LAS/LAZ file: its CRS, point count and extent (no point is read)."""
    path = check_point_cloud_path(path)
    try:
        with laspy.open(path) as reader:
            h = reader.header
            return HeaderFacts(path, crs_of(h, path), int(h.point_count), np.asarray(h.mins, dtype=np.float64),
                               np.asarray(h.maxs, dtype=np.float64))
    except Exception as e:
        raise PointCloudError(f"{path}: cannot read as LAS/LAZ ({e})") from None


def xy_extents_apart(lo_a, hi_a, lo_b, hi_b) -> bool:
    """Whether two x/y extents (lower and upper corners) share no point."""
    return bool(hi_a[0] < lo_b[0] or hi_b[0] < lo_a[0] or hi_a[1] < lo_b[1] or hi_b[1] < lo_a[1])


def check_same_crs(pre_crs, post_crs, pre_name, post_name) -> None:
    """Refuse a post-event epoch that names another CRS than the pre-event one."""
    if pre_crs and post_crs and pre_crs != post_crs:
        raise PointCloudError(f"{post_name}: CRS {post_crs} differs from the pre-event epoch's {pre_crs} "
                              f"({pre_name}); reproject one of them first")


def check_pair_headers(pre: HeaderFacts, post: HeaderFacts) -> None:
    """`check_pair`'s refusals that the headers alone can make, before either cloud is read (a
    pair of 2 x 75 M points takes 20 s to read, its headers milliseconds): CRS that differ, an
    empty cloud, extents that do not overlap (where both headers give one)."""
    check_same_crs(pre.crs, post.crs, pre.path, post.path)
    for h in (pre, post):
        if h.point_count == 0:
            raise PointCloudError(f"{h.path}: the point cloud is empty (its header counts no point)")
    if pre.bounds_known() and post.bounds_known() and xy_extents_apart(pre.mins, pre.maxs, post.mins, post.maxs):
        a = np.array([pre.mins[:2], pre.maxs[:2]]).round(2).tolist()
        b = np.array([post.mins[:2], post.maxs[:2]]).round(2).tolist()
        raise PointCloudError(f"{post.path}: no overlap with the pre-event epoch {pre.path} "
                              f"(x/y extents {b} vs {a}, from the files' headers)")


def check_pair(pre: Epoch, post: Epoch) -> None:
    """Refuse a pre/post pair that cannot be compared: CRS differ, or no overlap in x/y.

    One epoch with a CRS and one without (common: a photogrammetry export without CRS
    metadata) is taken as one CRS, with a warning naming both files: the overlap check
    below still refuses clouds in frames kilometres apart, and a responder should not be
    stopped by missing metadata. Both epochs then carry the known CRS (the outputs' CRS)."""
    check_same_crs(pre.crs, post.crs, pre.source, post.source)
    if bool(pre.crs) != bool(post.crs):
        known, unknown = (pre, post) if pre.crs else (post, pre)
        log.warning("%s names no CRS but %s is in %s: taking both as %s (their x/y extents overlap); "
                    "if they are not, reproject one of them", unknown.source, known.source, known.crs, known.crs)
        unknown.crs = known.crs
    for e in (pre, post):
        if len(e) == 0:
            raise PointCloudError(f"{e.source}: the point cloud is empty")
    a, b = pre.bounds_xy(), post.bounds_xy()
    if xy_extents_apart(a[0], a[1], b[0], b[1]):
        raise PointCloudError(f"{post.source}: no overlap with the pre-event epoch {pre.source} "
                              f"(x/y extents {b.round(2).tolist()} vs {a.round(2).tolist()})")
