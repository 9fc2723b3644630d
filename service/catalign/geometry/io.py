"""Read meshes and point clouds from the file formats catalign accepts.

Meshes (``.obj .ply .stl .off .glb``) are read with trimesh, point clouds (``.ply .pcd .npy
.xyz``) with numpy or Open3D. A ``.ply`` without faces is a point cloud. Every failure (missing,
unreadable, empty, non-finite) raises :class:`~catalign.errors.ShapeReadError` with a sentence
that names the file and the problem. Before any reader runs,
:func:`~catalign.geometry.headers.check_header` compares what the file declares with its size
and the optional limits: a reader that trusted a lying header would allocate memory that the
file cannot justify, and the server would be killed for it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from catalign.errors import ShapeReadError
from catalign.geometry.headers import check_header

MESH_SUFFIXES = frozenset({".obj", ".ply", ".stl", ".off", ".glb"})
POINT_SUFFIXES = frozenset({".ply", ".pcd", ".npy", ".xyz"})
SUPPORTED_SUFFIXES = MESH_SUFFIXES | POINT_SUFFIXES

# trimesh logs a warning with a traceback for a file it reads anyway (an ASCII STL with a
# garbled normal) or before it gives up; the caller hears of a bad file from ShapeReadError,
# in a sentence, so only trimesh's errors reach the log.
logging.getLogger("trimesh").setLevel(logging.ERROR)


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh as plain arrays: vertices (V,3) float64 and faces (F,3) int64."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class ShapeData:
    """What a shape file holds: always points; a mesh too when the file had faces."""

    points: np.ndarray
    mesh: MeshData | None


def check_points(points: np.ndarray, what: str) -> np.ndarray:
    """Return ``points`` as a float64 (N,3) array, or raise if empty, mis-shaped or non-finite."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:  # strings, records: not coordinates
        raise ShapeReadError(f"{what}: expected numeric point coordinates ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeReadError(f"{what}: expected an (N, 3) array of points, got shape {arr.shape}")
    if len(arr) == 0:
        raise ShapeReadError(f"{what}: holds no points")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise ShapeReadError(f"{what}: {bad} of {len(arr)} points have NaN or infinite coordinates")
    return arr


def read_shape(
    path: str | Path, *, max_points: int | None = None, max_faces: int | None = None
) -> ShapeData:
    """Read any supported shape file; meshes keep their faces, point clouds have none.

    ``max_points`` / ``max_faces`` refuse larger files, from their headers where they declare
    counts, before anything is read; ``None`` checks the headers only against the file's size.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ShapeReadError(
            f"{path}: unsupported file type {suffix or '(none)'}; "
            f"supported: {' '.join(sorted(SUPPORTED_SUFFIXES))}"
        )
    if not path.is_file():
        raise ShapeReadError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ShapeReadError(f"{path}: the file is empty")
    check_header(path, max_points=max_points, max_faces=max_faces)
    if suffix == ".npy":
        shape = ShapeData(points=_read_npy(path), mesh=None)
    elif suffix == ".xyz":
        shape = ShapeData(points=_read_xyz(path), mesh=None)
    elif suffix == ".pcd":
        shape = ShapeData(points=_read_pcd(path), mesh=None)
    else:
        shape = _read_with_trimesh(path)
    _check_read_counts(path, shape, max_points, max_faces)
    return shape


def read_points(
    path: str | Path, *, max_points: int | None = None, max_faces: int | None = None
) -> np.ndarray:
    """Read a file as points: a point cloud's points, or a mesh's vertices."""
    return read_shape(path, max_points=max_points, max_faces=max_faces).points


def read_mesh(
    path: str | Path, *, max_points: int | None = None, max_faces: int | None = None
) -> MeshData:
    """Read a file that must hold a triangle mesh."""
    shape = read_shape(path, max_points=max_points, max_faces=max_faces)
    if shape.mesh is None:
        raise ShapeReadError(f"{path}: holds points but no triangles; a mesh was expected")
    return shape.mesh


def _check_read_counts(
    path: Path, shape: ShapeData, max_points: int | None, max_faces: int | None
) -> None:
    """The limits again, on what was read: polygons split into more triangles than declared."""
    if max_points is not None and len(shape.points) > max_points:
        raise ShapeReadError(
            f"{path}: holds {len(shape.points)} points, more than the limit of {max_points} points"
        )
    faces = 0 if shape.mesh is None else len(shape.mesh.faces)
    if max_faces is not None and faces > max_faces:
        raise ShapeReadError(
            f"{path}: holds {faces} faces, more than the limit of {max_faces} faces"
        )


def _read_npy(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ShapeReadError(f"{path}: not a readable .npy array ({exc})") from exc
    return check_points(arr, str(path))


def _read_xyz(path: Path) -> np.ndarray:
    try:
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        raise ShapeReadError(f"{path}: not a readable .xyz text file ({exc})") from exc
    if arr.size and arr.shape[1] > 3:
        arr = arr[:, :3]  # .xyz files often carry normals or colours after the coordinates
    return check_points(arr.reshape(-1, 3) if arr.size == 0 else arr, str(path))


def _read_pcd(path: Path) -> np.ndarray:
    import open3d as o3d  # heavy import kept local: the SDK-facing parts never need it

    cloud = o3d.io.read_point_cloud(str(path), format="pcd")
    points = np.asarray(cloud.points)
    if len(points) == 0:
        raise ShapeReadError(f"{path}: no points could be read (corrupt or empty .pcd file)")
    return check_points(points, str(path))


def _read_with_trimesh(path: Path) -> ShapeData:
    import trimesh

    try:
        loaded = trimesh.load(path, force=None, process=False)
    except Exception as exc:  # trimesh raises many unrelated types for bad files
        raise ShapeReadError(f"{path}: not a readable {path.suffix} file ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        geometries = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not geometries:
            raise ShapeReadError(f"{path}: the scene holds no triangle mesh")
        loaded = trimesh.util.concatenate(geometries)
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) > 0:
        vertices = check_points(loaded.vertices, str(path))
        faces = np.asarray(loaded.faces, dtype=np.int64)
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ShapeReadError(
                f"{path}: its faces refer to vertices {int(faces.min())} to {int(faces.max())}, "
                f"but it has only vertices 0 to {len(vertices) - 1}"
            )
        return ShapeData(points=vertices, mesh=MeshData(vertices=vertices, faces=faces))
    vertices = getattr(loaded, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise ShapeReadError(f"{path}: holds no points or triangles")
    return ShapeData(points=check_points(vertices, str(path)), mesh=None)
