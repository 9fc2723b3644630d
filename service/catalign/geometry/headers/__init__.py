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

from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from catalign.errors import ShapeReadError
from catalign.geometry.headers._common import (
    CHUNK_BYTES,
    GLTF_FILL_EXPANSION,
    HEADER_BYTES,
    LZF_MAX_EXPANSION,
    TEXT_VALUE_BYTES,
    Declared,
    File,
)
from catalign.geometry.headers.gltf import check_glb
from catalign.geometry.headers.npy import check_npy
from catalign.geometry.headers.pcd import check_pcd
from catalign.geometry.headers.ply import check_ply
from catalign.geometry.headers.stl import check_stl
from catalign.geometry.headers.text import check_obj, check_off, check_xyz

__all__ = [
    "CHUNK_BYTES",
    "GLTF_FILL_EXPANSION",
    "HEADER_BYTES",
    "LZF_MAX_EXPANSION",
    "TEXT_VALUE_BYTES",
    "Declared",
    "check_header",
]

_CHECKS: dict[str, Callable[[File, BinaryIO], Declared]] = {
    ".pcd": check_pcd,
    ".ply": check_ply,
    ".obj": check_obj,
    ".stl": check_stl,
    ".off": check_off,
    ".glb": check_glb,
    ".npy": check_npy,
    ".xyz": check_xyz,
}


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
            return check(File(path, size, max_points, max_faces), handle)
    except OSError as exc:
        raise ShapeReadError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
