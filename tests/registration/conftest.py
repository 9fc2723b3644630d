"""Fixtures for the registration stages: small in-memory libraries, no index on disk."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from catalign.geometry.distance_grid import CELL_VOXELS, TRUNCATION_VOXELS, DistanceGrid
from catalign.library.entry import LibraryEntry
from catalign.library.loaded import Library
from catalign.library.retrieval import global_descriptor
from catalign.library.store import Manifest


def entry(
    model_id: str,
    points: np.ndarray,
    keypoints: np.ndarray | None = None,
    features: np.ndarray | None = None,
    voxel_size: float = 0.03,
) -> LibraryEntry:
    """A library entry from surface ``points``; key points default to the points themselves
    and features to random unit vectors (seeded by the id's length, so fixed per id); its
    distance grid as a library of ``voxel_size`` builds it."""
    points = np.asarray(points, dtype=np.float64)
    keypoints = points if keypoints is None else keypoints
    if features is None:
        features = np.random.default_rng(len(model_id)).normal(size=(len(keypoints), 8))
        features /= np.linalg.norm(features, axis=1, keepdims=True)
    low, high = points.min(axis=0), points.max(axis=0)
    return LibraryEntry(
        model_id=model_id,
        points=points.astype(np.float32),
        keypoints=np.asarray(keypoints, dtype=np.float64),
        features=np.asarray(features, dtype=np.float32),
        descriptor=global_descriptor(features),
        bbox_min=low,
        bbox_max=high,
        size=high - low,
        grid=DistanceGrid.around(
            points, cell=CELL_VOXELS * voxel_size, truncation=TRUNCATION_VOXELS * voxel_size
        ),
        source=f"test:{model_id}",
        source_sha256="0" * 64,
        units="m",
    )


def library_of(*entries: LibraryEntry, voxel_size: float = 0.03) -> Library:
    """A loaded library holding ``entries``, as :func:`catalign.library.loaded.load` gives it."""
    manifest = Manifest(fingerprint="test", voxel_size=voxel_size, created="", updated="")
    return Library(Path("/nonexistent/test-library"), manifest, entries)


@pytest.fixture
def make_entry() -> Callable[..., LibraryEntry]:
    """Factory: :func:`entry`."""
    return entry


@pytest.fixture
def make_library() -> Callable[..., Library]:
    """Factory: :func:`library_of`."""
    return library_of
