"""Fuzzing :func:`pointcloud2_points` with PointCloud2-shaped messages (no ROS needed).

Inputs are a valid organized cloud (10 x 5 records of x, y, z, intensity float32 and padding,
padded rows, one NaN point; either byte order) with one to three parts edited: height, width,
point_step or row_step set to uint32 edges, neighbours or wrong types; fields dropped, repeated,
renamed or given other offsets and datatypes; data truncated, flipped, or handed over as a list
(with out-of-range ints), bytearray, ``array.array``, strided memoryview or float32 array.
Property: finite (N, 3) float64 points, or :class:`InvalidPointsError`; never another
exception and never a read outside the buffer.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catalign_client import InvalidPointsError
from catalign_client._pointcloud2 import pointcloud2_points
from tests.fuzz._kit import TARGETS, pointcloud2_message, run_target, seed_points

FUZZ = settings(max_examples=1000, deadline=None, derandomize=True, database=None)
TARGET = TARGETS["sdk-pointcloud2"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-pointcloud2")


@pytest.mark.parametrize("big_endian", [False, True])
def test_the_valid_message_reads_its_points(big_endian: bool) -> None:
    points = pointcloud2_points(pointcloud2_message(big_endian=big_endian))
    np.testing.assert_array_equal(points, seed_points()[1:50])


@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_reads_points_or_refuses(rng: random.Random, folder: Path) -> None:
    run_target(TARGET, TARGET.generate(rng), folder)


def test_a_record_larger_than_numpy_allows_is_refused() -> None:
    """A uint32 point_step past a C int made numpy's record type raise ValueError."""
    msg = pointcloud2_message()
    msg.width, msg.point_step = 0, 2**32 - 1
    with pytest.raises(InvalidPointsError, match="has no points"):
        pointcloud2_points(msg)
