"""The query frame: found from the cloud alone, so a rigidly moved cloud lands on the same
points there, and answers found there go back to the observation exactly."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.shapes import procedural_shape
from catalign.frames import MODEL_UP
from catalign.geometry.se3 import make_pose, random_rotation, transform
from catalign.registration.prepare.frame import query_frame
from catalign.registration.prepare.validation import DENSE_POINTS, validate_cloud
from catalign.registration.results import Alternative, Orientation, RegistrationResult
from catalign.registration.stages.describe import rotations_of

UP = np.array([0.0, 0.0, 1.0])


def _cloud(seed: int) -> np.ndarray:
    """A lopsided box of points: distinct spreads and skewed along each axis."""
    rng = np.random.default_rng(seed)
    return rng.exponential([0.4, 0.2, 0.1], size=(500, 3)) + np.array([0.3, -0.1, 0.2])


def _motion(seed: int, keep_up: bool) -> np.ndarray:
    """A rigid motion; about ``UP`` only when ``keep_up`` (a robot that knows up moved)."""
    rng = np.random.default_rng(seed)
    if keep_up:
        angle = rng.uniform(-np.pi, np.pi)
        rotation = np.array(
            [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
        )
    else:
        rotation = random_rotation(rng)
    return make_pose(rotation, rng.uniform(-2, 2, size=3))


@pytest.mark.parametrize("with_up", [True, False], ids=["up", "no-up"])
@pytest.mark.parametrize("seed", range(5))
def test_a_moved_cloud_lands_on_the_same_points(seed: int, with_up: bool) -> None:
    points = _cloud(seed)
    motion = _motion(100 + seed, keep_up=False)
    up = UP if with_up else None
    moved_up = motion[:3, :3] @ UP if with_up else None
    here = query_frame(points, up).points(points)
    there = query_frame(transform(points, motion), moved_up).points(transform(points, motion))
    np.testing.assert_allclose(there, here, atol=1e-9)


@pytest.mark.parametrize("with_up", [True, False], ids=["up", "no-up"])
@pytest.mark.parametrize("seed", range(5))
def test_a_moved_mirror_symmetric_cloud_lands_on_the_same_points(seed: int, with_up: bool) -> None:
    """A chair is mirror-symmetric from side to side, its widest axis often that one: the
    frame must not hang on the sign of its (zero) third moment."""
    half = _cloud(seed) * np.array([2.0, 1.0, 1.0])  # widest along x, as a broad chair
    points = np.concatenate([half, half * np.array([-1.0, 1.0, 1.0])])
    motion = _motion(200 + seed, keep_up=False)
    moved_up = motion[:3, :3] @ UP if with_up else None
    here = query_frame(points, UP if with_up else None).points(points)
    there = query_frame(transform(points, motion), moved_up).points(transform(points, motion))
    np.testing.assert_allclose(there, here, atol=1e-9)


@pytest.mark.parametrize("with_up", [True, False], ids=["up", "no-up"])
def test_a_moved_dense_cloud_is_thinned_on_the_same_grid(with_up: bool) -> None:
    """A dense cloud is thinned on a grid of quarter voxels: laid in the query's own frame, the
    same chair seen from a moved sensor keeps the same points."""
    rng = np.random.default_rng(0)
    surface = procedural_shape(0).points
    points = np.concatenate([surface + rng.normal(scale=1e-3, size=surface.shape)] * 8)
    assert len(points) > DENSE_POINTS
    motion = _motion(300, keep_up=False)
    up, moved_up = (UP, motion[:3, :3] @ UP) if with_up else (None, None)
    here = validate_cloud(points, voxel_size=0.025, up=up)
    there = validate_cloud(transform(points, motion), voxel_size=0.025, up=moved_up)
    assert len(here.points) < DENSE_POINTS and len(there.points) == len(here.points)
    np.testing.assert_allclose(there.points, here.points, atol=1e-9)


def test_with_up_the_frame_is_levelled_and_centred() -> None:
    points = _cloud(0)
    frame = query_frame(points, 2 * UP)
    np.testing.assert_allclose(frame.direction(UP), MODEL_UP, atol=1e-12)
    np.testing.assert_allclose(frame.points(points).mean(axis=0), 0.0, atol=1e-12)
    assert frame.direction(None) is None


def _result(pose: np.ndarray, orientation: Orientation) -> RegistrationResult:
    return RegistrationResult(
        model_id="m",
        pose=pose,
        fitness=0.5,
        inlier_rmse=0.01,
        num_inliers=10,
        inlier_ratio=0.5,
        candidates=[],
        timings_ms={},
        correspondences=(np.ones((2, 3)), np.zeros((2, 3))),
        orientations=(orientation,),
        orientation=orientation,
        alternatives=(Alternative("a", pose, 0.1, 0.2, None),),
    )


@pytest.mark.parametrize("seed", range(3))
def test_an_answer_goes_back_to_the_observation(seed: int) -> None:
    points = _cloud(seed)
    up = _motion(seed, keep_up=False)[:3, :3] @ UP
    frame = query_frame(points, up)
    model = np.random.default_rng(seed).normal(size=(20, 3))
    found = make_pose(random_rotation(np.random.default_rng(seed + 7)), np.array([0.1, 0.2, 0.3]))
    searched = Orientation(
        frame.direction(up),
        given=True,
        headings=(0.4, -2.0),
        headings_proposed=True,
        floor_level=-0.3,
        proposed_headings=((0.4, 0.7), (-2.0, 0.2)),
    )
    back = frame.result(_result(found, searched))

    # the pose puts the model where it was found, seen from the observation
    np.testing.assert_allclose(frame.points(transform(model, back.pose)), transform(model, found))
    np.testing.assert_allclose(back.alternatives[0].pose, back.pose)
    np.testing.assert_allclose(frame.points(back.correspondences[0]), np.ones((2, 3)), atol=1e-12)
    # the orientation describes the observation as the searched one described the frame
    turned = back.orientation
    np.testing.assert_allclose(turned.up, up, atol=1e-12)
    for there, here in zip(rotations_of(turned), rotations_of(searched), strict=True):
        np.testing.assert_allclose(there, here @ frame.rotation, atol=1e-12)
    assert [m for _, m in turned.proposed_headings] == [0.7, 0.2]
    heights = frame.points(points) @ searched.up, points @ turned.up
    np.testing.assert_allclose(heights[1] - heights[0], turned.floor_level + 0.3, atol=1e-12)
