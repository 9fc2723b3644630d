"""PLY: every element's declared count, against the fewest bytes its properties take.

The reader allocates each element (vertices, faces and any other) from the ``element NAME N``
lines, so the header is read up to ``end_header`` and every count, times the fewest bytes a row
takes (its property types, a list's length prefix, or a digit and a separator per value in ASCII),
must fit in the bytes after the header.
"""

from __future__ import annotations

from typing import Any, BinaryIO

from catalign.geometry.headers._common import (
    HEADER_BYTES,
    TEXT_VALUE_BYTES,
    Declared,
    File,
    header_lines,
    whole,
)

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


def check_ply(f: File, handle: BinaryIO) -> Declared:
    prefix = handle.read(HEADER_BYTES)
    if prefix.split(b"\n", 1)[0].strip().lower() != b"ply":
        raise f.unreadable("it does not start with the line 'ply'")
    lines, data_start = header_lines(f, prefix, lambda w: w[0] == "end_header", "end_header")
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
            elements.append([line[1], whole(f, line[2], f"{line[1]} count"), 0, 0])
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


def _ply_property_bytes(f: File, line: list[str]) -> int:
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
