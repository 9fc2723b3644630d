"""Reading ``sensor_msgs/msg/PointCloud2`` messages into (N, 3) points, without ROS installed.

Robots speak ROS: a depth camera or lidar driver publishes PointCloud2, and the natural thing for
a node is to hand that message straight to ``client.align(msg)``. The SDK must not depend on
rclpy or ``sensor_msgs_py``, so it reads any object shaped like the message (duck typing). The
layout is what makes this more than ``np.frombuffer``: x, y and z are packed fields at declared
offsets inside a ``point_step``-byte record, next to colour, intensity or ring fields and padding;
rows may be padded too (``row_step > width * point_step``); bytes may be big-endian; and
organized clouds (``height > 1``, one record per pixel) mark pixels without a return with NaN.
A structured numpy dtype with explicit offsets and ``itemsize=point_step``, laid over the buffer
with the row stride, reads all of that without copying; non-finite points are then dropped,
since NaN is the message's own way of saying "no point here".
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from ._exceptions import InvalidPointsError

# sensor_msgs/msg/PointField datatype constants.
_DATATYPE_NAMES = {
    1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16",
    5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64",
}  # fmt: skip
_FLOAT_TYPES = {7: "f4", 8: "f8"}  # the coordinates must be FLOAT32 or FLOAT64
_DETECT = ("fields", "point_step", "data", "width", "height")


@runtime_checkable
class PointCloud2Like(Protocol):
    """Anything shaped like ``sensor_msgs/msg/PointCloud2`` (rclpy's message, or a stand-in).

    ``fields`` holds objects with ``name``, ``offset``, ``datatype`` and ``count`` (ROS
    ``PointField``); ``data`` is bytes, a bytearray, a memoryview, an ``array.array`` or a list
    of ints, ``height`` rows of ``row_step`` bytes, each holding ``width`` records of
    ``point_step`` bytes.
    """

    @property
    def fields(self) -> Any: ...

    @property
    def point_step(self) -> int: ...

    @property
    def row_step(self) -> int: ...

    @property
    def is_bigendian(self) -> bool: ...

    @property
    def height(self) -> int: ...

    @property
    def width(self) -> int: ...

    @property
    def data(self) -> Any: ...


def is_pointcloud2(obj: object) -> bool:
    """Whether ``obj`` looks like a PointCloud2 message (checked by attributes, not by type)."""
    return all(hasattr(obj, name) for name in _DETECT)


def pointcloud2_points(msg: Any) -> np.ndarray:
    """The finite x, y, z of every point of ``msg`` as a C-contiguous (N, 3) float64 array.

    Points are in message order (row by row for an organized cloud); any point with a NaN or
    infinite coordinate is left out. :class:`InvalidPointsError` when x, y or z is missing or not
    FLOAT32/FLOAT64, when ``data`` is shorter than ``row_step * height``, or when no finite point
    is left.
    """
    height, width = _count(msg, "height"), _count(msg, "width")
    point_step = _count(msg, "point_step")
    row_step = _count(msg, "row_step", default=width * point_step)
    if point_step == 0:
        raise InvalidPointsError("PointCloud2 point_step is 0: records must have a size")
    if row_step < width * point_step:
        raise InvalidPointsError(
            f"PointCloud2 row_step {row_step} is smaller than width * point_step "
            f"({width} * {point_step})"
        )
    buffer = _bytes(msg.data)
    if buffer.size < row_step * height:
        raise InvalidPointsError(
            f"PointCloud2 data holds {buffer.size} bytes, fewer than row_step * height "
            f"({row_step} * {height} = {row_step * height})"
        )
    if width * height == 0:
        raise InvalidPointsError(f"PointCloud2 has no points (width {width}, height {height})")
    # Only now is point_step known to fit in the data, and so in the record type numpy builds.
    endian = ">" if getattr(msg, "is_bigendian", False) else "<"
    dtype = _record_dtype(msg.fields, point_step, endian)
    # One view over the buffer: rows row_step bytes apart, records point_step bytes apart.
    strides = (row_step, point_step)
    records = np.ndarray((height, width), dtype=dtype, buffer=buffer, strides=strides)
    xyz = np.empty((height * width, 3), dtype=np.float64)
    for column, axis in enumerate("xyz"):
        xyz[:, column] = records[axis].reshape(-1)
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.any():
        raise InvalidPointsError(
            f"PointCloud2 has no finite point: all {xyz.shape[0]} are NaN or infinite"
        )
    return xyz if finite.all() else np.ascontiguousarray(xyz[finite])


def _count(msg: Any, name: str, default: int | None = None) -> int:
    value = getattr(msg, name, default)
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise InvalidPointsError(f"PointCloud2 {name} must be an integer >= 0, got {value!r}")
    return int(value)


def _record_dtype(fields: Any, point_step: int, endian: str) -> np.dtype:
    """x, y, z at their offsets in a record of ``point_step`` bytes; other fields skipped."""
    by_name = {getattr(field, "name", None): field for field in fields}
    formats, offsets = [], []
    for axis in "xyz":
        field = by_name.get(axis)
        if field is None:
            present = ", ".join(str(name) for name in by_name) or "none"
            raise InvalidPointsError(f"PointCloud2 has no {axis!r} field (fields: {present})")
        datatype = getattr(field, "datatype", None)
        if datatype not in _FLOAT_TYPES:
            kind = _DATATYPE_NAMES.get(datatype, f"unknown datatype {datatype!r}")
            raise InvalidPointsError(
                f"PointCloud2 field {axis!r} is {kind}; only FLOAT32 (7) and FLOAT64 (8) "
                "coordinates are supported"
            )
        fmt = np.dtype(endian + _FLOAT_TYPES[datatype])
        offset = getattr(field, "offset", None)
        if not isinstance(offset, int | np.integer) or offset < 0:
            raise InvalidPointsError(f"PointCloud2 field {axis!r} has a bad offset {offset!r}")
        if offset + fmt.itemsize > point_step:
            raise InvalidPointsError(
                f"PointCloud2 field {axis!r} (offset {offset}, {fmt.itemsize} bytes) does not fit "
                f"in point_step {point_step}"
            )
        formats.append(fmt)
        offsets.append(int(offset))
    return np.dtype(
        {"names": ["x", "y", "z"], "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def _bytes(data: Any) -> np.ndarray:
    """``data`` as a flat uint8 array: buffers are viewed, a list of ints (rclpy) is copied."""
    if isinstance(data, list | tuple):
        try:
            return np.array(data, dtype=np.uint8)
        except (OverflowError, TypeError, ValueError) as exc:
            raise InvalidPointsError(f"PointCloud2 data is not a list of bytes: {exc}") from exc
    try:
        view = memoryview(data)
    except TypeError as exc:
        raise InvalidPointsError(
            f"PointCloud2 data must be bytes, a buffer or a list of ints, got {type(data).__name__}"
        ) from exc
    if view.format != "B" or view.ndim != 1 or not view.c_contiguous:
        try:
            view = view.cast("B")
        except TypeError:  # not C-contiguous, or a format memoryview cannot recast
            view = memoryview(view.tobytes())
    return np.frombuffer(view, dtype=np.uint8)
