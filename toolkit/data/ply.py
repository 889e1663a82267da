"""Minimal PLY point-cloud I/O (vertex positions only), ASCII and binary, no dependencies.

Reads the ``x``, ``y``, ``z`` properties of the ``vertex`` element of files written by trimesh,
open3d, Taichi's ``PLYWriter`` or plyfile (other properties and later elements such as faces are
ignored; elements *before* ``vertex`` must have fixed-size properties). Writes binary
little-endian float32 (or float64) ``x y z``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.data.errors import DatasetError, require_file

__all__ = ["read_ply_points", "write_ply_points"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_header(data: bytes, path: Path) -> tuple[str, list[tuple[str, int, list]], int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path} is not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = data.index(b"\n", end) + 1
    fmt, elements = None, []
    for raw in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            elif words[1] in _TYPES:
                elements[-1][2].append((words[2], _TYPES[words[1]]))
            else:
                raise DatasetError(f"{path}: unknown PLY property type {words[1]!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, body_start


def read_ply_points(path: str | Path) -> np.ndarray:
    """Vertex positions of a PLY file as an (N, 3) float64 array."""
    path = Path(path)
    require_file(path, "a PLY point cloud")
    data = path.read_bytes()
    fmt, elements, offset = _parse_header(data, path)
    endian = ">" if fmt == "binary_big_endian" else "<"
    lines = data[offset:].decode("ascii", errors="replace").split("\n") if fmt == "ascii" else None
    line_no = 0
    for name, count, props in elements:
        if name != "vertex" and any(t is None for _, t in props):
            raise DatasetError(f"{path}: element {name!r} with list properties precedes 'vertex'")
        names = [p for p, _ in props]
        if name == "vertex" and any(t is None for _, t in props):
            raise DatasetError(f"{path}: list properties in the vertex element are not supported")
        if fmt == "ascii":
            rows = lines[line_no : line_no + count]
            line_no += count
            if name != "vertex":
                continue
            try:
                table = np.array([r.split() for r in rows], dtype=np.float64).reshape(count, len(props))
            except ValueError:
                raise DatasetError(f"{path}: malformed ASCII vertex rows") from None
            cols = {n: table[:, i] for i, n in enumerate(names)}
        else:
            dtype = np.dtype([(n, endian + t) for n, t in props])
            if offset + dtype.itemsize * count > len(data):
                raise DatasetError(f"{path}: file is truncated in element {name!r}")
            table = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
            if name != "vertex":
                continue
            cols = {n: table[n] for n in names}
        if not {"x", "y", "z"} <= set(cols):
            raise DatasetError(f"{path}: vertex element has no x, y, z properties ({names})")
        return np.stack([cols["x"], cols["y"], cols["z"]], axis=-1).astype(np.float64)
    raise DatasetError(f"{path}: no 'vertex' element")


def write_ply_points(path: str | Path, points, *, double: bool = False) -> Path:
    """Write (N, 3) points as a binary little-endian PLY; returns the path."""
    pts = np.asarray(points, dtype=np.float64 if double else np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    kind = "double" if double else "float"
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {pts.shape[0]}\n"
        f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + pts.astype("<" + pts.dtype.str[1:]).tobytes())
    return path
