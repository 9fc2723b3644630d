"""Truncated distance grids: exact at the cell centres, trilinear between, far outside."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from catalign.geometry.distance_grid import LEVELS, DistanceGrid


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return np.random.default_rng(0).uniform(-0.2, 0.2, (500, 3)) * [1.0, 2.0, 0.5]


def test_cell_centres_hold_the_exact_distance_to_a_quantization_step(points) -> None:
    grid = DistanceGrid.around(points, cell=0.02, truncation=0.06)
    index = np.stack(np.indices(grid.values.shape), axis=-1).reshape(-1, 3)
    centres = grid.origin + grid.cell * index
    exact, _ = cKDTree(points).query(centres)
    read = grid.distances(centres)
    near = exact < grid.truncation
    assert np.all(np.abs(read[near] - exact[near]) <= grid.step / 2 + 1e-12)
    assert np.all(read[~near] == pytest.approx(grid.truncation))
    assert grid.values.dtype == np.uint8 and grid.values.max() == LEVELS


def test_between_centres_a_read_is_within_a_cell_of_the_exact_distance(points) -> None:
    grid = DistanceGrid.around(points, cell=0.0125, truncation=0.075)
    probes = points + np.random.default_rng(1).normal(scale=0.02, size=points.shape)
    exact, _ = cKDTree(points).query(probes)
    near = exact < 0.06
    assert np.all(np.abs(grid.distances(probes)[near] - exact[near]) <= grid.cell)


def test_outside_the_grid_reads_the_truncation(points) -> None:
    grid = DistanceGrid.around(points, cell=0.02, truncation=0.06)
    outside = np.array([[5.0, 0.0, 0.0], [0.0, -3.0, 0.0]])
    assert np.allclose(grid.distances(outside), grid.truncation)
