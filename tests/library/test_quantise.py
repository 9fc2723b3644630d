"""The narrowing of what an entry stores: each narrowing gives back values that narrow to
themselves (an entry in memory equals its file), within the step it promises."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.distance_grid import LEVELS, DistanceGrid
from catalign.library.quantise import (
    GRID_STEPS,
    SURFACE_STEPS,
    grid_from_steps,
    grid_steps,
    narrowed_grid,
    narrowed_keypoints,
    narrowed_points,
    stored_surface,
)


@pytest.fixture
def surface() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.uniform([-0.3, 0.0, -0.25], [0.3, 0.9, 0.25], size=(2_000, 3))


def test_grid_levels_narrow_to_themselves_and_far_stays_far(surface):
    grid = DistanceGrid.around(surface, cell=0.0125, truncation=0.075)
    narrowed = narrowed_grid(grid)
    np.testing.assert_array_equal(narrowed_grid(narrowed).values, narrowed.values)
    far = grid.values == LEVELS
    assert far.any() and (narrowed.values[far] == LEVELS).all()
    # what becomes "far" was within half a step of it: beyond every check's inlier distance
    assert (grid.values[narrowed.values == LEVELS] >= LEVELS * (1 - 0.5 / GRID_STEPS)).all()
    # within half a step of GRID_STEPS over the truncation, in metres
    error = np.abs(narrowed.values.astype(float) - grid.values) * grid.step
    assert error.max() <= grid.truncation / GRID_STEPS / 2 + grid.step / 2
    probes = surface[:300] + 0.01
    assert np.abs(narrowed.distances(probes) - grid.distances(probes)).max() <= 0.002


def test_grid_steps_beyond_six_bits_are_refused():
    # 128 is 31.6 steps of 255/63: step 32, which stands for 129.5, stored as 130
    assert grid_from_steps(grid_steps(np.array([0, 128, 255], np.uint8))).tolist() == [0, 130, 255]
    with pytest.raises(ValueError, match="beyond"):
        grid_from_steps(np.array([GRID_STEPS + 1], np.uint8))


def test_the_surface_is_stored_sorted_whole_and_in_twelve_bits(surface):
    low, high = surface.min(axis=0), surface.max(axis=0)
    stored = stored_surface(surface, low, high)
    assert (np.diff(stored[:, 0]) >= 0).all()
    step = (high - low) / SURFACE_STEPS
    gaps = np.abs(np.sort(stored, axis=0) - np.sort(surface, axis=0))
    assert (gaps <= step / 2 + 1e-6).all()
    np.testing.assert_array_equal(stored_surface(stored, low, high), stored)  # narrowed once


def test_key_points_narrow_within_the_grid_box_to_themselves(surface):
    grid = DistanceGrid.around(surface, cell=0.0125, truncation=0.075)
    keypoints = surface[::7] + 0.0125  # voxel centres may leave the surface's box
    narrowed = narrowed_keypoints(keypoints, *grid.box)
    np.testing.assert_array_equal(narrowed_keypoints(narrowed, *grid.box), narrowed)
    span = grid.box[1] - grid.box[0]
    assert np.abs(narrowed - keypoints).max() <= span.max() / 65_535
    np.testing.assert_array_equal(narrowed_points(narrowed, *grid.box), narrowed.astype(np.float32))
