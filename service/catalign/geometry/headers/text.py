"""Text formats: OBJ and XYZ, which declare nothing and are counted, and OFF, which declares.

OBJ and XYZ state no counts, and their readers' memory follows the file's size, so they are only
counted (by streaming the file, never by reading it whole) when a limit on points or faces is
given. OFF declares its vertex and face counts on its first lines; each takes at least a few
digits and separators, so the counts must fit in the bytes after the header.
"""

from __future__ import annotations

import re
from typing import BinaryIO

from catalign.geometry.headers._common import (
    HEADER_BYTES,
    TEXT_VALUE_BYTES,
    Declared,
    File,
    count_line_starts,
    whole,
)

_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]", re.MULTILINE)
_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t]", re.MULTILINE)
_XYZ_ROW = re.compile(rb"^[ \t\r\f\v]*[^#\s]", re.MULTILINE)


def check_obj(f: File, handle: BinaryIO) -> Declared:
    if not f.limited:  # nothing declared, and the reader's memory follows the file's size
        return Declared(points=None, faces=None)
    points, faces = count_line_starts(f.path, [_OBJ_VERTEX, _OBJ_FACE], [f.max_points, f.max_faces])
    return f.within_limits(points, faces, how="the file holds at least")


def check_xyz(f: File, handle: BinaryIO) -> Declared:
    if f.max_points is None:
        return Declared(points=None, faces=None)
    (points,) = count_line_starts(f.path, [_XYZ_ROW], [f.max_points])
    return f.within_limits(points, None, how="the file holds at least")


def check_off(f: File, handle: BinaryIO) -> Declared:
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
    vertices = whole(f, counts[0], "vertex count")
    faces = whole(f, counts[1], "face count")
    data_start = min(start, f.size)
    f.fits(
        [(vertices, "vertices", 3 * TEXT_VALUE_BYTES), (faces, "faces", 4 * TEXT_VALUE_BYTES)],
        f.size - data_start,
        True,
    )
    return f.within_limits(vertices, faces)
