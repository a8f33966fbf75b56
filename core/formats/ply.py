"""Binary PLY for scene meshes: double vertices, faces with building_id and surface
(and, optionally, `porous`: uchar 1 on tree-crown faces a laser ray may pass).

Writes exactly the layout of the scene contract (docs/DESIGN.md). Reads that layout and the
variations other tools produce (float vertices, other list/index integer types, big
endian, extra properties, polygons); polygons are fan-triangulated on read.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..runtime.atomic import open_replacing

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


@dataclass
class MeshArrays:
    """Triangle mesh with per-face labels, as stored in mesh.ply."""

    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    building_id: np.ndarray  # (m,) int32
    surface: np.ndarray  # (m,) uint8
    porous: np.ndarray | None = None  # (m,) bool, None when the file has no `porous` property


def write_ply(path: str | os.PathLike, mesh: MeshArrays, comment: str = "quakescan scene mesh") -> None:
    """Write the contract's binary little-endian PLY atomically (temp file + rename)."""
    path = Path(path)
    vertices = np.ascontiguousarray(mesh.vertices, dtype="<f8")
    faces = np.asarray(mesh.faces)
    m = len(faces)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {comment}\n"
        f"element vertex {len(vertices)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {m}\n"
        "property list uchar int vertex_indices\n"
        "property int building_id\n"
        "property uchar surface\n"
        + ("property uchar porous\n" if mesh.porous is not None else "")
        + "end_header\n"
    ).encode("ascii")
    fields = [("n", "u1"), ("v", "<i4", (3,)), ("building_id", "<i4"), ("surface", "u1")]
    if mesh.porous is not None:  # written only when asked: meshes without vegetation keep their bytes
        fields.append(("porous", "u1"))
    records = np.empty(m, dtype=np.dtype(fields))
    records["n"] = 3
    records["v"] = faces
    records["building_id"] = mesh.building_id
    records["surface"] = mesh.surface
    if mesh.porous is not None:
        records["porous"] = mesh.porous
    with open_replacing(path, "wb", SceneError) as f:
        f.write(header)
        f.write(vertices.tobytes())
        f.write(records.tobytes())


def _parse_header(path: Path, raw: bytes):
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise SceneError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    nl = raw.find(b"\n", end)
    body_start = nl + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[dict] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append({"name": words[1], "count": int(words[2]), "props": []})
        elif words[0] == "property":
            if not elements:
                raise SceneError(f"{path}: PLY property before any element")
            if words[1] == "list":
                elements[-1]["props"].append((words[4], ("list", _type(path, words[2]), _type(path, words[3]))))
            else:
                elements[-1]["props"].append((words[2], _type(path, words[1])))
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise SceneError(f"{path}: PLY format {fmt!r} is not supported; write binary_little_endian "
                         "(the scene contract's format)")
    return ("<" if fmt == "binary_little_endian" else ">"), elements, body_start


def _type(path: Path, name: str) -> str:
    try:
        return _PLY_TYPES[name]
    except KeyError:
        raise SceneError(f"{path}: unknown PLY property type {name!r}") from None


