"""ROS ``sensor_msgs/msg/PointCloud2`` messages, built by hand, read without ROS installed."""

from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest

from catalign_client import InvalidPointsError, PointCloud2Like
from catalign_client._points import as_points

INT16, FLOAT32, FLOAT64 = 3, 7, 8


@dataclass
class PointField:
    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class PointCloud2:
    """The attributes of ``sensor_msgs.msg.PointCloud2`` that matter (header left out)."""

    fields: list[PointField]
    point_step: int
    row_step: int
    height: int
    width: int
    data: Any
    is_bigendian: bool = False
    is_dense: bool = False


def pack(
    grid: np.ndarray,
    layout: dict[str, tuple[int, str]],
    point_step: int,
    *,
    row_step: int | None = None,
    bigendian: bool = False,
    seed: int = 0,
) -> PointCloud2:
    """A message holding ``grid`` ((H, W, 3), or (N, 3) for an unorganized cloud) with fields
    ``{name: (offset, numpy type)}``; padding and unused bytes are random, to be ignored."""
    if grid.ndim == 2:
        grid = grid[None]
    height, width, _ = grid.shape
    row_step = row_step or width * point_step
    raw = np.random.default_rng(seed).integers(0, 256, row_step * height, dtype=np.uint8)
    endian = ">" if bigendian else "<"
    dtype = np.dtype(
        {
            "names": list(layout),
            "formats": [endian + kind for _, kind in layout.values()],
            "offsets": [offset for offset, _ in layout.values()],
            "itemsize": point_step,
        }
    )
    records = np.ndarray((height, width), dtype=dtype, buffer=raw, strides=(row_step, point_step))
    for column, axis in enumerate("xyz"):
        if axis in layout:
            records[axis] = grid[..., column]
    datatypes = {"f4": FLOAT32, "f8": FLOAT64, "i2": INT16, "u4": 6}
    fields = [PointField(name, offset, datatypes[kind]) for name, (offset, kind) in layout.items()]
    return PointCloud2(fields, point_step, row_step, height, width, raw.tobytes(), bigendian)


XYZ_RGB = {"x": (0, "f4"), "y": (4, "f4"), "z": (8, "f4"), "rgb": (16, "u4")}


@pytest.fixture
def cloud() -> np.ndarray:
    return np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)


def test_float32_xyz_with_rgb_and_padding(cloud):
    msg = pack(cloud, XYZ_RGB, point_step=32)
    assert isinstance(msg, PointCloud2Like)
    points = as_points(msg)
    assert points.dtype == np.float64 and points.flags.c_contiguous
    np.testing.assert_array_equal(points, cloud.astype(np.float64))


def test_big_endian(cloud):
    msg = pack(cloud, {"x": (0, "f4"), "y": (4, "f4"), "z": (8, "f4")}, 16, bigendian=True)
    np.testing.assert_array_equal(as_points(msg), cloud)


def test_float64_fields(cloud):
    precise = cloud.astype(np.float64) + 1e-9
    layout = {"intensity": (0, "f4"), "x": (8, "f8"), "y": (16, "f8"), "z": (24, "f8")}
    np.testing.assert_array_equal(as_points(pack(precise, layout, 32)), precise)


def test_organized_cloud_keeps_exactly_the_finite_points_in_order():
    rng = np.random.default_rng(2)
    grid = rng.uniform(-2, 2, size=(480, 640, 3)).astype(np.float32)
    missing = rng.random((480, 640)) < 0.3
    grid[missing] = np.nan  # no return: x, y and z are NaN
    grid[5, 7, 2] = np.nan  # a single bad coordinate drops the point too
    grid[9, 9, 0] = np.inf
    msg = pack(grid, XYZ_RGB, point_step=32)
    assert (msg.height, msg.width) == (480, 640)
    flat = grid.reshape(-1, 3)
    expected = flat[np.isfinite(flat).all(axis=1)].astype(np.float64)
    points = as_points(msg)
    assert len(points) == int((~missing).sum()) - 2
    np.testing.assert_array_equal(points, expected)


def test_row_padding_is_skipped():
    grid = np.arange(3 * 5 * 3, dtype=np.float32).reshape(3, 5, 3)
    msg = pack(grid, {"x": (0, "f4"), "y": (4, "f4"), "z": (8, "f4")}, 16, row_step=5 * 16 + 24)
    np.testing.assert_array_equal(as_points(msg), grid.reshape(-1, 3))


@pytest.mark.parametrize(
    "container",
    [
        list,  # rclpy gives uint8[] as a list of ints in some versions
        lambda raw: array.array("B", raw),  # and as array.array in others
        bytearray,
        memoryview,
        lambda raw: np.frombuffer(raw, dtype=np.uint8),
    ],
    ids=["list", "array.array", "bytearray", "memoryview", "numpy"],
)
def test_data_containers(cloud, container):
    msg = pack(cloud, XYZ_RGB, point_step=32)
    msg.data = container(msg.data)
    np.testing.assert_array_equal(as_points(msg), cloud)


def _without_z(msg: PointCloud2) -> None:
    msg.fields = [f for f in msg.fields if f.name != "z"]


def _int16_y(msg: PointCloud2) -> None:
    msg.fields[1].datatype = INT16


def _truncated(msg: PointCloud2) -> None:
    msg.data = msg.data[:-1]


def _all_nan(msg: PointCloud2) -> None:
    msg.data = np.full(len(msg.data) // 4, np.nan, dtype="<f4").tobytes()


def _bad_list(msg: PointCloud2) -> None:
    msg.data = [256] * len(msg.data)


def _z_past_record(msg: PointCloud2) -> None:
    msg.fields[2].offset = 30


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (_without_z, "PointCloud2 has no 'z' field (fields: x, y, rgb)"),
        (_int16_y, "field 'y' is INT16; only FLOAT32 (7) and FLOAT64 (8)"),
        (_truncated, "data holds 1599 bytes, fewer than row_step * height (1600 * 1 = 1600)"),
        (_all_nan, "no finite point: all 50 are NaN or infinite"),
        (_bad_list, "data is not a list of bytes"),
        (_z_past_record, "field 'z' (offset 30, 4 bytes) does not fit in point_step 32"),
    ],
)
def test_bad_messages_are_refused_with_a_sentence(cloud, spoil, message):
    msg = pack(cloud, XYZ_RGB, point_step=32)
    spoil(msg)
    with pytest.raises(InvalidPointsError) as caught:
        as_points(msg)
    assert message in str(caught.value)


def test_client_align_sends_the_finite_points_as_float32(make_api, align_answer):
    grid = np.random.default_rng(3).normal(size=(4, 6, 3)).astype(np.float32)
    grid[1, 2] = np.nan
    msg = pack(grid, XYZ_RGB, point_step=32, bigendian=True)
    api = make_api(lambda request: httpx.Response(200, json=align_answer()))
    result = api.align(msg, up=(0, 0, 1))
    (request,) = api.requests
    flat = grid.reshape(-1, 3)
    expected = flat[np.isfinite(flat).all(axis=1)].astype("<f4").tobytes()
    assert request.headers["content-type"] == "application/octet-stream"
    assert request.content == expected and len(expected) == 12 * 23
    assert result.model_id == "chair_0042" and result.up == (0.0, 0.0, 1.0)
