"""The refine stage: coarse-to-fine ICP from a rough pose, scale kept, surfaces cached."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.alignment import point_cloud
from catalign.registration.describe import QueryView
from catalign.registration.hypothesise import Hypothesis
from catalign.registration.refine import Refiner

POSE = make_pose(axis_angle(np.array([0.1, 1.0, 0.2]), 0.9), np.array([0.3, -0.1, 1.1]))
# a two-point hypothesis a few degrees and centimetres off
NUDGE = make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(4.0)), np.array([0.02, 0, 0]))


@pytest.fixture
def refiner(box_chair, make_entry, make_library) -> Refiner:
    library = make_library(make_entry("chair", box_chair.points))
    return Refiner(library, distance=0.03, normal_radius=0.06)


def _query(points: np.ndarray, pose: np.ndarray):
    keypoints, _ = voxel_downsample(transform(points, pose), 0.03)
    return keypoints, point_cloud(keypoints)


def _hypothesis(pose: np.ndarray, keypoints: np.ndarray) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis("chair", pose, np.zeros((0, 2), dtype=np.int64), view)


def test_a_rough_pose_is_refined_onto_the_surface(refiner: Refiner, box_chair) -> None:
    keypoints, query = _query(box_chair.points, POSE)
    rough = _hypothesis(NUDGE @ POSE, keypoints)
    refined = refiner.refine(rough, query)
    assert rotation_error_deg(refined.transform[:3, :3], POSE[:3, :3]) < 0.5
    assert np.linalg.norm(refined.transform[:3, 3] - POSE[:3, 3]) < 0.005
    assert refined.view is rough.view and refined.model_id == "chair"
    assert refiner.fit(refined, query).fitness > 0.95
    assert refiner.fit(rough, query).fitness < refiner.fit(refined, query).fitness


def test_a_similarity_pose_keeps_its_scale(refiner: Refiner, box_chair) -> None:
    scaled = POSE.copy()
    scaled[:3, :3] *= 1.1
    keypoints, query = _query(box_chair.points, scaled)
    start = NUDGE @ POSE
    start[:3, :3] *= 1.1
    refined = refiner.refine(_hypothesis(start, keypoints), query)
    assert np.cbrt(np.linalg.det(refined.transform[:3, :3])) == pytest.approx(1.1, rel=1e-9)
    assert rotation_error_deg(refined.transform[:3, :3] / 1.1, POSE[:3, :3]) < 0.5
    assert refiner.fit(refined, query).fitness > 0.95


def test_surfaces_are_cached_and_scaled_copies_leave_them_alone(refiner: Refiner) -> None:
    surface = refiner.surface("chair")
    assert refiner.surface("chair") is surface and surface.has_normals()
    before = np.asarray(surface.points).copy()
    scaled = refiner.surface("chair", 2.0)
    assert np.allclose(np.asarray(scaled.points), 2.0 * before)
    assert np.array_equal(np.asarray(refiner.surface("chair").points), before)
