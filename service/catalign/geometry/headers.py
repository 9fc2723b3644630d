"""Check what a shape file declares before any reader allocates memory for it.

Readers trust headers: Open3D sizes its point arrays from a PCD's ``POINTS`` line, numpy from a
``.npy`` shape, trimesh from a GLB accessor's ``count``. A 59-byte PCD that claims a billion
points makes the reader ask for 24 GB before it finds out that the data is not there, and the
server is killed. The checks here run first: they read only a bounded prefix of a file (or, for
formats that declare nothing, stream it in chunks and count lines), compare every declared count
with what the file's size on disk can hold and with optional limits, and raise
:class:`~catalign.errors.ShapeReadError` with one sentence that names the file, what it declares
and why that is refused. Nothing here builds an array of points.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from catalign.errors import ShapeReadError

HEADER_BYTES = 64 * 1024
"""The most bytes read to find a text header (PCD, PLY, OFF); a longer header is refused."""

CHUNK_BYTES = 1 << 20
"""Bytes read at a time when a file declares nothing and its lines must be counted."""

TEXT_VALUE_BYTES = 2
"""The fewest bytes a number takes in a text format: one digit and one separator."""

LZF_MAX_EXPANSION = 88
"""LZF (PCD ``binary_compressed``) turns at most 3 input bytes into 264 output bytes."""

GLTF_FILL_EXPANSION = 64
"""glTF accessors without data are filled with zeros: at most this many times the file size."""

_LINE_HEAD = 256  # bytes of a line kept across chunks: only a line's start is ever matched
_WHOLE = re.compile(r"[+-]?[0-9]{1,30}")  # longer numbers are refused, not parsed


@dataclass(frozen=True)
class Declared:
    """The counts a file declares (or holds, where it was counted); ``None``: not counted."""

    points: int | None
    faces: int | None


def check_header(
    path: str | Path, *, max_points: int | None = None, max_faces: int | None = None
) -> Declared:
    """Refuse a file whose declared counts its size cannot hold or that exceed the limits.

    Dispatches on the suffix (``.pcd .ply .obj .stl .off .glb .npy .xyz``); ``None`` limits
    mean only the checks against the file's size. Formats that declare no counts (OBJ, XYZ,
    ASCII STL) are only counted, by streaming, when a limit is given.
    """
    path = Path(path)
    for name, limit in (("max_points", max_points), ("max_faces", max_faces)):
        if limit is not None and limit < 1:
            raise ValueError(f"{name} must be a positive number or None, got {limit}")
    check = _CHECKS.get(path.suffix.lower())
    if check is None:
        raise ShapeReadError(f"{path}: no header check for file type {path.suffix or '(none)'}")
    try:
        size = path.stat().st_size
        with path.open("rb") as handle:
            return check(_File(path, size, max_points, max_faces), handle)
    except OSError as exc:
        raise ShapeReadError(f"{path}: cannot be read ({exc.strerror or exc})") from exc


# ---- shared wording and arithmetic -----------------------------------------------------------


@dataclass(frozen=True)
class _File:
    path: Path
    size: int
    max_points: int | None
    max_faces: int | None

    def unreadable(self, why: str) -> ShapeReadError:
        """A file whose header is malformed or claims more than the file holds."""
        return ShapeReadError(f"{self.path}: not a readable {self.path.suffix.lower()} file: {why}")

    def room(self, available: int) -> str:
        """How many bytes the data may take, in words: the size, and what follows the header."""
        if available == self.size:
            return f"the file's {self.size} bytes"
        return f"the file's {self.size} bytes ({available} after the header)"

    def fits(self, items: Sequence[tuple[int, str, int]], available: int, text: bool) -> None:
        """Refuse unless ``(count, noun, fewest bytes each)`` items fit in ``available`` bytes.

        ``text``: the last value of a text file needs no separator, so one byte less will do.
        """
        slack = 1 if text else 0
        for count, noun, each in items:
            if each > 0 and count * each > available + slack:
                raise self.unreadable(
                    f"the header declares {count} {noun}, but {self.room(available)} "
                    f"can hold at most {(available + slack) // each}"
                )
        need = sum(count * each for count, _, each in items)
        if need > available + slack:
            listed = " and ".join(f"{count} {noun}" for count, noun, _ in items)
            raise self.unreadable(
                f"the header declares {listed}, which take at least {need} bytes, "
                f"but {self.room(available)} are fewer"
            )

    def within_limits(
        self, points: int | None, faces: int | None, *, how: str = "the header declares"
    ) -> Declared:
        """Refuse counts over ``max_points`` / ``max_faces``; return them as :class:`Declared`."""
        if self.max_points is not None and points is not None and points > self.max_points:
            raise ShapeReadError(
                f"{self.path}: {how} {points} points, more than the limit of "
                f"{self.max_points} points"
            )
        if self.max_faces is not None and faces is not None and faces > self.max_faces:
            raise ShapeReadError(
                f"{self.path}: {how} {faces} faces, more than the limit of {self.max_faces} faces"
            )
        return Declared(points=points, faces=faces)

    @property
    def limited(self) -> bool:
        return self.max_points is not None or self.max_faces is not None


def _whole(f: _File, text: str, what: str) -> int:
    """A header value that must be a whole number of at least zero."""
    if not _WHOLE.fullmatch(text):
        raise f.unreadable(f"the header's {what} {text!r} is not a whole number")
    value = int(text)
    if value < 0:
        raise f.unreadable(f"the header declares a negative {what} ({value})")
    return value


def _header_lines(
    f: _File, prefix: bytes, is_last: Callable[[list[str]], bool], last: str
) -> tuple[list[list[str]], int]:
    """Split a text header into lines of words, up to and including the line ``is_last`` picks.

    Returns the lines and the offset of the first byte after the header.
    """
    lines: list[list[str]] = []
    start = 0
    while start < len(prefix):
        end = prefix.find(b"\n", start)
        if end < 0:
            if len(prefix) == f.size:  # the header is the whole file and lacks a final newline
                end = len(prefix)
            else:
                break
        words = prefix[start:end].decode("latin-1").split()
        lines.append(words)
        start = end + 1
        if words and is_last(words):
            return lines, min(start, f.size)
    if len(prefix) < f.size:
        raise f.unreadable(f"the header does not end within its first {HEADER_BYTES} bytes")
    raise f.unreadable(f"the header has no {last} line")


def _count_line_starts(
    path: Path, patterns: Sequence[re.Pattern[bytes]], stops: Sequence[int | None]
) -> list[int]:
    """Count the lines each pattern matches at their start, reading the file in chunks.

    Stops early once a count passes its stop value. Only the first bytes of a line are kept
    from one chunk to the next, so memory stays bounded whatever the line lengths.
    """
    counts = [0] * len(patterns)
    carry = b""
    with path.open("rb") as handle:
        while True:
            chunk = handle.read(CHUNK_BYTES)
            text = carry + chunk
            cut = len(text) if not chunk else text.rfind(b"\n") + 1
            body, carry = text[:cut], text[cut:][:_LINE_HEAD]
            for i, pattern in enumerate(patterns):
                counts[i] += len(pattern.findall(body))
            if any(s is not None and c > s for c, s in zip(counts, stops, strict=True)):
                return counts
            if not chunk:
                return counts


# ---- PCD ---------------------------------------------------------------------------------


def _check_pcd(f: _File, handle: BinaryIO) -> Declared:
    prefix = handle.read(HEADER_BYTES)
    lines, data_start = _header_lines(f, prefix, lambda w: w[0] == "DATA", "DATA")
    values = {w[0]: w[1:] for w in lines if w and not w[0].startswith("#")}
    fields = values.get("FIELDS", values.get("COLUMNS"))
    if fields is None:
        raise f.unreadable("the header has no FIELDS line")
    if not {"x", "y", "z"} <= set(fields):
        raise f.unreadable(f"the header's FIELDS ({' '.join(fields)}) do not name x, y and z")
    sizes = _pcd_column(f, values, "SIZE", fields, ["4"] * len(fields))
    counts = _pcd_column(f, values, "COUNT", fields, ["1"] * len(fields))
    _pcd_column(f, values, "TYPE", fields, ["F"] * len(fields))
    field_bytes = [_whole(f, s, "field SIZE") for s in sizes]
    if any(b not in (1, 2, 4, 8) for b in field_bytes):
        raise f.unreadable(f"the header's SIZE ({' '.join(sizes)}) is not 1, 2, 4 or 8 bytes")
    field_counts = [_whole(f, c, "field COUNT") for c in counts]
    point_values = sum(field_counts)
    point_bytes = sum(b * c for b, c in zip(field_bytes, field_counts, strict=True))

    declared = []
    if "POINTS" in values:
        declared.append(_whole(f, _single(f, values, "POINTS"), "POINTS value"))
    if "WIDTH" in values:
        width = _whole(f, _single(f, values, "WIDTH"), "WIDTH")
        height = _whole(f, _single(f, values, "HEIGHT"), "HEIGHT") if "HEIGHT" in values else 1
        declared.append(width * height)
    if not declared:
        raise f.unreadable("the header declares neither POINTS nor WIDTH")
    points = max(declared)  # Open3D takes whichever comes last: both must be possible

    encoding = values["DATA"][0] if values["DATA"] else "ascii"
    available = f.size - data_start
    if encoding == "ascii":
        f.fits([(points, "points", TEXT_VALUE_BYTES * max(point_values, 1))], available, True)
    elif encoding == "binary":
        f.fits([(points, "points", point_bytes)], available, False)
    elif encoding == "binary_compressed":
        _check_pcd_compressed(f, handle, data_start, points, point_bytes)
    else:
        raise f.unreadable(f"the header's DATA line names an unknown encoding {encoding!r}")
    return f.within_limits(points, None)


def _pcd_column(
    f: _File, values: dict[str, list[str]], key: str, fields: list[str], default: list[str]
) -> list[str]:
    """One value per field (SIZE, TYPE, COUNT), or ``default`` when the line is absent."""
    column = values.get(key, default)
    if len(column) != len(fields):
        raise f.unreadable(
            f"the header's {key} line has {len(column)} values for {len(fields)} FIELDS"
        )
    return column


def _single(f: _File, values: dict[str, list[str]], key: str) -> str:
    if len(values[key]) != 1:
        raise f.unreadable(f"the header's {key} line holds {len(values[key])} values, not one")
    return values[key][0]


def _check_pcd_compressed(
    f: _File, handle: BinaryIO, data_start: int, points: int, point_bytes: int
) -> None:
    """The 8 bytes after DATA: compressed and uncompressed sizes, both allocated by Open3D."""
    handle.seek(data_start)
    sizes = handle.read(8)
    if len(sizes) < 8:
        raise f.unreadable("the file ends before the sizes of its compressed data")
    compressed, uncompressed = struct.unpack("<II", sizes)
    available = f.size - data_start - 8
    if compressed > available:
        raise f.unreadable(
            f"the header declares {compressed} bytes of compressed data, "
            f"but {f.room(available)} are fewer"
        )
    if uncompressed != points * point_bytes:
        raise f.unreadable(
            f"the header declares {points} points of {point_bytes} bytes, but its compressed "
            f"data would expand to {uncompressed} bytes"
        )
    if point_bytes and uncompressed > compressed * LZF_MAX_EXPANSION:
        raise f.unreadable(
            f"the header declares {points} points, but {compressed} compressed bytes "
            f"can hold at most {compressed * LZF_MAX_EXPANSION // point_bytes}"
        )


# ---- PLY ---------------------------------------------------------------------------------

_PLY_BYTES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "float16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "int64": 8,
    "uint64": 8,
    "double": 8,
    "float64": 8,
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def _check_ply(f: _File, handle: BinaryIO) -> Declared:
    prefix = handle.read(HEADER_BYTES)
    if prefix.split(b"\n", 1)[0].strip().lower() != b"ply":
        raise f.unreadable("it does not start with the line 'ply'")
    lines, data_start = _header_lines(f, prefix, lambda w: w[0] == "end_header", "end_header")
    words = [w for w in lines[1:] if w]
    if not words or words[0][0] != "format" or len(words[0]) < 2:
        raise f.unreadable("its second line is not a 'format' line")
    encoding = words[0][1]
    if encoding not in _PLY_FORMATS:
        raise f.unreadable(f"the header names an unknown format {encoding!r}")
    elements: list[list[Any]] = []  # [name, count, fewest bytes per row, values per row]
    for line in words[1:]:
        if line[0] == "element":
            if len(line) != 3:
                raise f.unreadable(f"the header line {' '.join(line)!r} is not 'element NAME N'")
            elements.append([line[1], _whole(f, line[2], f"{line[1]} count"), 0, 0])
        elif line[0] == "property":
            if not elements:
                raise f.unreadable("the header has a property before any element")
            elements[-1][2] += _ply_property_bytes(f, line)
            elements[-1][3] += 1
    text = encoding == "ascii"
    items = [
        (count, _ply_noun(name), TEXT_VALUE_BYTES * max(values, 1) if text else row_bytes)
        for name, count, row_bytes, values in elements
    ]
    f.fits(items, f.size - data_start, text)
    counts = {name: count for name, count, _, _ in elements}
    return f.within_limits(counts.get("vertex", 0), counts.get("face"))


def _ply_property_bytes(f: _File, line: list[str]) -> int:
    """The fewest bytes a property takes per row: its type, or a list's length prefix."""
    if len(line) >= 2 and line[1] == "list":
        if len(line) != 5:
            raise f.unreadable(f"the header line {' '.join(line)!r} is not a list property")
        type_name = line[2]
    elif len(line) == 3:
        type_name = line[1]
    else:
        raise f.unreadable(f"the header line {' '.join(line)!r} is not a property")
    if type_name not in _PLY_BYTES:
        raise f.unreadable(f"the header names an unknown property type {type_name!r}")
    return _PLY_BYTES[type_name]


