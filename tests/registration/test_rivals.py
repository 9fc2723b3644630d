"""The rival check: a near-twin's winning pose, carried to the observed chair's own model and
refined, fits clearly better and replaces it; a right winner, or one that fits exactly, is
kept, and so is a winner that the rival's refined pose turned away from."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.describe import QueryView
from catalign.registration.hypothesise import Hypothesis
from catalign.registration.refine import Refiner
from catalign.registration.rivals import RivalCheck

POSE = make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), 0.8), np.array([0.4, -0.2, 1.5]))
DISTANCE = 0.03


@pytest.fixture
def library(box_chair, make_entry, make_library):
    """The box chair, and a twin 25 % larger about the same centre."""
    points = box_chair.points
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    twin = centre + 1.25 * (points - centre)
    return make_library(make_entry("chair", points), make_entry("twin", twin))


def _check(library, **options) -> RivalCheck:
    refiner = Refiner(library, distance=DISTANCE, icp_iterations=30, icp_points=None)
    settings = dict(
        rival_models=5,
        rival_icp=1,
        rival_margin=0.05,
        rival_turn_deg=180.0,
        rival_shift_m=10.0,
        exact_fitness=0.9,
    )
    return RivalCheck(library, refiner, **(settings | options))


def _posed(model_id: str, keypoints: np.ndarray, pose: np.ndarray = POSE) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis(model_id, pose, np.zeros((0, 2), dtype=np.int64), view)


def _observed(library, model_id: str) -> np.ndarray:
    keypoints, _ = voxel_downsample(transform(library[model_id].points, POSE), DISTANCE)
    return keypoints


def test_the_own_model_at_the_twins_pose_replaces_the_twin(library) -> None:
    keypoints = _observed(library, "chair")
    rival = _check(library).challenger(_posed("twin", keypoints), keypoints, ["twin", "chair"])
    assert rival is not None and rival.model_id == "chair"
    assert rotation_error_deg(rival.transform[:3, :3], POSE[:3, :3]) < 1.0
    assert np.linalg.norm(rival.transform[:3, 3] - POSE[:3, 3]) < 0.01


def test_a_winner_that_fits_better_is_kept(library) -> None:
    keypoints = _observed(library, "twin")
    check = _check(library, exact_fitness=1.0)  # challenged although it fits exactly
    assert check.challenger(_posed("twin", keypoints), keypoints, ["twin", "chair"]) is None


@pytest.mark.parametrize("options", [{"rival_models": 0}, {"exact_fitness": 0.0}])
def test_no_challenge_when_switched_off_or_the_winner_fits_exactly(library, options) -> None:
    keypoints = _observed(library, "chair")
    check = _check(library, **options)
    assert check.challenger(_posed("twin", keypoints), keypoints, ["twin", "chair"]) is None


def test_a_rival_whose_pose_turned_away_from_the_winners_is_not_taken(library) -> None:
    keypoints = _observed(library, "chair")
    turned = POSE @ make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(8.0)), np.zeros(3))
    winner = _posed("twin", keypoints, turned)
    free = _check(library).challenger(winner, keypoints, ["twin", "chair"])
    # ICP takes the own model back to the truth, 8 degrees from the winner's pose ...
    assert free is not None and free.model_id == "chair"
    assert rotation_error_deg(free.transform[:3, :3], POSE[:3, :3]) < 2.0
    # ... which a check that keeps the winner's pose refuses.
    assert (
        _check(library, rival_turn_deg=4.0).challenger(winner, keypoints, ["twin", "chair"]) is None
    )
    assert _check(library, rival_turn_deg=12.0).challenger(winner, keypoints, ["twin", "chair"])
