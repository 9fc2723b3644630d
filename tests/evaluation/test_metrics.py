from __future__ import annotations

import numpy as np
import pytest

from catalign.data.views import WORLD_UP, upright_rotation
from catalign.evaluation.metrics import (
    MATCH_TAU_M,
    PoseError,
    canonical_pose_error,
    match_accuracy,
    proposal_hits,
    success_rates,
)
from catalign.evaluation.report import COLUMNS
from catalign.geometry.levelling import leveller, yaw_of
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.se3 import axis_angle, compose, make_pose, random_rotation, transform
from catalign.geometry.symmetry import YawSymmetry
from catalign.registration.results import Orientation

Z = np.array([0.0, 0.0, 1.0])


def frame(centre, scale=1.0) -> NCCFrame:
    return NCCFrame(centre=np.asarray(centre, dtype=float), scale=scale)


@pytest.fixture
def pose_gt(rng) -> np.ndarray:
    return make_pose(random_rotation(rng), rng.uniform(-1, 1, size=3))


def test_identical_poses_have_zero_error(pose_gt):
    f = frame([0.1, 0.4, -0.2], 1.3)
    error = canonical_pose_error(pose_gt, f, pose_gt.copy(), f)
    assert error.rre_deg == pytest.approx(0.0, abs=1e-5)
    assert error.rte_m == pytest.approx(0.0, abs=1e-12)


def test_known_rotation_and_translation_at_the_origin():
    f = frame([0.0, 0.0, 0.0])
    estimate = make_pose(axis_angle(Z, np.radians(30)), np.array([0.03, 0.04, 0.0]))
    error = canonical_pose_error(estimate, f, np.eye(4), f)
    assert error.rre_deg == pytest.approx(30.0)
    assert error.rte_m == pytest.approx(0.05)


def test_translation_error_is_measured_at_the_bbox_centre():
    # a 90 degree error about z moves a centre at (1, 0, 0) to (0, 1, 0): RTE sqrt(2)
    f = frame([1.0, 0.0, 0.0])
    estimate = make_pose(axis_angle(Z, np.pi / 2), np.zeros(3))
    error = canonical_pose_error(estimate, f, np.eye(4), f)
    assert error.rre_deg == pytest.approx(90.0)
    assert error.rte_m == pytest.approx(np.sqrt(2.0))


def test_the_rotation_error_is_to_the_nearest_symmetric_pose(pose_gt):
    # A table turned half way round (about the model's up, +Y) and 3 degrees more.
    f = frame([0.0, 0.4, 0.0])
    turned = compose(
        pose_gt, make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(183)), np.zeros(3))
    )
    plain = canonical_pose_error(turned, f, pose_gt, f)
    symmetric = canonical_pose_error(turned, f, pose_gt, f, YawSymmetry(2))
    assert plain.rre_deg == pytest.approx(177.0)
    assert symmetric.rre_deg == pytest.approx(3.0)
    assert symmetric.rte_m == pytest.approx(plain.rte_m)  # the centre is on the axis
    assert canonical_pose_error(turned, f, pose_gt, f, YawSymmetry(3)).rre_deg > 50


def test_rte_is_independent_of_the_world_frame(pose_gt, rng):
    f = frame([0.2, 0.5, -0.1])
    offset = make_pose(axis_angle(Z, np.radians(20)), np.array([0.0, 0.06, 0.0]))
    estimate = compose(pose_gt, offset)  # an error expressed in the model frame
    error = canonical_pose_error(estimate, f, pose_gt, f)
    origin_in_model = transform(f.centre[None], offset)[0]
    assert error.rre_deg == pytest.approx(20.0)
    assert error.rte_m == pytest.approx(np.linalg.norm(origin_in_model - f.centre))


def test_cross_instance_uses_each_shapes_bbox_centre(pose_gt):
    model_frame = frame([0.0, 0.45, 0.02], 1.2)
    observed_frame = frame([0.01, 0.40, -0.03], 1.0)
    # the same pose for both: the canonical frames differ by the difference of the centres
    error = canonical_pose_error(pose_gt, model_frame, pose_gt, observed_frame)
    assert error.rre_deg == pytest.approx(0.0, abs=1e-5)
    assert error.rte_m == pytest.approx(np.linalg.norm(model_frame.centre - observed_frame.centre))
    # an estimate that puts the model's bbox centre on the observed one's has no RTE
    shift = make_pose(np.eye(3), observed_frame.centre - model_frame.centre)
    aligned = canonical_pose_error(compose(pose_gt, shift), model_frame, pose_gt, observed_frame)
    assert aligned.rte_m == pytest.approx(0.0, abs=1e-12)
    assert aligned.rre_deg == pytest.approx(0.0, abs=1e-5)
    # the scale of the frames plays no part in the pose error
    rescaled = frame(model_frame.centre, 7.0)
    assert canonical_pose_error(pose_gt, rescaled, pose_gt, observed_frame) == error