def _ply_noun(name: str) -> str:
    return {"vertex": "vertices", "face": "faces"}.get(name, f"'{name}' elements")


# ---- OBJ, XYZ and STL: counted, not declared ---------------------------------------------

_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]", re.MULTILINE)
_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t]", re.MULTILINE)
_XYZ_ROW = re.compile(rb"^[ \t\r\f\v]*[^#\s]", re.MULTILINE)
_STL_FACET = re.compile(rb"^[ \t]*facet[ \t\r\n]", re.MULTILINE | re.IGNORECASE)


def _check_obj(f: _File, handle: BinaryIO) -> Declared:
    if not f.limited:  # nothing declared, and the reader's memory follows the file's size
        return Declared(points=None, faces=None)
    points, faces = _count_line_starts(
        f.path, [_OBJ_VERTEX, _OBJ_FACE], [f.max_points, f.max_faces]
    )
    return f.within_limits(points, faces, how="the file holds at least")


def _check_xyz(f: _File, handle: BinaryIO) -> Declared:
    if f.max_points is None:
        return Declared(points=None, faces=None)
    (points,) = _count_line_starts(f.path, [_XYZ_ROW], [f.max_points])
    return f.within_limits(points, None, how="the file holds at least")


def _check_stl(f: _File, handle: BinaryIO) -> Declared:
    head = handle.read(84)
    triangles = int.from_bytes(head[80:84], "little") if len(head) == 84 else None
    if triangles is not None and 84 + 50 * triangles == f.size:  # binary, as trimesh decides
        _check_stl_points(f, triangles, "the header declares")
        return f.within_limits(3 * triangles, triangles)
    if head.lstrip()[:5].lower() == b"solid":  # ASCII: no counts to trust
        if not f.limited:
            return Declared(points=None, faces=None)
        stop = None if f.max_points is None else f.max_points // 3
        if f.max_faces is not None:
            stop = f.max_faces if stop is None else min(stop, f.max_faces)
        (facets,) = _count_line_starts(f.path, [_STL_FACET], [stop])
        _check_stl_points(f, facets, "the file holds at least")
        return f.within_limits(3 * facets, facets, how="the file holds at least")
    if triangles is None:
        raise f.unreadable("it is shorter than a binary STL header and does not start 'solid'")
    if 84 + 50 * triangles > f.size:
        raise f.unreadable(
            f"the header declares {triangles} triangles, but {f.room(f.size)} "
            f"can hold at most {max(f.size - 84, 0) // 50}"
        )
    raise f.unreadable(
        f"the header declares {triangles} triangles, which take {84 + 50 * triangles} bytes, "
        f"but the file has {f.size}"
    )


