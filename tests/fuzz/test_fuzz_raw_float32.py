"""Fuzzing the raw ``application/octet-stream`` body: N * 12 bytes of little-endian float32.

Inputs are valid bodies (50 points, one point) truncated, flipped, spliced, repeated and with
words set to NaN, infinity or huge values, plus random bytes. Property: :func:`decode_binary`
gives finite (N, 3) points within the limit, or :class:`InvalidInputError`; never another
exception.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catalign.api.inputs import decode_binary
from catalign.api.schemas import RegisterOptions
from catalign.errors import InvalidInputError
from tests.fuzz._kit import MAX_POINTS, TARGETS, float32_seeds, run_target

FUZZ = settings(max_examples=800, deadline=None, derandomize=True, database=None)
TARGET = TARGETS["raw-float32"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-raw")


def test_every_seed_reads_as_points(folder: Path) -> None:
    assert [run_target(TARGET, seed, folder) for seed in float32_seeds()] == [50, 1]


@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_reads_points_or_refuses(rng: random.Random, folder: Path) -> None:
    run_target(TARGET, TARGET.generate(rng), folder)


@FUZZ
@given(body=st.binary(max_size=600))
def test_any_bytes_read_as_their_points_or_are_refused(body: bytes) -> None:
    """A body that reads gives back exactly its own float32 values."""
    try:
        points = decode_binary(body, RegisterOptions(), MAX_POINTS).points
    except InvalidInputError:
        return
    assert points is not None
    np.testing.assert_array_equal(points, np.frombuffer(body, "<f4").reshape(-1, 3))
