"""Turning whatever a robot holds into the (N, 3) points the service takes, and onto the wire.

Robots hold point clouds as numpy arrays, nested lists, Open3D clouds (``.points``), trimesh
objects (``.vertices``) or ROS ``sensor_msgs/msg/PointCloud2`` messages (read in
:mod:`._pointcloud2`); the SDK must accept all of them without importing those libraries. Bad
points are refused here, before any bytes travel, with a message that says what is wrong, so a
caller learns about a NaN from the SDK rather than from a 422 a round trip later. Encoding lives
here too: raw little-endian float32 (12 bytes a point, the default) or JSON.
"""

from __future__ import annotations

from typing import Any, Protocol, TypeAlias, runtime_checkable

import numpy as np
import numpy.typing as npt

from ._exceptions import InvalidPointsError
from ._pointcloud2 import PointCloud2Like, is_pointcloud2, pointcloud2_points

_FLOAT32_MAX = float(np.finfo(np.float32).max)


@runtime_checkable
class HasPoints(Protocol):
    """Anything with a ``.points`` attribute, e.g. ``open3d.geometry.PointCloud``."""

    @property
    def points(self) -> Any: ...


@runtime_checkable
class HasVertices(Protocol):
    """Anything with a ``.vertices`` attribute, e.g. ``trimesh.PointCloud`` or ``Trimesh``."""

    @property
    def vertices(self) -> Any: ...


PointsLike: TypeAlias = "npt.ArrayLike | HasPoints | HasVertices | PointCloud2Like"


def as_points(points: PointsLike) -> np.ndarray:
    """A C-contiguous (N, 3) float64 copy of ``points``, or :class:`InvalidPointsError`.

    A PointCloud2 message gives its finite points (NaN marks a missing return there); anything
    else must be all finite.
    """
    if is_pointcloud2(points):
        return pointcloud2_points(points)
    source = points
    if not isinstance(points, np.ndarray | list | tuple):
        for attribute in ("points", "vertices"):
            if hasattr(points, attribute):
                source = getattr(points, attribute)
                break
    try:
        array = np.asarray(source)
    except (TypeError, ValueError) as exc:  # ragged lists, objects numpy cannot read
        raise InvalidPointsError(f"points are not a numeric (N, 3) array: {exc}") from exc
    if array.dtype.kind not in "iuf":
        raise InvalidPointsError(
            f"points must be real numbers, got an array of dtype {array.dtype} "
            f"(from {type(points).__name__})"
        )
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidPointsError(f"points must have shape (N, 3), got {array.shape}")
    if array.shape[0] == 0:
        raise InvalidPointsError("points are empty: at least one point is needed")
    result = np.array(array, dtype=np.float64, order="C")
    finite = np.isfinite(result).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InvalidPointsError(
            f"{bad.size} of {len(result)} points are not finite (NaN or inf), "
            f"first at row {int(bad[0])}"
        )
    return result


def encode_binary(points: np.ndarray) -> bytes:
    """Raw little-endian float32, x y z per point: exactly ``12 * N`` bytes."""
    if np.abs(points).max() > _FLOAT32_MAX:
        raise InvalidPointsError("points exceed the float32 range of the binary encoding")
    return np.ascontiguousarray(points, dtype="<f4").tobytes()


def encode_json(points: np.ndarray) -> list[list[float]]:
    """Nested lists of Python floats, for the JSON body."""
    return points.tolist()