def _check_stl_points(f: _File, triangles: int, how: str) -> None:
    """STL repeats each corner: three points per triangle."""
    if f.max_points is not None and 3 * triangles > f.max_points:
        raise ShapeReadError(
            f"{f.path}: {how} {triangles} triangles ({3 * triangles} points), "
            f"more than the limit of {f.max_points} points"
        )


# ---- OFF ---------------------------------------------------------------------------------


def _check_off(f: _File, handle: BinaryIO) -> Declared:
    prefix = handle.read(HEADER_BYTES)
    start, found = 0, []  # the words of the first two lines that are neither blank nor comments
    while start < len(prefix) and len(found) < 2:
        end = prefix.find(b"\n", start)
        end = len(prefix) if end < 0 else end
        words = prefix[start:end].split(b"#", 1)[0].decode("latin-1").split()
        start = end + 1
        if not words:
            continue
        if not found:
            if not words[0].upper().endswith("OFF"):
                raise f.unreadable("its first line is not 'OFF'")
            found.append(words[0])
            if len(words) > 1:  # the counts may share the OFF line
                found.append(" ".join(words[1:]))
                break
        else:
            found.append(" ".join(words))
    if not found:
        raise f.unreadable("its first line is not 'OFF'")
    if len(found) < 2:
        raise f.unreadable("the header has no vertex and face counts after 'OFF'")
    counts = found[1].split()
    if len(counts) < 2:
        raise f.unreadable(f"the counts line {found[1]!r} does not hold vertices and faces")
    vertices = _whole(f, counts[0], "vertex count")
    faces = _whole(f, counts[1], "face count")
    data_start = min(start, f.size)
    f.fits(
        [(vertices, "vertices", 3 * TEXT_VALUE_BYTES), (faces, "faces", 4 * TEXT_VALUE_BYTES)],
        f.size - data_start,
        True,
    )
    return f.within_limits(vertices, faces)