def read_ply(path: str | os.PathLike) -> MeshArrays:
    """Read a scene mesh; raise SceneError naming the file on anything malformed."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise SceneError(f"{path}: mesh file is missing") from None
    endian, elements, pos = _parse_header(path, raw)
    data = memoryview(raw)
    vertices = faces = building_id = surface = porous = None
    for el in elements:
        name, count, props = el["name"], el["count"], el["props"]
        has_list = any(isinstance(t, tuple) for _, t in props)
        if not has_list:
            dtype = np.dtype([(p, endian + t) for p, t in props])
            need = dtype.itemsize * count
            if pos + need > len(raw):
                raise SceneError(f"{path}: file ends inside element {name!r} "
                                 f"({len(raw) - pos} bytes left, {need} needed)")
            arr = np.frombuffer(data[pos:pos + need], dtype=dtype, count=count)
            pos += need
            if name == "vertex":
                missing = [c for c in "xyz" if c not in dtype.names]
                if missing:
                    raise SceneError(f"{path}: vertex element lacks {','.join(missing)}")
                vertices = np.column_stack([arr[c].astype(np.float64) for c in "xyz"])
            continue
        arr, pos = _read_list_element(path, data, pos, endian, name, count, props)
        if name == "face":
            faces, building_id, surface, porous = arr
    if vertices is None:
        raise SceneError(f"{path}: no vertex element")
    if faces is None:
        raise SceneError(f"{path}: no face element")
    return MeshArrays(vertices, faces, building_id, surface, porous)


def _read_list_element(path, data, pos, endian, name, count, props):
    """Read an element holding a list property (faces). Fast path when all lists are
    equally long; otherwise a record-by-record walk with fan triangulation."""
    if name != "face":
        raise SceneError(f"{path}: element {name!r} with list properties is not supported")
    list_props = [p for p, t in props if isinstance(t, tuple)]
    if list_props not in (["vertex_indices"], ["vertex_index"]):
        raise SceneError(f"{path}: face element must have exactly one list 'vertex_indices', "
                         f"found {list_props}")
    prop_names = [p for p, _ in props]
    for needed in ("building_id", "surface"):
        if needed not in prop_names:
            raise SceneError(f"{path}: face element lacks property {needed!r} (scene contract)")
    has_porous = "porous" in prop_names
    if count == 0:
        empty = np.zeros((0, 3), np.int64)
        return (empty, np.zeros(0, np.int32), np.zeros(0, np.uint8), np.zeros(0, bool) if has_porous else None), pos
    first_len_type = next(t for _, t in props if isinstance(t, tuple))[1]
    # Probe the first record's list length, assume it is uniform, verify.
    fields_before = []
    for p, t in props:
        if isinstance(t, tuple):
            break
        fields_before.append((p, endian + t))
    probe_off = pos + sum(np.dtype(t).itemsize for _, t in fields_before)
    n0 = int(np.frombuffer(data[probe_off:probe_off + np.dtype(first_len_type).itemsize],
                           dtype=endian + first_len_type)[0])
    fields = []
    for p, t in props:
        if isinstance(t, tuple):
            fields.append(("__n", endian + t[1]))
            fields.append(("__v", endian + t[2], (n0,)))
        else:
            fields.append((p, endian + t))
    dtype = np.dtype(fields)
    need = dtype.itemsize * count
    if n0 >= 3 and pos + need <= len(data):
        arr = np.frombuffer(data[pos:pos + need], dtype=dtype, count=count)
        if np.all(arr["__n"] == n0):
            polys = arr["__v"].astype(np.int64)
            faces, owner = _fan(polys)
            return (faces, arr["building_id"][owner].astype(np.int32), arr["surface"][owner].astype(np.uint8),
                    arr["porous"][owner] != 0 if has_porous else None), pos + need
    return _read_faces_slow(path, data, pos, endian, count, props)


def _fan(polys: np.ndarray):
    """Fan-triangulate (m, k) polygons → (m*(k-2), 3) triangles and the owning polygon."""
    m, k = polys.shape
    if k == 3:
        return polys, np.arange(m)
    tris = np.stack([np.repeat(polys[:, :1], k - 2, 1), polys[:, 1:-1], polys[:, 2:]], axis=2)
    return tris.reshape(-1, 3), np.repeat(np.arange(m), k - 2)


def _read_faces_slow(path, data, pos, endian, count, props):
    tris, bids, surfs, porous = [], [], [], []
    has_porous = any(p == "porous" for p, _ in props)
    for i in range(count):
        values = {}
        for p, t in props:
            if isinstance(t, tuple):
                lt, it = np.dtype(endian + t[1]), np.dtype(endian + t[2])
                if pos + lt.itemsize > len(data):
                    raise SceneError(f"{path}: file ends inside face {i}")
                n = int(np.frombuffer(data[pos:pos + lt.itemsize], dtype=lt)[0])
                pos += lt.itemsize
                if n < 3:
                    raise SceneError(f"{path}: face {i} has {n} vertices (need at least 3)")
                if pos + n * it.itemsize > len(data):
                    raise SceneError(f"{path}: file ends inside face {i}")
                values[p] = np.frombuffer(data[pos:pos + n * it.itemsize], dtype=it).astype(np.int64)
                pos += n * it.itemsize
            else:
                dt = np.dtype(endian + t)
                if pos + dt.itemsize > len(data):
                    raise SceneError(f"{path}: file ends inside face {i}")
                values[p] = np.frombuffer(data[pos:pos + dt.itemsize], dtype=dt)[0]
                pos += dt.itemsize
        poly = values.get("vertex_indices", values.get("vertex_index"))
        for j in range(1, len(poly) - 1):
            tris.append((poly[0], poly[j], poly[j + 1]))
            bids.append(values["building_id"])
            surfs.append(values["surface"])
            porous.append(values.get("porous", 0))
    return (np.array(tris, np.int64).reshape(-1, 3), np.array(bids, np.int32),
            np.array(surfs, np.uint8), np.array(porous) != 0 if has_porous else None), pos
