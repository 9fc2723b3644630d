"""The category fit: another instance's frame placed on the observed chair's, pose rigid."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.levelling import leveller
from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.stages.category_fit import (
    ROUGH_TILT_DEG,
    CategoryFitter,
    rough_up_estimate,
    supported,
)
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import Refiner

Z_UP = np.array([0.0, 0.0, 1.0])
TURN = leveller(Z_UP)
# model +Y onto world +Z, turned about it, moved
POSE = make_pose(axis_angle(Z_UP, 0.6) @ TURN.T, np.array([0.3, -0.2, 0.0]))


@pytest.fixture
def fitter(box_chair, make_entry, make_library) -> CategoryFitter:
    library = make_library(make_entry("chair", box_chair.points))
    refiner = Refiner(library, distance=0.03, icp_iterations=30, icp_points=None)
    return CategoryFitter(library, refiner, extent_points=1_500)


def _hypothesis(pose: np.ndarray, keypoints: np.ndarray) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis("chair", pose, np.zeros((0, 2), dtype=np.int64), view)


def _observe(points: np.ndarray) -> np.ndarray:
    keypoints, _ = voxel_downsample(transform(points, POSE), 0.03)
    return keypoints


def _centre_error(fitter: CategoryFitter, pose: np.ndarray, observed_centre: np.ndarray) -> float:
    centre = fitter.library["chair"].centre
    return float(np.linalg.norm(transform(centre[None], pose)[0] - observed_centre))


def test_isolated_points_do_not_count_unless_most_are() -> None:
    grid = np.stack(np.meshgrid(*[np.arange(5) * 0.01] * 3), axis=-1).reshape(-1, 3)
    strays = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    assert np.array_equal(supported(np.concatenate([grid, strays]), 0.015), grid)
    assert np.array_equal(supported(strays, 0.015), strays)


def test_a_larger_chair_gets_the_model_centre_on_its_own(fitter, box_chair) -> None:
    """15% larger than the model: the rigid fit hugs one side; the category fit puts the
    model's centre on the observed chair's, the pose upright and rigid."""
    centre = fitter.library["chair"].centre
    larger = (box_chair.points - centre) * 1.15 + centre
    keypoints = _observe(larger)
    hugging = make_pose(np.eye(3), np.array([0.04, 0.0, 0.03])) @ POSE
    hugging = fitter.refiner.refine(_hypothesis(hugging, keypoints), keypoints)
    observed_centre = transform(centre[None], POSE)[0]
    assert _centre_error(fitter, hugging.transform, observed_centre) > 0.015
    fitted = fitter.fit(hugging, keypoints, TURN, solid=supported(keypoints, 0.06))
    assert _centre_error(fitter, fitted.transform, observed_centre) < 0.01
    assert rotation_error_deg(fitted.transform[:3, :3], POSE[:3, :3]) < 2.0
    assert np.linalg.det(fitted.transform[:3, :3]) == pytest.approx(1.0)


def test_without_refit_an_answer_is_only_stood_upright_and_centred(fitter, box_chair) -> None:
    """An alternative skips the refit's ICP: its pose is the levelled, centred one."""
    centre = fitter.library["chair"].centre
    keypoints = _observe((box_chair.points - centre) * 1.15 + centre)
    tilted = make_pose(axis_angle(np.array([1.0, 0, 0]), np.radians(4.0)), np.zeros(3)) @ POSE
    hypothesis = _hypothesis(tilted, keypoints)
    solid = supported(keypoints, 0.06)
    placed = fitter.fit(hypothesis, keypoints, TURN, solid=solid, refit=False)
    expected = fitter.centre_on_extent(fitter.stand_upright(hypothesis, TURN), solid)
    assert np.array_equal(placed.transform, expected.transform)
    refitted = fitter.fit(hypothesis, keypoints, TURN, solid=solid)
    assert not np.array_equal(refitted.transform, expected.transform)  # the ICP moved it


def test_the_same_size_needs_no_refit(fitter, box_chair) -> None:
    keypoints = _observe(box_chair.points)
    hypothesis = _hypothesis(POSE, keypoints)
    height = float(np.ptp(keypoints @ TURN[1]))
    assert fitter.fit_at_observed_size(hypothesis, keypoints, height) is hypothesis


