"""Reading point files on the robot without open3d, so the CLI can send compact float32 points.

The SDK must not pull in open3d or trimesh, yet the commonest capture formats are simple enough to
read with numpy: ``.npy``, whitespace- or comma-separated ``.xyz`` text, and the vertex x/y/z of
ASCII or binary ``.ply``. Anything else (``.pcd``, a PLY whose vertices are interleaved with list
properties in binary) raises :class:`UnsupportedFileError`, and the CLI uploads the file for the
server to parse instead.
"""

from __future__ import annotations

import io
import math
import struct
from pathlib import Path
from tokenize import TokenError
from typing import BinaryIO

import numpy as np

from ._exceptions import InvalidPointsError

LOCAL_SUFFIXES = (".npy", ".xyz", ".ply")

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


class UnsupportedFileError(Exception):
    """This reader cannot parse the file; the server may (upload it instead)."""


def read_points(path: str | Path) -> np.ndarray:
    """The x/y/z columns of a ``.npy``, ``.xyz`` or ``.ply`` file as an (N, 3) float64 array."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return _read_npy(path)
    if suffix == ".xyz":
        return _read_xyz(path)
    if suffix == ".ply":
        return _read_ply(path)
    raise UnsupportedFileError(f"{path.name}: no local reader for {suffix or 'no suffix'}")


def _read_npy(path: Path) -> np.ndarray:
    try:
        with path.open("rb") as handle:
            _check_npy_header(path.name, handle, path.stat().st_size)
            array = np.load(handle, allow_pickle=False)
    except (ValueError, SyntaxError, TypeError, OverflowError, RecursionError, TokenError) as exc:
        raise InvalidPointsError(f"{path.name}: not a plain numeric .npy array: {exc}") from exc
    if array.ndim != 2 or array.shape[1] < 3:
        raise InvalidPointsError(f"{path.name}: expected an (N, 3) array, got shape {array.shape}")
    if array.dtype.kind not in "biuf":
        raise InvalidPointsError(f"{path.name}: expected numbers, got an array of {array.dtype}")
    return np.asarray(array[:, :3], dtype=np.float64)


def _check_npy_header(name: str, handle: BinaryIO, size: int) -> None:
    """Refuse a header whose length or array the file's size cannot hold, before numpy
    allocates either; leaves ``handle`` at the start of the file."""
    fmt = np.lib.format
    version = fmt.read_magic(handle)
    if version not in ((1, 0), (2, 0), (3, 0)):
        raise InvalidPointsError(f"{name}: unknown .npy format version {version}")
    layout = "<H" if version == (1, 0) else "<I"
    length = handle.read(struct.calcsize(layout))
    if len(length) < struct.calcsize(layout) or struct.unpack(layout, length)[0] > size:
        raise InvalidPointsError(f"{name}: the .npy header is longer than the file")
    handle.seek(len(fmt.MAGIC_PREFIX) + 2)
    read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, _, dtype = read_header(handle)
    declared = math.prod(shape) * dtype.itemsize
    if declared != size - handle.tell():
        raise InvalidPointsError(
            f"{name}: the .npy header declares {declared} bytes of data, "
            f"but the file holds {size - handle.tell()}"
        )
    handle.seek(0)


def _read_xyz(path: Path) -> np.ndarray:
    text = path.read_text(encoding="utf-8", errors="replace").replace(",", " ")
    try:
        array = np.loadtxt(io.StringIO(text), comments="#", usecols=(0, 1, 2), ndmin=2)
    except ValueError as exc:
        raise InvalidPointsError(f"{path.name}: not x y z text rows: {exc}") from exc
    return array.reshape(-1, 3)


def _read_ply(path: Path) -> np.ndarray:
    data = path.read_bytes()
    header, body = _split_ply_header(path.name, data)
    fmt, elements = _parse_ply_header(path.name, header)
    names = [name for name, _, _ in elements]
    if "vertex" not in names:
        raise InvalidPointsError(f"{path.name}: PLY has no vertex element")
    index = names.index("vertex")
    count, properties = elements[index][1], elements[index][2]
    prop_names = [p[0] for p in properties]
    if not {"x", "y", "z"} <= set(prop_names):
        raise InvalidPointsError(f"{path.name}: PLY vertices lack x, y or z")
    if fmt == "ascii":
        if any(kind is None for _, kind in properties[: max(map(prop_names.index, "xyz"))]):
            raise UnsupportedFileError(f"{path.name}: PLY with list properties before x, y, z")
        return _ply_ascii(path.name, body, elements[:index], count, prop_names)
    if any(kind is None for _, _, props in elements[: index + 1] for _, kind in props):
        raise UnsupportedFileError(f"{path.name}: binary PLY with list properties before x, y, z")
    endian = _PLY_FORMATS[fmt]
    offset = sum(n * _row_dtype(props, endian).itemsize for _, n, props in elements[:index])
    dtype = _row_dtype(properties, endian)
    if len(body) < offset + count * dtype.itemsize:
        raise InvalidPointsError(f"{path.name}: PLY is truncated ({count} vertices declared)")
    rows = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
    return np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float64)


_PlyProperty = tuple[str, str | None]  # name, numpy type code (None for a list property)
_PlyElement = tuple[str, int, list[_PlyProperty]]


def _split_ply_header(name: str, data: bytes) -> tuple[str, bytes]:
    if not data.startswith(b"ply"):
        raise InvalidPointsError(f"{name}: not a PLY file (no 'ply' magic)")
    for marker in (b"end_header\r\n", b"end_header\n"):
        at = data.find(marker)
        if at >= 0:
            return data[:at].decode("ascii", errors="replace"), data[at + len(marker) :]
    raise InvalidPointsError(f"{name}: PLY header has no end_header line")


def _parse_ply_header(name: str, header: str) -> tuple[str, list[_PlyElement]]:
    fmt = ""
    elements: list[_PlyElement] = []
    for line in header.splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) >= 3:
            prop = words[-1] if words[1] == "list" else words[2]
            if any(prop == known for known, _ in elements[-1][2]):
                raise InvalidPointsError(
                    f"{name}: PLY element {elements[-1][0]!r} has two properties named {prop!r}"
                )
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            elif words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise InvalidPointsError(f"{name}: unknown PLY property type {words[1]!r}")
        else:
            raise InvalidPointsError(f"{name}: bad PLY header line {line!r}")
    if fmt not in _PLY_FORMATS:
        raise InvalidPointsError(f"{name}: unknown PLY format {fmt!r}")
    return fmt, elements


def _row_dtype(properties: list[_PlyProperty], endian: str) -> np.dtype:
    return np.dtype([(prop, endian + str(kind)) for prop, kind in properties])


def _ply_ascii(
    name: str, body: bytes, before: list[_PlyElement], count: int, prop_names: list[str]
) -> np.ndarray:
    lines = body.decode("ascii", errors="replace").splitlines()
    start = sum(n for _, n, _ in before)
    rows = lines[start : start + count]
    if len(rows) < count:
        raise InvalidPointsError(f"{name}: PLY is truncated ({count} vertices declared)")
    columns = [prop_names.index(axis) for axis in "xyz"]
    try:
        values = [row.split() for row in rows]
        return np.array([[float(v[c]) for c in columns] for v in values]).reshape(-1, 3)
    except (IndexError, ValueError) as exc:
        raise InvalidPointsError(f"{name}: bad PLY vertex row: {exc}") from exc