# ---- GLB ---------------------------------------------------------------------------------

_GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_GLTF_TYPE_COMPONENTS = {
    "SCALAR": 1,
    "VEC2": 2,
    "VEC3": 3,
    "VEC4": 4,
    "MAT2": 4,
    "MAT3": 9,
    "MAT4": 16,
}
_GLTF_TRIANGLES, _GLTF_STRIP, _GLTF_FAN = 4, 5, 6


def _check_glb(f: _File, handle: BinaryIO) -> Declared:
    head = handle.read(20)
    if len(head) < 12 or head[:4] != b"glTF":
        raise f.unreadable("it does not start with the GLB magic 'glTF'")
    version, length = struct.unpack("<II", head[4:12])
    if version != 2:
        raise f.unreadable(f"the header declares glTF version {version}; only 2 is read")
    if length != f.size:
        raise f.unreadable(f"the header declares {length} bytes, but the file has {f.size}")
    if len(head) < 20:
        raise f.unreadable("the file ends before its JSON chunk")
    json_bytes, json_type = struct.unpack("<I4s", head[12:20])
    if json_type != b"JSON":
        raise f.unreadable("its first chunk is not JSON")
    if json_bytes > f.size - 20:
        raise f.unreadable(
            f"the header declares a JSON chunk of {json_bytes} bytes, "
            f"but {f.room(f.size - 20)} are fewer"
        )
    try:
        gltf = json.loads(handle.read(json_bytes))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise f.unreadable(f"its JSON chunk does not parse ({exc})") from None
    if not isinstance(gltf, dict):
        raise f.unreadable("its JSON chunk is not an object")
    bin_bytes = _glb_bin_chunk(f, handle, 20 + json_bytes)
    return _GltfCheck(f, gltf, bin_bytes).run()


