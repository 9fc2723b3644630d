"""Fuzzing the PLY readers: the service's header check and trimesh, and the SDK's numpy reader.

Inputs are valid ASCII, binary little- and big-endian PLY clouds and meshes put through the
mutators of ``_kit.py`` (truncation, flipped bytes, edited counts, types and header lines), and
random bytes. Property: finite (N, 3) points within the limit (meshes: faces that index existing
vertices), or the project's own error; never another exception or a huge allocation.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catalign.errors import ShapeReadError
from catalign.geometry.io import read_mesh
from catalign_client import InvalidPointsError
from catalign_client._files import read_points as client_read_points
from tests.fuzz._kit import TARGETS, ply_seeds, run_target

FUZZ = settings(max_examples=600, deadline=None, derandomize=True, database=None)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-ply")


@pytest.mark.parametrize("name", ["ply", "sdk-ply"])
def test_every_seed_reads_as_points(name: str, folder: Path) -> None:
    """The mutations start from files that read: otherwise they only test the first check."""
    for seed in ply_seeds():
        assert run_target(TARGETS[name], seed, folder) in (42, 50)


@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_service_reads_points_or_refuses(rng: random.Random, folder: Path) -> None:
    run_target(TARGETS["ply"], TARGETS["ply"].generate(rng), folder)


@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_sdk_reads_points_or_refuses(rng: random.Random, folder: Path) -> None:
    run_target(TARGETS["sdk-ply"], TARGETS["sdk-ply"].generate(rng), folder)


def test_faces_of_missing_vertices_are_refused(folder: Path) -> None:
    """trimesh keeps a face index past the vertices; the mesh would crash surface sampling."""
    mesh = ply_seeds()[1]  # ASCII, 42 vertices and 80 triangles
    first_face = mesh.index(b"\n3 ") + 1
    path = folder / "missing-vertex.ply"
    path.write_bytes(mesh[:first_face] + b"3 0 1 4000" + mesh[mesh.index(b"\n", first_face) :])
    with pytest.raises(ShapeReadError, match="refer to vertices 0 to 4000"):
        read_mesh(path)


def test_sdk_refuses_a_repeated_property(folder: Path) -> None:
    """numpy cannot build a record type with two fields of one name (it raised ValueError)."""
    binary = ply_seeds()[2]
    path = folder / "repeated.ply"
    path.write_bytes(binary.replace(b"property float z", b"property float y", 1))
    with pytest.raises(InvalidPointsError, match="two properties named 'y'"):
        client_read_points(path)
