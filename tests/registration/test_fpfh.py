from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from catalign.data.shapes import Shape, SharedChairs, to_metric
from catalign.errors import CatalignError, ConfigError
from catalign.features.extractor import FPFHExtractor
from catalign.geometry.se3 import (
    axis_angle,
    make_pose,
    random_rotation,
    rotation_error_deg,
    transform,
    translation_error,
)
from catalign.registration.methods import METHODS, build_registrar
from catalign.registration.results import LibraryShape, Registrar, RegistrationResult
from catalign.registration.stages.nearest import mutual_nearest

RRE_MAX_DEG = 5.0
RTE_MAX_M = 0.03


def register_known_pose(points: np.ndarray, pose: np.ndarray) -> RegistrationResult:
    registrar = build_registrar("fpfh")
    registrar.prepare([LibraryShape("chair", points)])
    return registrar.register(transform(points, pose), seed=0)


def check_recovered(result: RegistrationResult, points: np.ndarray, pose: np.ndarray) -> None:
    assert result.model_id == "chair"
    assert rotation_error_deg(result.pose[:3, :3], pose[:3, :3]) < RRE_MAX_DEG
    assert translation_error(result.pose[:3, 3], pose[:3, 3]) < RTE_MAX_M
    # model -> observation: x_obs = R x_model + t puts the model onto the observation
    observed = transform(points, pose)
    placed = transform(points, result.pose)
    assert np.linalg.norm(placed - observed, axis=1).max() < RTE_MAX_M + 0.02
    assert cKDTree(observed).query(placed)[0].mean() < 0.01


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_known_pose_of_box_chair(box_chair: Shape, seed: int):
    rng = np.random.default_rng(seed)
    pose = make_pose(random_rotation(rng), rng.uniform(-1.0, 1.0, size=3))
    result = register_known_pose(box_chair.points, pose)
    check_recovered(result, box_chair.points, pose)
    assert result.fitness > 0.9
    assert result.num_inliers > 0 and 0.0 < result.inlier_ratio <= 1.0
    assert [c.model_id for c in result.candidates] == ["chair"]
    assert set(result.timings_ms) == {"features", "match_ransac_icp"}
    query_points, model_points = result.correspondences
    assert query_points.shape == model_points.shape and query_points.shape[1] == 3


def test_pose_convention_is_model_to_observation(box_chair: Shape):
    """A pure translation and a 90 degree yaw: the returned pose is the one applied to the
    model, not its inverse."""
    pose = make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), np.pi / 2), np.array([0.8, 0.0, -0.5]))
    result = register_known_pose(box_chair.points, pose)
    np.testing.assert_allclose(result.pose[:3, :3], pose[:3, :3], atol=0.05)
    np.testing.assert_allclose(result.pose[:3, 3], pose[:3, 3], atol=RTE_MAX_M)
    np.testing.assert_array_equal(result.pose[3], [0.0, 0.0, 0.0, 1.0])
    inverse_error = np.linalg.norm(np.linalg.inv(result.pose)[:3, 3] - pose[:3, 3])
    assert inverse_error > 0.5  # the inverse would be clearly wrong


def test_recovers_known_pose_of_a_shared_chair(shared_chairs: SharedChairs):
    # val[0] is symmetric under a half turn (a 180-degree answer is as right as the truth)
    shape = to_metric(shared_chairs.load(shared_chairs.ids("val")[1]))
    rng = np.random.default_rng(0)
    pose = make_pose(random_rotation(rng), rng.uniform(-1.0, 1.0, size=3))
    check_recovered(register_known_pose(shape.points, pose), shape.points, pose)


def test_picks_the_right_library_model(box_chair: Shape):
    rng = np.random.default_rng(5)
    ball = rng.normal(size=(8000, 3))
    ball = 0.4 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
    registrar = build_registrar("fpfh")
    registrar.prepare([LibraryShape("ball", ball), LibraryShape("chair", box_chair.points)])
    pose = make_pose(axis_angle(np.array([0.0, 0.0, 1.0]), 0.7), np.array([0.3, 0.2, 0.1]))
    result = registrar.register(transform(box_chair.points, pose), seed=0)
    assert result.model_id == "chair"
    assert [c.model_id for c in result.candidates] == ["chair", "ball"]
    assert result.candidates[0].score > result.candidates[1].score


def test_register_needs_prepare():
    with pytest.raises(RuntimeError, match="prepare"):
        build_registrar("fpfh").register(np.zeros((10, 3)))


def test_mutual_nearest():
    features = np.eye(40)
    order = np.random.default_rng(0).permutation(40)
    matches = mutual_nearest(features, features[order])
    assert len(matches) == 40
    np.testing.assert_array_equal(order[matches[:, 1]], matches[:, 0])
    # too few mutual matches: fall back to the nearest in both directions (here the same 5)
    few = mutual_nearest(features[:5], features[:5], min_mutual=30)
    assert few.shape == (5, 2)


def test_build_registrar():
    registrar = build_registrar("fpfh")
    assert isinstance(registrar, Registrar)
    assert isinstance(registrar.extractor, FPFHExtractor)
    assert registrar.name == "fpfh"
    assert "fpfh" in METHODS


def test_build_registrar_unknown_name():
    with pytest.raises(
        ConfigError, match="unknown method 'nope'; known methods: fpfh, fpfh-engine, learned"
    ):
        build_registrar("nope")
    assert issubclass(ConfigError, CatalignError)
