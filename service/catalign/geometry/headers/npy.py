"""NPY: the array's declared shape and type, against the bytes after its header.

numpy allocates the array the header declares, so its size must equal exactly what follows the
header; object arrays are refused, since reading them would unpickle, and a numeric array must be
an ``(N, 3)`` array of points.
"""

from __future__ import annotations

import math
import struct
from tokenize import TokenError
from typing import BinaryIO

import numpy as np

from catalign.errors import ShapeReadError
from catalign.geometry.headers._common import Declared, File


def check_npy(f: File, handle: BinaryIO) -> Declared:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(handle)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"it is .npy format version {version[0]}.{version[1]}")
        _check_header_length(f, handle, version)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(handle)
        else:  # 2.0 and 3.0 share a layout; 3.0 only allows UTF-8 in field names
            shape, _, dtype = fmt.read_array_header_2_0(handle)
    except (ValueError, SyntaxError, TypeError, RecursionError, TokenError) as exc:
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


def _check_header_length(f: File, handle: BinaryIO, version: tuple[int, int]) -> None:
    """numpy reads the whole declared header before it checks its length: up to 4 GB."""
    start = handle.tell()
    layout = "<H" if version == (1, 0) else "<I"
    length_bytes = handle.read(struct.calcsize(layout))
    handle.seek(start)
    if len(length_bytes) < struct.calcsize(layout):
        raise f.unreadable("the file ends before the length of its header")
    (length,) = struct.unpack(layout, length_bytes)
    available = f.size - start - len(length_bytes)
    if length > available:
        raise f.unreadable(
            f"its header is declared {length} bytes long, but {f.room(available)} are fewer"
        )
