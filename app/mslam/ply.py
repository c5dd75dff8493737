"""PLY point clouds: the map a run exports and the clouds the evaluation reads (docs/upstream.md §13).

A run writes upstream's ``save_ply`` layout: binary little-endian, vertex ``x y z`` float32 and
``red green blue`` uchar. Ground-truth clouds come from elsewhere (scanner exports, meshes
converted by other tools), so the reader takes any of the three PLY encodings (``ascii``,
``binary_little_endian``, ``binary_big_endian``), any scalar property types, extra properties
(normals, alpha, confidence) and elements after ``vertex`` (faces). Colours are optional: a
cloud without them reads as mid-grey.

The writer goes through :func:`mslam.atomic.write_atomic` (temporary file + rename), so an
error never leaves a partial file. The reader raises ``ValueError("<file>[:<line>]: <what>")``
on a malformed file and ``FileNotFoundError`` on a missing one.

Public functions: write_ply, read_ply

Upstream: mast3r_slam/evaluate.py (save_ply) — layout re-implemented from its description.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mslam.atomic import write_atomic
from mslam_ref.conventions import as_float_array

__all__ = ["read_ply", "write_ply"]

#: PLY scalar type names (both spellings of the standard) -> NumPy type codes without byte order.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

#: PLY encodings the reader takes -> NumPy byte order ("" for text).
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}

#: The colour a point without ``red green blue`` properties reads as.
GREY = 128


def write_ply(path: str | Path, xyz: Any, rgb: Any) -> None:
    """Write a coloured point cloud as a binary little-endian PLY, atomically.

    Upstream: mast3r_slam/evaluate.py::save_ply (vertex x, y, z float; red, green, blue uchar).

    Args:
        path: output file (parent folders are created).
        xyz: (N, 3) finite points (stored as float32).
        rgb: (N, 3) colours, integers in [0, 255] (stored as uint8).

    Raises:
        ValueError: on bad shapes, non-finite points or colours outside [0, 255].
    """
    xyz = as_float_array(xyz, "xyz", 3)
    rgb_arr = np.asarray(rgb)
    if xyz.ndim != 2:
        raise ValueError(f"xyz: expected shape (N, 3), got {xyz.shape}")
    if rgb_arr.shape != xyz.shape:
        raise ValueError(f"rgb: expected shape {xyz.shape} to match xyz, got {rgb_arr.shape}")
    if rgb_arr.size and (
        not np.all(np.isfinite(rgb_arr)) or rgb_arr.min() < 0 or rgb_arr.max() > 255
    ):
        raise ValueError("rgb: colours must be finite and in [0, 255]")
    if np.any(np.abs(xyz) > np.finfo(np.float32).max):
        raise ValueError("xyz: values overflow float32")
    n = len(xyz)
    vertex = np.empty(
        n,
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
               ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )  # fmt: skip
    vertex["x"], vertex["y"], vertex["z"] = xyz.astype(np.float32).T
    rgb_u8 = (
        np.rint(rgb_arr).astype(np.uint8) if rgb_arr.dtype.kind == "f" else rgb_arr.astype(np.uint8)
    )
    vertex["red"], vertex["green"], vertex["blue"] = rgb_u8.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    )
    write_atomic(path, header.encode("ascii") + vertex.tobytes())


def _parse_header(path: Path, header: list[str]) -> tuple[str, int, list[tuple[str, str]]]:
    """(byte order, vertex count, [(name, type code)]) of a PLY header's lines.

    The vertex element must come first: the reader stops after it.
    """
    order, n_vertex, fields, in_vertex = None, None, [], False
    for k, line in enumerate(header, start=1):
        tok = line.split()
        if not tok or tok[0] in ("ply", "comment", "obj_info"):
            continue
        if tok[0] == "format":
            if tok[1:2] == [] or tok[1] not in _FORMATS:
                raise ValueError(f"{path}:{k}: unsupported PLY format {line!r}")
            order = _FORMATS[tok[1]]
        elif tok[0] == "element":
            if n_vertex is None and tok[1:2] != ["vertex"]:
                raise ValueError(f"{path}:{k}: the first element must be 'vertex', got {line!r}")
            in_vertex = tok[1:2] == ["vertex"]
            if in_vertex:
                try:
                    n_vertex = int(tok[2])
                except (IndexError, ValueError):
                    raise ValueError(f"{path}:{k}: bad element line {line!r}") from None
        elif tok[0] == "property" and in_vertex:
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise ValueError(f"{path}:{k}: unsupported vertex property {line!r}")
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
    if order is None or n_vertex is None:
        raise ValueError(f"{path}: PLY header lacks a format or a vertex element")
    names = [f[0] for f in fields]
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: PLY vertices need x, y, z; got {names}")
    return order, n_vertex, fields


def _ascii_vertices(path: Path, body: bytes, n: int, names: list[str]) -> dict[str, np.ndarray]:
    """Columns of the first ``n`` data lines of an ASCII PLY body, by property name."""
    lines = body.decode("ascii", errors="replace").splitlines()[:n]
    if len(lines) < n:
        raise ValueError(f"{path}: truncated PLY: {n} vertices, found {len(lines)} lines")
    try:
        table = np.array([ln.split()[: len(names)] for ln in lines], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{path}: a vertex line is not {len(names)} numbers") from None
    if table.shape != (n, len(names)):
        raise ValueError(f"{path}: a vertex line has fewer than {len(names)} numbers")
    return {name: table[:, i] for i, name in enumerate(names)}


def read_ply(path: str | Path) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
    """Read the vertices of a PLY point cloud or mesh: positions and colours.

    Takes ASCII, binary little- and big-endian files; any scalar vertex properties (only
    ``x y z`` are required); elements after ``vertex`` are ignored.

    Args:
        path: the file.

    Returns:
        xyz (N, 3) float32 and rgb (N, 3) uint8 (:data:`GREY` where the file has no
        ``red green blue``; float colours in [0, 1] are scaled to [0, 255]).

    Raises:
        ValueError: naming the file on a bad header, an unsupported format or truncated data.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[data.index(b"\n", end) + 1 :] if b"\n" in data[end:] else b""
    order, n, fields = _parse_header(path, header)
    names = [f[0] for f in fields]
    if order:
        dtype = np.dtype([(name, order + code) for name, code in fields])
        if len(body) < n * dtype.itemsize:
            raise ValueError(
                f"{path}: truncated PLY: {n} vertices need {n * dtype.itemsize} "
                f"bytes, found {len(body)}"
            )
        v = np.frombuffer(body, dtype=dtype, count=n)
        cols: dict[str, np.ndarray] = {name: v[name] for name in names}
    else:
        cols = _ascii_vertices(path, body, n, names)
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
    if not {"red", "green", "blue"} <= set(names):
        return xyz, np.full((n, 3), GREY, np.uint8)
    rgb = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).astype(np.float64)
    if dict(fields)["red"].startswith("f"):
        rgb = rgb * 255.0
    return xyz, np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
