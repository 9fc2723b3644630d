"""Fuzzing the PCD readers: the service's header check then Open3D, and the SDK's refusal.

Inputs are valid ASCII, binary and LZF ``binary_compressed`` PCD files (the last from Open3D's
own writer) put through the mutators of ``_kit.py``, and random bytes. Property: finite (N, 3)
points within the limit, or the project's own error; never another exception, and never an
allocation that the file's size does not justify (Open3D sizes its arrays from the header). The
SDK has no PCD reader: it must refuse every file with the error that makes the CLI upload it.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catalign.errors import ShapeReadError
from catalign.geometry.io import read_points
from catalign_client._files import UnsupportedFileError
from catalign_client._files import read_points as client_read_points
from tests._memory import address_space_capped
from tests.fuzz._kit import SEED_POINTS, TARGETS, pcd_seeds, run_target

FUZZ = settings(max_examples=600, deadline=None, derandomize=True, database=None)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-pcd")


def test_every_seed_reads_as_points(folder: Path) -> None:
    for seed in pcd_seeds():
        assert run_target(TARGETS["pcd"], seed, folder) == SEED_POINTS


@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_service_reads_points_or_refuses(rng: random.Random, folder: Path) -> None:
    run_target(TARGETS["pcd"], TARGETS["pcd"].generate(rng), folder)


@settings(max_examples=50, deadline=None, derandomize=True, database=None)
@given(rng=st.randoms(use_true_random=False))
def test_sdk_leaves_every_pcd_to_the_server(rng: random.Random, folder: Path) -> None:
    path = folder / "sdk.pcd"
    path.write_bytes(TARGETS["sdk-pcd"].generate(rng))
    with pytest.raises(UnsupportedFileError):
        client_read_points(path)


def test_width_without_height_is_refused(folder: Path) -> None:
    """Open3D multiplies WIDTH by a HEIGHT it never set and asks for gigabytes (bad_alloc)."""
    binary = pcd_seeds()[1]
    path = folder / "no-height.pcd"
    path.write_bytes(binary.replace(b"HEIGHT 1\n", b"").replace(b"POINTS 50\n", b""))
    with address_space_capped(), pytest.raises(ShapeReadError, match="WIDTH but no HEIGHT"):
        read_points(path)


def test_a_field_of_no_values_is_refused(folder: Path) -> None:
    """Open3D reads a value of every field whatever its COUNT, and crashed (SIGSEGV) on 0."""
    path = folder / "no-values.pcd"
    path.write_bytes(pcd_seeds()[0].replace(b"COUNT 1 1 1\n", b"COUNT 1 1 -0\n"))
    with pytest.raises(ShapeReadError, match="has a field of no values"):
        read_points(path)


@pytest.mark.parametrize(
    "line", [b"POINTS\x80\x80 1111111111111111111111111111111", b"POINTSX 1", b"DATAX ascii"]
)
def test_a_keyword_with_more_after_it_is_refused(line: bytes, folder: Path) -> None:
    """Open3D takes a line for a keyword when it starts with one: a garbled POINTS line with a
    huge count made it ask for memory it has not (bad_alloc, found by the long fuzz run)."""
    path = folder / "near-keyword.pcd"
    path.write_bytes(pcd_seeds()[2].replace(b"POINTS 50", line))
    with address_space_capped(), pytest.raises(ShapeReadError, match="is not the"):
        read_points(path)


@pytest.mark.parametrize(
    ("edit", "why"),
    [
        ((b"WIDTH 50\nHEIGHT 1\n", b"HEIGHT 1\nWIDTH 50\n"), "HEIGHT line comes before any WIDTH"),
        ((b"WIDTH 50\n", b"WIDTH 1000000000\nHEIGHT 1\nWIDTH 50\n"), "2 WIDTH lines"),
    ],
    ids=["height-first", "repeated-width"],
)
def test_counts_open3d_would_take_from_elsewhere_are_refused(
    edit: tuple[bytes, bytes], why: str, folder: Path
) -> None:
    """Open3D multiplies at each HEIGHT line by the width read so far: uninitialised when HEIGHT
    comes first (bad_alloc or garbage, from run to run), a larger earlier WIDTH when repeated."""
    path = folder / "reordered.pcd"
    path.write_bytes(pcd_seeds()[1].replace(*edit))
    with address_space_capped(), pytest.raises(ShapeReadError, match=why):
        read_points(path)
