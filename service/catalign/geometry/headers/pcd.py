"""PCD: the POINTS or WIDTH x HEIGHT a header declares, against its data encoding.

Open3D sizes its point arrays from the header, so the declared points must fit what follows
``DATA``: at least a digit and a separator per value for ``ascii``, the declared field sizes for
``binary``, and for ``binary_compressed`` the compressed and uncompressed sizes (both allocated
by the reader) must agree with the points and with what LZF can expand to.
"""

from __future__ import annotations

import struct
from typing import BinaryIO

from catalign.geometry.headers._common import (
    HEADER_BYTES,
    LZF_MAX_EXPANSION,
    TEXT_VALUE_BYTES,
    Declared,
    File,
    header_lines,
    whole,
)

# The header's keywords. Open3D matches a line's first word by its start alone
# (``POINTS\x80 9999`` is a POINTS line to it), so a word that starts with one and is not it
# is refused rather than read differently from Open3D.
KEYWORDS = ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT")
KEYWORDS += ("VIEWPOINT", "POINTS", "DATA")


def check_pcd(f: File, handle: BinaryIO) -> Declared:
    prefix = handle.read(HEADER_BYTES)
    lines, data_start = header_lines(f, prefix, lambda w: w[0].startswith("DATA"), "DATA")
    _check_keywords(f, lines)
    values = {w[0]: w[1:] for w in lines if w and not w[0].startswith("#")}
    fields = values.get("FIELDS", values.get("COLUMNS"))
    if fields is None:
        raise f.unreadable("the header has no FIELDS line")
    if not {"x", "y", "z"} <= set(fields):
        raise f.unreadable(f"the header's FIELDS ({' '.join(fields)}) do not name x, y and z")
    sizes = _pcd_column(f, values, "SIZE", fields, ["4"] * len(fields))
    counts = _pcd_column(f, values, "COUNT", fields, ["1"] * len(fields))
    _pcd_column(f, values, "TYPE", fields, ["F"] * len(fields))
    field_bytes = [whole(f, s, "field SIZE") for s in sizes]
    if any(b not in (1, 2, 4, 8) for b in field_bytes):
        raise f.unreadable(f"the header's SIZE ({' '.join(sizes)}) is not 1, 2, 4 or 8 bytes")
    field_counts = [whole(f, c, "field COUNT") for c in counts]
    if 0 in field_counts:  # Open3D reads a value of every field all the same, past the record
        raise f.unreadable(f"the header's COUNT ({' '.join(counts)}) has a field of no values")
    point_values = sum(field_counts)
    point_bytes = sum(b * c for b, c in zip(field_bytes, field_counts, strict=True))

    _check_count_lines(f, [w[0] for w in lines if w])
    declared = []
    if "POINTS" in values:
        declared.append(whole(f, _single(f, values, "POINTS"), "POINTS value"))
    if "WIDTH" in values:
        if "HEIGHT" not in values:  # Open3D would multiply WIDTH by a height it never set
            raise f.unreadable("the header declares a WIDTH but no HEIGHT")
        width = whole(f, _single(f, values, "WIDTH"), "WIDTH")
        height = whole(f, _single(f, values, "HEIGHT"), "HEIGHT")
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
    f: File, values: dict[str, list[str]], key: str, fields: list[str], default: list[str]
) -> list[str]:
    """One value per field (SIZE, TYPE, COUNT), or ``default`` when the line is absent."""
    column = values.get(key, default)
    if len(column) != len(fields):
        raise f.unreadable(
            f"the header's {key} line has {len(column)} values for {len(fields)} FIELDS"
        )
    return column


def _check_keywords(f: File, lines: list[list[str]]) -> None:
    for words in lines:
        if not words or words[0].startswith("#"):
            continue
        near = [k for k in KEYWORDS if words[0].startswith(k) and words[0] != k]
        if near:
            raise f.unreadable(
                f"the header line starting {words[0][:24]!r} is not the {near[0]} keyword it "
                "begins with"
            )


def _check_count_lines(f: File, keys: list[str]) -> None:
    """Open3D sets its point count on each POINTS line and, as WIDTH times HEIGHT, on each
    HEIGHT line, with whatever width it has read by then (none: uninitialised memory)."""
    for key in ("POINTS", "WIDTH", "HEIGHT"):
        if keys.count(key) > 1:
            raise f.unreadable(f"the header has {keys.count(key)} {key} lines")
    if "HEIGHT" in keys and ("WIDTH" not in keys or keys.index("HEIGHT") < keys.index("WIDTH")):
        raise f.unreadable("the header's HEIGHT line comes before any WIDTH line")


def _single(f: File, values: dict[str, list[str]], key: str) -> str:
    if len(values[key]) != 1:
        raise f.unreadable(f"the header's {key} line holds {len(values[key])} values, not one")
    return values[key][0]


def _check_pcd_compressed(
    f: File, handle: BinaryIO, data_start: int, points: int, point_bytes: int
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