def test_a_tilted_pose_is_stood_upright_about_the_model_centre(fitter, box_chair) -> None:
    tilted = make_pose(axis_angle(np.array([1.0, 0, 0]), np.radians(6.0)), np.zeros(3)) @ POSE
    upright = fitter.stand_upright(_hypothesis(tilted, _observe(box_chair.points)), TURN)
    assert np.allclose(upright.transform[:3, :3] @ np.array([0, 1.0, 0]), Z_UP)
    centre = fitter.library["chair"].centre
    assert np.allclose(transform(centre[None], upright.transform), transform(centre[None], tilted))


@pytest.mark.parametrize(("rough", "expected"), [(True, 4.0), (False, 8.0)])
def test_a_rough_up_is_met_half_way_by_the_fit(
    fitter, box_chair, rough: bool, expected: float
) -> None:
    """The fit lies on the chair exactly; the up searched is 8 degrees off it. Given (or
    snapped to a plane), the up stands the pose; rough, the pose stands half-way."""
    keypoints = _observe(box_chair.points)
    off = axis_angle(np.array([1.0, 0, 0]), np.radians(8.0)) @ Z_UP
    placed = fitter.fit(
        _hypothesis(POSE, keypoints), keypoints, leveller(off), solid=keypoints, rough_up=rough
    )
    up = placed.transform[:3, :3] @ np.array([0, 1.0, 0])
    assert np.degrees(np.arccos(up @ Z_UP)) == pytest.approx(expected, abs=0.2)


def test_a_fit_tilted_far_from_a_rough_up_does_not_move_it() -> None:
    rough = np.array([0.0, 0.0, 1.0])
    near = axis_angle(np.array([1.0, 0, 0]), np.radians(ROUGH_TILT_DEG - 1)) @ rough
    far = axis_angle(np.array([1.0, 0, 0]), np.radians(ROUGH_TILT_DEG + 1)) @ rough
    halved = np.degrees(np.arccos(rough_up_estimate(rough, near) @ rough))
    assert halved == pytest.approx((ROUGH_TILT_DEG - 1) / 2)
    assert np.array_equal(rough_up_estimate(rough, far), rough)


def test_only_axes_the_view_spans_whole_are_centred(fitter, box_chair) -> None:
    """A chair 25% wider (model x) seen whole: the pose moves along x to share the middle. Cut
    to its front half (model z): z is kept where the fit put it."""
    centre = fitter.library["chair"].centre
    wider = (box_chair.points - centre) * np.array([1.25, 1.0, 1.0]) + centre
    front = wider[wider[:, 2] < centre[2]]
    off = make_pose(np.eye(3), POSE[:3, :3] @ np.array([0.03, 0.0, 0.03])) @ POSE
    shifted = fitter.centre_on_extent(_hypothesis(off, _observe(front)), _observe(front))
    # in model coordinates: x back to the middle, z left as it was
    moved = POSE[:3, :3].T @ (shifted.transform[:3, 3] - off[:3, 3])
    assert moved[0] == pytest.approx(-0.03, abs=0.01)
    assert moved[2] == pytest.approx(0.0, abs=1e-12)
    assert np.array_equal(shifted.transform[:3, :3], off[:3, :3])


def test_a_floor_under_the_view_gives_its_bottom(fitter, box_chair) -> None:
    """The legs' last 5 cm set aside with the floor: without the floor's level the middle of
    the observed height is 2.5 cm too high, and so is the pose; with it the pose comes back
    down to where the chair stands."""
    bottom = box_chair.points[:, 1].min()
    trimmed = box_chair.points[box_chair.points[:, 1] > bottom + 0.05]
    floor_level = float(transform(np.array([[0.0, bottom, 0.0]]), POSE)[0] @ Z_UP)
    raised = make_pose(np.eye(3), Z_UP * 0.03) @ POSE  # 3 cm too high
    keypoints = _observe(trimmed)
    truth = POSE[:3, 3] @ Z_UP
    alone = fitter.centre_on_extent(_hypothesis(raised, keypoints), keypoints)
    assert alone.transform[:3, 3] @ Z_UP - truth > 0.02
    grounded = fitter.centre_on_extent(_hypothesis(raised, keypoints), keypoints, floor_level)
    assert grounded.transform[:3, 3] @ Z_UP == pytest.approx(truth, abs=0.01)
