"""The verification checks read distance grids; KD-trees, which they replaced, are the reference.

A grid lookup may differ from the exact distance by about one cell (trilinear reads blunt the
distance field's cone at each surface point), so the scores are compared with the KD-tree
scores of the same formulas computed with distances one cell longer and one cell shorter.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from catalign.geometry.distance_grid import DistanceGrid
from catalign.geometry.se3 import axis_angle
from catalign.registration.stages.surface_checks import CoverageCheck, SurfaceCheck

UP = np.array([0.0, 1.0, 0.0])
CELL = 0.0125
DISTANCE = 0.05


def _grid(surface: np.ndarray) -> DistanceGrid:
    return DistanceGrid.around(surface, cell=CELL, truncation=0.075)


def _random_poses(rng: np.random.Generator, count: int, spread: float) -> np.ndarray:
    poses = np.stack([np.eye(4)] * count)
    for pose in poses:
        pose[:3, :3] = axis_angle(rng.normal(size=3), rng.uniform(0, 0.3))
        pose[:3, 3] = rng.normal(scale=spread, size=3)
    return poses


def _surface(rng: np.random.Generator, count: int = 3_000) -> np.ndarray:
    """Points on the faces of a box (a surface, not a volume: the distance field has cones)."""
    half = np.array([0.3, 0.45, 0.24])
    points = rng.uniform(-1.0, 1.0, (count, 3)) * half
    rows, axis = np.arange(count), rng.integers(0, 3, count)
    points[rows, axis] = np.sign(points[rows, axis]) * half[axis]
    return points


def _explained_by_tree(tree, probes, pose, slack: float) -> float:
    """The KD-tree reference: the surface check's formula with every distance moved by
    ``slack`` (clipped at zero)."""
    local = (probes - pose[:3, 3]) @ np.linalg.inv(pose[:3, :3]).T
    gaps, _ = tree.query(local)
    gaps = np.maximum(gaps + slack, 0.0)
    return float(np.clip(1 - (gaps / DISTANCE) ** 2, 0, None).mean())


def test_surface_grid_agrees_with_the_kd_tree_within_one_cell_on_random_poses() -> None:
    rng = np.random.default_rng(4)
    surface = _surface(rng)
    probes = surface[rng.choice(len(surface), 400, replace=False)] + rng.normal(
        scale=0.02, size=(400, 3)
    )
    poses = _random_poses(rng, 20, 0.03)
    poses[1, :3, :3] *= 1.1  # a similarity pose
    scores = SurfaceCheck(_grid(surface)).explained(probes, poses, DISTANCE)
    tree = cKDTree(surface)
    for pose, score in zip(poses, scores, strict=True):
        assert _explained_by_tree(tree, probes, pose, CELL) - 1e-9 <= score
        assert score <= _explained_by_tree(tree, probes, pose, -CELL) + 1e-9
        assert score == pytest.approx(_explained_by_tree(tree, probes, pose, 0.0), abs=0.03)


def test_surface_grid_reads_far_and_outside_points_as_unexplained() -> None:
    surface = _surface(np.random.default_rng(5))
    far = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, -0.2]])  # inside, outside
    assert SurfaceCheck(_grid(surface)).explained(far[1:2], np.eye(4)[None], DISTANCE)[0] == 0
    gaps = _grid(surface).distances(far)
    assert gaps[1] == pytest.approx(0.075)


def test_surface_check_refuses_a_distance_past_the_grid() -> None:
    surface = _surface(np.random.default_rng(6))
    with pytest.raises(ValueError, match="exceeds the library's distance grids"):
        SurfaceCheck(_grid(surface)).explained(surface[:5], np.eye(4)[None], 0.1)


def _covered_by_tree(observed, low, high, surface, pose, distance) -> float:
    posed = surface @ pose[:3, :3].T + pose[:3, 3]
    inside = np.all((posed >= low) & (posed <= high), axis=1)
    gaps, _ = cKDTree(observed).query(posed[inside])
    return float((gaps < distance).mean()) if inside.any() else 0.0


def test_coverage_grid_agrees_with_the_kd_tree_within_one_cell_on_random_poses() -> None:
    rng = np.random.default_rng(6)
    model = _surface(rng)
    observed = model[model[:, 2] > 0.0]  # a partial view: the model's front
    check = CoverageCheck(observed, margin=DISTANCE, cell=CELL)
    poses = _random_poses(rng, 20, 0.05)
    covered = check.covered(model, poses, DISTANCE)
    for pose, share in zip(poses, covered, strict=True):
        args = (observed, check.low, check.high, model, pose)
        # never more than the tree finds; at most what it finds a cell further out missed
        assert share <= _covered_by_tree(*args, DISTANCE) + 1e-9
        assert share >= _covered_by_tree(*args, DISTANCE - CELL) - 1e-9


def test_coverage_check_is_zero_when_nothing_lands_in_the_observed_region() -> None:
    observed = np.random.default_rng(7).uniform(0.0, 0.5, (100, 3))
    far = np.eye(4)
    far[:3, 3] = [10.0, 0.0, 0.0]
    check = CoverageCheck(observed, margin=DISTANCE, cell=CELL)
    assert check.covered(observed, far[None], DISTANCE)[0] == 0.0


def test_a_wide_region_gets_cells_large_enough_to_bound_the_grid() -> None:
    rng = np.random.default_rng(8)
    chair = rng.uniform(0.0, 0.5, (300, 3))
    stray = np.array([[3.0, 3.0, 3.0]])  # validation keeps points up to 3 m from the median
    check = CoverageCheck(np.vstack([chair, stray]), margin=DISTANCE, cell=CELL)
    assert check.nearest.size <= 1.05 * 500_000 and check.cell > CELL  # (cells + 1) per axis
    assert CoverageCheck(chair, margin=DISTANCE, cell=CELL).cell == CELL
    # coarser cells still measure real distances: most observed points find one near
    assert check.covered(chair, np.eye(4)[None], DISTANCE)[0] > 0.8
