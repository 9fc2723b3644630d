"""STL: a binary file's triangle count against its size; an ASCII file's facets, counted.

A binary STL declares its triangles in bytes 80 to 84 and takes exactly 84 bytes plus 50 a triangle,
which is how the reader tells it from ASCII; a file that is neither binary by that rule nor starts
``solid`` is refused. ASCII STL declares nothing and is counted, by streaming, only when a limit is
given. Either way each triangle repeats its three corners: three points against ``max_points``.
"""

from __future__ import annotations

import re
from typing import BinaryIO

from catalign.errors import ShapeReadError
from catalign.geometry.headers._common import Declared, File, count_line_starts

_STL_FACET = re.compile(rb"^[ \t]*facet[ \t\r\n]", re.MULTILINE | re.IGNORECASE)


def check_stl(f: File, handle: BinaryIO) -> Declared:
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
        (facets,) = count_line_starts(f.path, [_STL_FACET], [stop])
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


def _check_stl_points(f: File, triangles: int, how: str) -> None:
    """STL repeats each corner: three points per triangle."""
    if f.max_points is not None and 3 * triangles > f.max_points:
        raise ShapeReadError(
            f"{f.path}: {how} {triangles} triangles ({3 * triangles} points), "
            f"more than the limit of {f.max_points} points"
        )