def _lookup(table: dict[Any, int], key: object) -> int | None:
    """``table[key]``, or ``None`` for a missing or unhashable key (JSON lists, objects)."""
    return table.get(key) if isinstance(key, int | str) else None


def _glb_bin_chunk(f: _File, handle: BinaryIO, position: int) -> int:
    """The length of the BIN chunk (0 without one), after checking every chunk fits the file."""
    bin_bytes = None
    while position + 8 <= f.size:
        handle.seek(position)
        chunk_bytes, chunk_type = struct.unpack("<I4s", handle.read(8))
        if chunk_bytes > f.size - position - 8:
            raise f.unreadable(
                f"the header declares a chunk of {chunk_bytes} bytes, "
                f"but {f.room(f.size - position - 8)} are fewer"
            )
        if chunk_type == b"BIN\x00" and bin_bytes is None:
            bin_bytes = chunk_bytes
        position += 8 + chunk_bytes
    return bin_bytes or 0


class _GltfCheck:
    """Buffers within the file, views within buffers, accessors within views; then the counts."""

    def __init__(self, f: _File, gltf: dict[str, Any], bin_bytes: int) -> None:
        self.f = f
        self.gltf = gltf
        self.bin_bytes = bin_bytes

    def run(self) -> Declared:
        buffers = [self._buffer(i, b) for i, b in enumerate(self._list("buffers"))]
        views = [self._view(i, v, buffers) for i, v in enumerate(self._list("bufferViews"))]
        counts = [self._accessor(i, a, views) for i, a in enumerate(self._list("accessors"))]
        for i, image in enumerate(self._list("images")):
            self._not_outside(image, f"image {i}")
        points, faces = self._mesh_counts(counts)
        return self.f.within_limits(points, faces)

    def _list(self, key: str) -> list[dict[str, Any]]:
        items = self.gltf.get(key, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise self.f.unreadable(f"its JSON '{key}' is not a list of objects")
        return items

    def _int(self, obj: dict[str, Any], key: str, where: str, default: int | None = None) -> int:
        value = obj.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise self.f.unreadable(f"{where} has no whole, non-negative {key}")
        return value

    def _index(
        self, obj: dict[str, Any], key: str, where: str, length: int, default: int | None = None
    ) -> int:
        value = self._int(obj, key, where, default)
        if value >= length:
            raise self.f.unreadable(f"{where} refers to {key} {value}, which does not exist")
        return value

    def _not_outside(self, obj: dict[str, Any], where: str) -> None:
        uri = obj.get("uri")
        if uri is not None and not (isinstance(uri, str) and uri.startswith("data:")):
            raise self.f.unreadable(f"{where} refers to an outside file ({uri!r})")

    def _buffer(self, index: int, buffer: dict[str, Any]) -> int:
        where = f"buffer {index}"
        declared = self._int(buffer, "byteLength", where)
        self._not_outside(buffer, where)
        uri = buffer.get("uri")
        available = self.bin_bytes if uri is None else len(uri) * 3 // 4
        if declared > available:
            holder = "the BIN chunk" if uri is None else "its data URI"
            raise self.f.unreadable(
                f"the header declares {where} of {declared} bytes, "
                f"but {holder} holds at most {available}"
            )
        return declared

    def _view(self, index: int, view: dict[str, Any], buffers: list[int]) -> int:
        where = f"bufferView {index}"
        buffer = self._index(view, "buffer", where, len(buffers))
        offset = self._int(view, "byteOffset", where, 0)
        length = self._int(view, "byteLength", where)
        if offset + length > buffers[buffer]:
            raise self.f.unreadable(
                f"the header declares {where} of {length} bytes at offset {offset}, "
                f"but buffer {buffer} holds {buffers[buffer]}"
            )
        return index

    def _accessor(self, index: int, accessor: dict[str, Any], views: list[int]) -> int:
        where = f"accessor {index}"
        count = self._int(accessor, "count", where)
        item = self._item_bytes(accessor, where)
        if "bufferView" in accessor:
            offset = self._int(accessor, "byteOffset", where, 0)
            self._fits_view(accessor, where, count, item, offset)
        else:  # filled with zeros by the reader: allowed only in proportion to the file
            if count * item > GLTF_FILL_EXPANSION * self.f.size:
                raise self.f.unreadable(
                    f"the header declares {where} of {count} values without data, which would "
                    f"take {count * item} bytes, more than {GLTF_FILL_EXPANSION} times the "
                    f"file's {self.f.size} bytes"
                )
        sparse = accessor.get("sparse")
        if isinstance(sparse, dict):
            sparse_count = self._int(sparse, "count", f"{where}'s sparse part")
            for part, width in (("indices", None), ("values", item)):
                block = sparse.get(part)
                if not isinstance(block, dict):
                    raise self.f.unreadable(f"{where}'s sparse part has no {part}")
                if width is None:
                    width = _lookup(_GLTF_COMPONENT_BYTES, block.get("componentType")) or 4
                offset = self._int(block, "byteOffset", f"{where}'s sparse {part}", 0)
                self._fits_view(block, f"{where}'s sparse {part}", sparse_count, width, offset)
        return count

    def _item_bytes(self, accessor: dict[str, Any], where: str) -> int:
        component = _lookup(_GLTF_COMPONENT_BYTES, accessor.get("componentType"))
        components = _lookup(_GLTF_TYPE_COMPONENTS, accessor.get("type"))
        if component is None or components is None:
            raise self.f.unreadable(f"{where} has an unknown componentType or type")
        return component * components

    def _fits_view(
        self, obj: dict[str, Any], where: str, count: int, item: int, offset: int
    ) -> None:
        views = self._list("bufferViews")
        index = self._index(obj, "bufferView", where, len(views))
        view = views[index]
        stride = self._int(view, "byteStride", f"bufferView {index}", 0) or item
        need = offset + (count - 1) * stride + item if count else 0
        if need > view["byteLength"]:
            raise self.f.unreadable(
                f"the header declares {where} of {count} values of {item} bytes, which need "
                f"{need} bytes, but bufferView {index} holds {view['byteLength']}"
            )

    def _mesh_counts(self, counts: list[int]) -> tuple[int, int]:
        """Points (POSITION values) and triangles, once for every node that shows a mesh."""
        per_mesh = []
        for i, mesh in enumerate(self._list("meshes")):
            primitives = mesh.get("primitives", [])
            if not isinstance(primitives, list) or not all(isinstance(p, dict) for p in primitives):
                raise self.f.unreadable(f"mesh {i} has no list of primitives")
            points = faces = 0
            for p in primitives:
                attributes = p.get("attributes", {})
                if not isinstance(attributes, dict):
                    raise self.f.unreadable(f"a primitive of mesh {i} has no attributes object")
                n = counts[self._index(attributes, "POSITION", f"mesh {i}", len(counts))]
                points += n
                if "indices" in p:
                    n = counts[self._index(p, "indices", f"mesh {i}", len(counts))]
                mode = p.get("mode", _GLTF_TRIANGLES)
                if mode == _GLTF_TRIANGLES:
                    faces += n // 3
                elif mode in (_GLTF_STRIP, _GLTF_FAN):
                    faces += max(n - 2, 0)
            per_mesh.append((points, faces))
        shown = self._shown_meshes(len(per_mesh))
        return (
            sum(per_mesh[m][0] for m in shown),
            sum(per_mesh[m][1] for m in shown),
        )

    def _shown_meshes(self, n_meshes: int) -> list[int]:
        """The mesh of every node reachable from the default scene; every mesh without scenes."""
        nodes = self._list("nodes")
        scenes = self._list("scenes")
        if not scenes:
            return list(range(n_meshes))
        chosen = self._index(self.gltf, "scene", "the file", len(scenes), default=0)
        roots = scenes[chosen].get("nodes", [])
        pending = list(roots) if isinstance(roots, list) else []
        seen: set[int] = set()
        shown = []
        while pending:
            index = pending.pop()
            if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(nodes):
                raise self.f.unreadable(f"the scene refers to node {index!r}, which does not exist")
            if index in seen:
                continue
            seen.add(index)
            node = nodes[index]
            if "mesh" in node:
                shown.append(self._index(node, "mesh", f"node {index}", n_meshes))
            children = node.get("children", [])
            if isinstance(children, list):
                pending.extend(children)
        return shown


# ---- NPY ---------------------------------------------------------------------------------


def _check_npy(f: _File, handle: BinaryIO) -> Declared:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(handle)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"it is .npy format version {version[0]}.{version[1]}")
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(handle)
        else:  # 2.0 and 3.0 share a layout; 3.0 only allows UTF-8 in field names
            shape, _, dtype = fmt.read_array_header_2_0(handle)
    except (ValueError, SyntaxError, TypeError, RecursionError) as exc:
        raise f.unreadable(str(exc)) from None
    if dtype.hasobject:
        raise f.unreadable(f"it holds Python objects ({dtype}), which are never unpickled")
    data = math.prod(shape) * dtype.itemsize
    available = f.size - handle.tell()
    if data != available:
        shortfall = "are fewer" if data > available else "are more"
        raise f.unreadable(
            f"the header declares an array of shape {shape} and type {dtype} ({data} bytes), "
            f"but {f.room(available)} {shortfall}"
        )
    if dtype.kind in "biuf" and (len(shape) != 2 or shape[1] != 3):
        raise ShapeReadError(f"{f.path}: expected an (N, 3) array of points, got shape {shape}")
    return f.within_limits(shape[0] if len(shape) == 2 else None, None)


_CHECKS: dict[str, Callable[[_File, BinaryIO], Declared]] = {
    ".pcd": _check_pcd,
    ".ply": _check_ply,
    ".obj": _check_obj,
    ".stl": _check_stl,
    ".off": _check_off,
    ".glb": _check_glb,
    ".npy": _check_npy,
    ".xyz": _check_xyz,
}
