"""Shared fixtures: the shared chairs and tables (skipped when absent), the shipped weights (the
server tests are skipped without them; ``CATALIGN_TEST_MODEL_DIR`` names other ones), small
synthetic shapes."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from catalign.data.shapes import Shape, SharedChairs, default_chairs_root, default_tables_root
from catalign.features.extractor import DEFAULT_MODEL_DIR
from catalign.geometry.io import MeshData
from catalign.geometry.sampling import sample_surface


@pytest.fixture(scope="session")
def chairs_root() -> Path:
    """The shared chairs folder; tests that need it are skipped when it is absent."""
    root = default_chairs_root()
    if not (root / "pointclouds").is_dir() or not (root / "meshes").is_dir():
        pytest.skip(f"shared chairs not found at {root} (set CATALIGN_CHAIRS_DIR)")
    return root


@pytest.fixture(scope="session")
def tables_root() -> Path:
    """The shared tables folder (point clouds only); skipped when absent."""
    root = default_tables_root()
    if not (root / "pointclouds").is_dir():
        pytest.skip(f"shared tables not found at {root} (set CATALIGN_TABLES_DIR)")
    return root


@pytest.fixture(scope="session")
def model_dir() -> Path:
    """The extractor weights the server tests serve with; skipped when there are none."""
    path = Path(os.environ.get("CATALIGN_TEST_MODEL_DIR", DEFAULT_MODEL_DIR))
    if not (path / "model.safetensors").is_file() or not (path / "model_card.json").is_file():
        pytest.skip("model_store/ has no trained weights yet")
    return path


@pytest.fixture(scope="session")
def shared_chairs(chairs_root: Path) -> SharedChairs:
    return SharedChairs(chairs_root)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def _shape_from_trimesh(mesh: trimesh.Trimesh, shape_id: str = "mesh", count: int = 4000) -> Shape:
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    points = sample_surface(vertices, faces, count, np.random.default_rng(0))
    return Shape(shape_id=shape_id, points=points, mesh=MeshData(vertices=vertices, faces=faces))


@pytest.fixture
def shape_from_trimesh() -> Callable[..., Shape]:
    """Factory: a :class:`Shape` (surface points and mesh) from a trimesh mesh."""
    return _shape_from_trimesh


def _box_chair_mesh() -> trimesh.Trimesh:
    """A metric chair of boxes in the canonical frame (+Y up, backrest on +Z), with one armrest
    so that it has no rotational symmetry."""

    def box(extents: tuple[float, float, float], centre: tuple[float, float, float]):
        return trimesh.creation.box(
            extents=extents, transform=trimesh.transformations.translation_matrix(centre)
        )

    parts = [box((0.45, 0.05, 0.45), (0.0, 0.45, 0.0))]
    parts += [box((0.04, 0.45, 0.04), (x, 0.225, z)) for x in (-0.2, 0.2) for z in (-0.2, 0.2)]
    parts.append(box((0.45, 0.45, 0.04), (0.0, 0.7, 0.2)))
    parts.append(box((0.04, 0.04, 0.35), (0.22, 0.65, 0.0)))
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="session")
def box_chair() -> Shape:
    """A chair-like metric shape with 15,000 surface points and its mesh."""
    return _shape_from_trimesh(_box_chair_mesh(), "box-chair", count=15_000)


@pytest.fixture(scope="session")
def panel_with_a_leg() -> np.ndarray:
    """A flat 0.6 x 0.5 m panel in z = 0 (a backrest seen face on, 2 mm noise) with 0.4 % of
    the points on a thin leg reaching 0.4 m under it: all plane but for the leg, so a floor by
    every rule of :func:`~catalign.registration.prepare.floor.floor_mask` under +Z."""
    rng = np.random.default_rng(0)
    panel = np.column_stack(
        [rng.uniform(-0.3, 0.3, 9960), rng.uniform(-0.25, 0.25, 9960), rng.normal(0, 0.002, 9960)]
    )
    leg = np.column_stack(
        [rng.normal(0.1, 0.01, 40), rng.normal(0.0, 0.01, 40), rng.uniform(-0.4, 0.0, 40)]
    )
    return np.vstack([panel, leg])
