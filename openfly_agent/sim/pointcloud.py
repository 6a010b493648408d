"""Point clouds: sampling box surfaces, and reading / writing PCD (ASCII, binary) and PLY (ASCII, binary).

Points are (N, 3) x, y, z in metres. Files are written as float32; readers accept any numeric field
types, extra fields (intensity, rgb, normals, ...) and return float64 x, y, z, dropping NaN rows.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


class PointCloudError(ValueError):
    """A malformed point-cloud file; the message names the file and the field."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = str(path)


# --- sampling ---------------------------------------------------------------------------------------


def _face_grid(a_lo: float, a_hi: float, b_lo: float, b_hi: float, spacing: float):
    """Grid samples of a rectangle including its edges: (M,) a and (M,) b coordinates."""
    na = max(2, math.ceil((a_hi - a_lo) / spacing) + 1)
    nb = max(2, math.ceil((b_hi - b_lo) / spacing) + 1)
    ga, gb = np.meshgrid(np.linspace(a_lo, a_hi, na), np.linspace(b_lo, b_hi, nb), indexing="ij")
    return ga.ravel(), gb.ravel()


def sample_box_surfaces(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Samples <= `spacing` apart on the 4 walls and the top of each box: (P, 3) lo / hi -> (N, 3) float64.

    Bottom faces are skipped (they rest on the ground or on another part). Edges are always sampled, so
    thin parts (masts, billboards) are never missed by a voxel grid of the same spacing.
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    chunks = []
    for (x0, y0, z0), (x1, y1, z1) in zip(np.asarray(lo, np.float64), np.asarray(hi, np.float64)):
        gx, gz = _face_grid(x0, x1, z0, z1, spacing)
        chunks += [np.stack([gx, np.full_like(gx, y), gz], 1) for y in (y0, y1)]  # south / north walls
        gy, gz = _face_grid(y0, y1, z0, z1, spacing)
        chunks += [np.stack([np.full_like(gy, x), gy, gz], 1) for x in (x0, x1)]  # west / east walls
        gx, gy = _face_grid(x0, x1, y0, y1, spacing)
        chunks.append(np.stack([gx, gy, np.full_like(gx, z1)], 1))  # roof
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


# --- PCD --------------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip


def _as_points(points) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    return np.ascontiguousarray(points, dtype=np.float32)


def write_pcd(path, points, binary: bool = True) -> None:
    """Write (N, 3) points as a PCD v0.7 file with float32 x y z, DATA binary or ascii."""
    pts = _as_points(points)
    n = len(pts)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(pts.astype("<f4").tobytes())
        elif n:
            np.savetxt(f, pts, fmt="%.9g")


def _pcd_header(path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    """Header fields and the byte offset where the data starts."""
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise PointCloudError(path, "header has no DATA line")
        line = raw[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, offset


def _pcd_layout(path, header: dict[str, list[str]]):
    fields = header.get("FIELDS")
    if not fields:
        raise PointCloudError(path, "header field FIELDS is missing")
    sizes = header.get("SIZE", ["4"] * len(fields))
    types = header.get("TYPE", ["F"] * len(fields))
    counts = header.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise PointCloudError(path, "header fields FIELDS / SIZE / TYPE / COUNT have different lengths")
    for axis in "xyz":
        if axis not in fields:
            raise PointCloudError(path, f"header field FIELDS has no '{axis}' (got {fields})")
    dtype_fields = []
    for k, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts)):
        code = _PCD_TYPES.get((kind.upper(), int(size)))
        if code is None:
            raise PointCloudError(
                path, f"header fields TYPE/SIZE: unsupported {kind}{size} for field '{name}'"
            )
        unique = name if name != "_" else f"_pad{k}"
        dtype_fields.append((unique, "<" + code, (int(count),)) if int(count) > 1 else (unique, "<" + code))
    try:
        n_points = int(header.get("POINTS", [None])[0] or int(header["WIDTH"][0]) * int(header["HEIGHT"][0]))
    except (KeyError, ValueError) as err:
        raise PointCloudError(
            path, "header field POINTS (or WIDTH x HEIGHT) is missing or not an integer"
        ) from err
    return np.dtype(dtype_fields), n_points


def read_pcd(path) -> np.ndarray:
    """Read x, y, z of a PCD file (DATA ascii or binary) -> (N, 3) float64; NaN points are dropped."""
    raw = Path(path).read_bytes()
    header, offset = _pcd_header(path, raw)
    dtype, n = _pcd_layout(path, header)
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "binary":
        if len(raw) - offset < n * dtype.itemsize:
            raise PointCloudError(
                path, f"DATA binary holds {len(raw) - offset} bytes, expected {n * dtype.itemsize}"
            )
        rec = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
        xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    elif mode == "ascii":
        columns = []
        for name in dtype.names:
            shape = dtype[name].shape
            columns += [name] * (shape[0] if shape else 1)
        values = np.array(raw[offset:].split(), dtype=np.float64)
        if values.size != n * len(columns):
            raise PointCloudError(
                path, f"DATA ascii holds {values.size} values, expected {n} x {len(columns)}"
            )
        table = values.reshape(n, len(columns))
        # parse at the declared type, so float32 files read back exactly as written
        xyz = np.stack([table[:, columns.index(a)].astype(dtype[a].base) for a in "xyz"], 1).astype(
            np.float64
        )
    elif mode == "binary_compressed":
        raise PointCloudError(
            path, "DATA binary_compressed is not supported; convert it first, e.g. with PCL "
            "`pcl_convert_pcd_ascii_binary in.pcd out.pcd 1` (binary) or open3d",
        )  # fmt: skip
    else:
        raise PointCloudError(path, f"header field DATA has unknown mode {mode!r} (ascii | binary)")
    return xyz[np.isfinite(xyz).all(axis=1)]


# --- PLY --------------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}  # fmt: skip


def write_ply(path, points, binary: bool = True) -> None:
    """Write (N, 3) points as a PLY file with one `vertex` element of float x y z."""
    pts = _as_points(points)
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment openfly_agent point cloud, metres\nelement vertex {len(pts)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(pts.astype("<f4").tobytes())
        elif len(pts):
            np.savetxt(f, pts, fmt="%.9g")


def _ply_header(path, raw: bytes):
    """(format, [(element name, count, [(prop name, type or None for lists)])], data offset)."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise PointCloudError(path, "not a PLY file (missing 'ply' magic or 'end_header')")
    offset = raw.find(b"\n", end) + 1
    fmt, elements = None, []
    for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
        tokens = line.split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        if tokens[0] == "format":
            fmt = tokens[1]
        elif tokens[0] == "element":
            elements.append((tokens[1], int(tokens[2]), []))
        elif tokens[0] == "property" and elements:
            if tokens[1] == "list":
                elements[-1][2].append((tokens[-1], None))
            elif tokens[1] in _PLY_TYPES:
                elements[-1][2].append((tokens[2], _PLY_TYPES[tokens[1]]))
            else:
                raise PointCloudError(path, f"property {tokens[-1]!r} has unknown type {tokens[1]!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PointCloudError(
            path, f"header field format is {fmt!r} (ascii | binary_little_endian | big_endian)"
        )
    return fmt, elements, offset


def read_ply(path) -> np.ndarray:
    """Read x, y, z of the `vertex` element of a PLY file -> (N, 3) float64; NaN points are dropped."""
    raw = Path(path).read_bytes()
    fmt, elements, offset = _ply_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise PointCloudError(path, f"no 'vertex' element (elements: {names})")
    before = elements[: names.index("vertex")]
    _, n, props = elements[names.index("vertex")]
    prop_names = [p[0] for p in props]
    for axis in "xyz":
        if axis not in prop_names:
            raise PointCloudError(path, f"element vertex has no property '{axis}' (got {prop_names})")
    if any(t is None for _, t in props) or (
        fmt != "ascii" and any(t is None for e in before for _, t in e[2])
    ):
        raise PointCloudError(path, "list properties before or inside element vertex are not supported")
    if fmt == "ascii":
        lines = raw[offset:].splitlines()
        skip = sum(e[1] for e in before)
        rows = lines[skip : skip + n]
        if len(rows) < n:
            raise PointCloudError(path, f"element vertex declares {n} rows, file holds {len(rows)}")
        table = np.array(b" ".join(rows).split(), dtype=np.float64).reshape(n, len(props))
        types = dict(props)
        xyz = np.stack([table[:, prop_names.index(a)].astype(types[a]) for a in "xyz"], 1).astype(np.float64)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        for _, count, eprops in before:
            offset += count * np.dtype([(p, order + t) for p, t in eprops]).itemsize
        dtype = np.dtype([(p, order + t) for p, t in props])
        if len(raw) - offset < n * dtype.itemsize:
            raise PointCloudError(path, f"element vertex needs {n * dtype.itemsize} bytes, file holds fewer")
        rec = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
        xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


# --- by file name -------------------------------------------------------------------------------------


def write_points(path, points, binary: bool = True) -> None:
    """Write a .pcd or .ply file, chosen by the suffix of `path`."""
    suffix = Path(path).suffix.lower()
    if suffix == ".pcd":
        write_pcd(path, points, binary)
    elif suffix == ".ply":
        write_ply(path, points, binary)
    else:
        raise ValueError(f"{path}: unknown point-cloud suffix {suffix!r} (use .pcd or .ply)")


def read_points(path) -> np.ndarray:
    """Read a .pcd or .ply file, chosen by the suffix of `path`."""
    suffix = Path(path).suffix.lower()
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix == ".ply":
        return read_ply(path)
    raise ValueError(f"{path}: unknown point-cloud suffix {suffix!r} (use .pcd or .ply)")
