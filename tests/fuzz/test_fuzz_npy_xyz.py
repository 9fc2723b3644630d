"""Fuzzing the ``.npy`` and ``.xyz`` readers of the service (header check, numpy) and the SDK.

Inputs are valid ``.npy`` files (float64 v1.0, float32 v2.0, big-endian float64) with their
header's shape, type and length edited, and ``.xyz`` text (spaces; commas with normals and a
comment) with its numbers and lines edited, plus random bytes. Property: finite (N, 3) points
within the limit, or the project's own error; never another exception (numpy's tokenizer errors,
overflow) and never an allocation that the file's size does not justify.
"""

from __future__ import annotations

import random
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catalign.errors import ShapeReadError
from catalign.geometry.io import read_points
from catalign_client import InvalidPointsError
from catalign_client._files import read_points as client_read_points
from tests._memory import address_space_capped
from tests.fuzz._kit import (
    SEED_POINTS,
    TARGETS,
    npy_seeds,
    run_target,
    xyz_seeds,
)

FUZZ = settings(max_examples=500, deadline=None, derandomize=True, database=None)
NAMES = ["npy", "xyz", "sdk-npy", "sdk-xyz"]
SEEDS = {"npy": npy_seeds, "xyz": xyz_seeds, "sdk-npy": npy_seeds, "sdk-xyz": xyz_seeds}


def npy_with_header(header: bytes, version: int = 1, body: bytes = b"") -> bytes:
    length = struct.pack("<H" if version == 1 else "<I", len(header))
    return b"\x93NUMPY" + bytes([version, 0]) + length + header + body


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-npy-xyz")


@pytest.mark.parametrize("name", NAMES)
def test_every_seed_reads_as_points(name: str, folder: Path) -> None:
    for seed in SEEDS[name]():
        assert run_target(TARGETS[name], seed, folder) == SEED_POINTS


@pytest.mark.parametrize("name", NAMES)
@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_reads_points_or_refuses(name: str, rng: random.Random, folder: Path) -> None:
    run_target(TARGETS[name], TARGETS[name].generate(rng), folder)


UNCLOSED = b"{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3\n"
HUGE_SHAPE = b"{'descr': '<f8', 'fortran_order': False, 'shape': (10000000000000, 3), }\n"
OVERFLOWING_SHAPE = (
    b"{'descr': '<f8', 'fortran_order': False, 'shape': (9223372036854775808, 3), }\n"
)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (npy_with_header(UNCLOSED), "EOF in multi-line statement"),
        (npy_with_header(HUGE_SHAPE, body=bytes(48)), "but the file holds 48"),
        (npy_with_header(OVERFLOWING_SHAPE, body=bytes(48)), "but the file holds 48"),
        (npy_with_header(b"{", version=2)[:8] + b"\xff\xff\xff\xff{", "header is longer"),
    ],
    ids=["unclosed-header", "huge-shape", "overflowing-shape", "4gb-header"],
)
def test_sdk_refuses_npy_headers_that_lie(data: bytes, why: str, folder: Path) -> None:
    """numpy raised TokenError, MemoryError or OverflowError for these before the SDK checked."""
    path = folder / "lying.npy"
    path.write_bytes(data)
    with address_space_capped(), pytest.raises(InvalidPointsError, match=why):
        client_read_points(path)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (npy_with_header(UNCLOSED), "EOF in multi-line statement"),
        (npy_with_header(b"{", version=2)[:8] + b"\xff\xff\xff\xff{", "declared 4294967295 bytes"),
    ],
    ids=["unclosed-header", "4gb-header"],
)
def test_service_refuses_npy_headers_that_lie(data: bytes, why: str, folder: Path) -> None:
    """The header check let numpy's TokenError out, and read a 4 GB header (MemoryError)."""
    path = folder / "lying.npy"
    path.write_bytes(data)
    with address_space_capped(), pytest.raises(ShapeReadError, match=why):
        read_points(path)