@pytest.fixture
def match_setup(rng, pose_gt):
    model_points = rng.uniform(-0.4, 0.4, size=(200, 3)) + np.array([0.0, 0.45, 0.0])
    model_frame = NCCFrame.fit(model_points)
    observed_frame = frame([0.05, 0.5, 0.0], model_frame.scale * 1.1)
    carried = observed_frame.from_ncc(model_frame.to_ncc(model_points))
    return model_points, model_frame, observed_frame, transform(carried, pose_gt)


def test_match_accuracy_perfect(match_setup, pose_gt):
    model_points, model_frame, observed_frame, query = match_setup
    assert match_accuracy(query, model_points, model_frame, pose_gt, observed_frame) == 1.0


def test_match_accuracy_shifted(match_setup, pose_gt):
    model_points, model_frame, observed_frame, query = match_setup
    far = query + np.array([0.0, 0.0, 2 * MATCH_TAU_M])
    assert match_accuracy(far, model_points, model_frame, pose_gt, observed_frame) == 0.0
    near = query + np.array([0.0, 0.0, 0.5 * MATCH_TAU_M])
    assert match_accuracy(near, model_points, model_frame, pose_gt, observed_frame) == 1.0
    half = query.copy()
    half[::2] += [0.1, 0.0, 0.0]
    assert match_accuracy(half, model_points, model_frame, pose_gt, observed_frame) == 0.5
    # a permutation breaks correspondences even though the point sets are the same
    mixed = query[np.roll(np.arange(len(query)), 1)]
    assert match_accuracy(mixed, model_points, model_frame, pose_gt, observed_frame) < 0.2
    # tau is a parameter
    tight = match_accuracy(near, model_points, model_frame, pose_gt, observed_frame, tau=0.01)
    assert tight == 0.0


def test_match_accuracy_without_correspondences(pose_gt):
    f = frame([0, 0, 0])
    empty = np.zeros((0, 3))
    assert match_accuracy(empty, empty, f, pose_gt, f) == 0.0


def test_success_rates_percentages():
    errors = [
        PoseError(5.0, 0.01),
        PoseError(15.0, 0.07),
        PoseError(25.0, 0.20),
        PoseError(35.0, 0.04),
    ]
    assert success_rates(errors) == {
        "RRE<10": 25.0,
        "RRE<20": 50.0,
        "RRE<30": 75.0,
        "RTE<5cm": 50.0,
        "RTE<10cm": 75.0,
    }


def test_success_rates_thresholds_are_strict_and_match_report_columns():
    rates = success_rates([PoseError(10.0, 0.05), PoseError(0.0, 0.0)])
    assert rates["RRE<10"] == 50.0 and rates["RTE<5cm"] == 50.0
    assert rates["RRE<20"] == 100.0 and rates["RTE<10cm"] == 100.0
    assert set(rates) <= set(COLUMNS)
    assert success_rates([PoseError(0.0, 0.0)]) == dict.fromkeys(rates, 100.0)


@pytest.mark.parametrize(
    ("order", "turn_deg", "hit"),
    [(1, 0, True), (1, 180, False), (2, 180, True), (2, 90, False), (4, 90, True), (0, 137, True)],
)
def test_a_heading_hits_when_the_shapes_symmetry_makes_it_equal_to_the_true_one(
    order: int, turn_deg: float, hit: bool
) -> None:
    """A table that looks the same turned half way round is found at either heading."""
    rotation = upright_rotation(0.7)
    truth = yaw_of(leveller(WORLD_UP) @ rotation)
    proposed = truth + np.radians(turn_deg)
    searched = Orientation(WORLD_UP, False, (proposed, proposed), headings_proposed=True)
    hits = proposal_hits((searched,), rotation, YawSymmetry(order))
    assert hits["heading@1"] is hit and hits["heading@2"] is hit
