"""The hypothesise stage: upright poses from pairs with ``up``, one free pose without."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.levelling import leveller
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesiser
from catalign.registration.stages.match import Matches

Z_UP = np.array([0.0, 0.0, 1.0])


def _hypothesiser(**options) -> Hypothesiser:
    defaults = {
        "distance": 0.02,
        "pair_draws": 2_000,
        "poses_per_view": 4,
        "ransac_iterations": 5_000,
        "up_tolerance_deg": 30.0,
    }
    return Hypothesiser(**(defaults | options))


def _matches(pose: np.ndarray, outliers: float = 0.4, seed: int = 0) -> Matches:
    """Matches of 200 model points posed by ``pose``, a share of them wrong."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(-0.3, 0.3, (200, 3))
    observed = transform(model, pose)
    wrong = rng.random(len(model)) < outliers
    observed[wrong] = rng.uniform(-0.3, 0.3, (int(wrong.sum()), 3)) + pose[:3, 3]
    pairs = np.stack([np.arange(200), np.arange(200)], axis=1)
    view = QueryView(observed, np.zeros((200, 4), dtype=np.float32))
    return Matches("m", view, pairs, model)


def _upright_pose(yaw: float) -> np.ndarray:
    """Model +Y onto world +Z, turned by ``yaw`` about it, and moved."""
    rotation = axis_angle(Z_UP, yaw) @ leveller(Z_UP).T
    return make_pose(rotation, np.array([0.5, -0.2, 0.8]))


def test_with_up_the_best_pose_first_and_every_pose_upright() -> None:
    pose = _upright_pose(2.0)
    found = _hypothesiser().poses(_matches(pose), leveller(Z_UP), estimate_scale=False, seed=0)
    assert 1 <= len(found) <= 4
    best = found[0]
    assert best.model_id == "m" and best.matches.shape == (200, 2)
    assert rotation_error_deg(best.transform[:3, :3], pose[:3, :3]) < 1.0
    assert np.linalg.norm(best.transform[:3, 3] - pose[:3, 3]) < 0.01
    for hypothesis in found:  # every one stands the model's up along the world's
        assert np.allclose(hypothesis.transform[:3, :3] @ np.array([0, 1.0, 0]), Z_UP)


def test_with_up_distinct_poses_are_kept_for_verification() -> None:
    """Half the matches say one heading, half the heading turned round (a chair's front and
    back): both poses are proposed, for the surface to decide."""
    front, back = _upright_pose(0.5), _upright_pose(0.5 + np.pi)
    one, other = _matches(front, outliers=0.0, seed=1), _matches(back, outliers=0.0, seed=2)
    view = QueryView(np.concatenate([one.observed, other.observed]), np.zeros((400, 4)))
    pairs = np.stack([np.arange(400), np.arange(400)], axis=1)
    both = Matches("m", view, pairs, np.concatenate([one.model_points, other.model_points]))
    found = _hypothesiser().poses(both, leveller(Z_UP), estimate_scale=False, seed=0)
    errors = [
        min(rotation_error_deg(h.transform[:3, :3], p[:3, :3]) for h in found)
        for p in (front, back)
    ]
    assert max(errors) < 1.0


def test_without_up_one_free_pose() -> None:
    pose = make_pose(axis_angle(np.array([0.3, 1.0, -0.2]), 1.3), np.array([0.1, 0.4, 1.2]))
    found = _hypothesiser().poses(_matches(pose), None, estimate_scale=False, seed=0)
    assert len(found) == 1
    assert rotation_error_deg(found[0].transform[:3, :3], pose[:3, :3]) < 1.0


def test_a_scale_is_estimated_by_the_three_point_search_even_with_up() -> None:
    pose = _upright_pose(0.7)
    pose[:3, :3] *= 1.2
    found = _hypothesiser().poses(
        _matches(pose, outliers=0.2), leveller(Z_UP), estimate_scale=True, seed=0
    )
    assert len(found) == 1
    assert np.cbrt(np.linalg.det(found[0].transform[:3, :3])) == pytest.approx(1.2, rel=0.01)


def test_the_same_seed_gives_the_same_poses() -> None:
    matches, turn = _matches(_upright_pose(1.0)), leveller(Z_UP)
    one = _hypothesiser().poses(matches, turn, estimate_scale=False, seed=4)
    two = _hypothesiser().poses(matches, turn, estimate_scale=False, seed=4)
    assert all(np.array_equal(a.transform, b.transform) for a, b in zip(one, two, strict=True))
