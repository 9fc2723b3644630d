"""The rival check: a near-twin's winning pose, carried to the observed chair's own model and
refined, fits clearly better and replaces it; a right winner, or one that fits exactly, is
kept."""

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
    settings = dict(rival_models=5, rival_icp=1, rival_margin=0.05, exact_fitness=0.9)
    return RivalCheck(library, refiner, **(settings | options))


def _posed(model_id: str, keypoints: np.ndarray) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis(model_id, POSE, np.zeros((0, 2), dtype=np.int64), view)


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
