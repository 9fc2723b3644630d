from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.se3 import (
    axis_angle,
    compose,
    invert,
    make_pose,
    random_rotation,
    rotation_between,
    rotation_error_deg,
    transform,
    translation_error,
)

RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_pose(random_rotation(rng), rng.uniform(-2, 2, size=3))


def test_make_pose_layout():
    pose = make_pose(RZ90, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(pose[:3, :3], RZ90)
    np.testing.assert_array_equal(pose[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(pose[3], [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("seed", range(5))
def test_invert_is_inverse(seed):
    pose = random_pose(np.random.default_rng(seed))
    np.testing.assert_allclose(pose @ invert(pose), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert(pose) @ pose, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert(pose), np.linalg.inv(pose), atol=1e-12)


def test_compose_applies_last_pose_first():
    rotate = make_pose(RZ90, np.zeros(3))
    shift = make_pose(np.eye(3), np.array([1.0, 0.0, 0.0]))
    point = np.zeros((1, 3))
    # compose(rotate, shift): shift first, then rotate -> (1,0,0) rotated to (0,1,0)
    np.testing.assert_allclose(transform(point, compose(rotate, shift)), [[0.0, 1.0, 0.0]])
    # compose(shift, rotate): rotating the origin does nothing, then shift -> (1,0,0)
    np.testing.assert_allclose(transform(point, compose(shift, rotate)), [[1.0, 0.0, 0.0]])
    np.testing.assert_array_equal(compose(), np.eye(4))
    rng = np.random.default_rng(0)
    a, b, c = (random_pose(rng) for _ in range(3))
    np.testing.assert_allclose(compose(a, b, c), a @ b @ c)


def test_transform_matches_homogeneous_product(rng):
    pose = random_pose(rng)
    points = rng.normal(size=(50, 3))
    homogeneous = np.c_[points, np.ones(len(points))] @ pose.T
    np.testing.assert_allclose(transform(points, pose), homogeneous[:, :3], atol=1e-12)
    np.testing.assert_allclose(transform(transform(points, pose), invert(pose)), points, atol=1e-12)


@pytest.mark.parametrize(
    ("axis", "angle", "expected"),
    [
        ([0, 0, 1], np.pi / 2, RZ90),
        ([1, 0, 0], np.pi / 2, [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),
        ([0, 1, 0], np.pi / 2, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
        ([0, 0, 5], np.pi, np.diag([-1.0, -1.0, 1.0])),  # axis need not be unit
        ([1, 1, 1], 0.0, np.eye(3)),
        ([1, 1, 1], 2 * np.pi / 3, [[0, 0, 1], [1, 0, 0], [0, 1, 0]]),  # cycles x -> y -> z
    ],
)
def test_axis_angle_known_matrices(axis, angle, expected):
    np.testing.assert_allclose(axis_angle(np.array(axis), angle), expected, atol=1e-12)


def test_axis_angle_keeps_axis_fixed(rng):
    axis = rng.normal(size=3)
    rotation = axis_angle(axis, 1.234)
    np.testing.assert_allclose(rotation @ axis, axis, atol=1e-12)
    assert rotation_error_deg(rotation, np.eye(3)) == pytest.approx(np.degrees(1.234))


def test_random_rotation_is_proper_orthonormal():
    rng = np.random.default_rng(7)
    rotations = [random_rotation(rng) for _ in range(200)]
    for rotation in rotations:
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    # uniform on SO(3): the rotated z axes cover the sphere, mean close to zero
    z_axes = np.array([r[:, 2] for r in rotations])
    assert np.linalg.norm(z_axes.mean(axis=0)) < 0.2
    assert len({r.tobytes() for r in rotations}) == len(rotations)


@pytest.mark.parametrize(
    ("a", "b"),
    [
        ([1, 0, 0], [0, 1, 0]),
        ([0, 0, 2], [0, 3, 0]),  # not unit length
        ([1, 2, 3], [1, 2, 3]),  # identical
        ([1, 0, 0], [-1, 0, 0]),  # antiparallel
        ([0, 0, 1], [0, 0, -1]),  # antiparallel
        ([1, 2, 3], [-1, -2, -3]),  # antiparallel, generic
        ([0.3, -0.4, 0.5], [-0.2, 0.9, 0.1]),
    ],
)
def test_rotation_between_maps_a_onto_b(a, b):
    a, b = np.array(a, dtype=float), np.array(b, dtype=float)
    rotation = rotation_between(a, b)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    a_unit, b_unit = a / np.linalg.norm(a), b / np.linalg.norm(b)
    np.testing.assert_allclose(rotation @ a_unit, b_unit, atol=1e-12)
    # the smallest rotation: its angle is the angle between a and b
    cos = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    expected = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert rotation_error_deg(rotation, np.eye(3)) == pytest.approx(expected, abs=1e-6)


def test_rotation_between_random_directions(rng):
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        rotation = rotation_between(a, b)
        a_unit, b_unit = a / np.linalg.norm(a), b / np.linalg.norm(b)
        np.testing.assert_allclose(rotation @ a_unit, b_unit, atol=1e-10)


def test_rotation_error_known_values():
    rz30 = axis_angle(np.array([0, 0, 1.0]), np.radians(30))
    assert rotation_error_deg(rz30, np.eye(3)) == pytest.approx(30.0)
    assert rotation_error_deg(np.eye(3), rz30) == pytest.approx(30.0)
    assert rotation_error_deg(rz30, rz30) == pytest.approx(0.0, abs=1e-5)
    rx = axis_angle(np.array([1.0, 0, 0]), np.radians(100))
    assert rotation_error_deg(rx, np.eye(3)) == pytest.approx(100.0)
    assert rotation_error_deg(np.diag([-1.0, -1.0, 1.0]), np.eye(3)) == pytest.approx(180.0)
    # relative: the error of R1 against R2 is the angle of R1^T R2, independent of a common frame
    frame = random_rotation(np.random.default_rng(3))
    assert rotation_error_deg(frame @ rz30, frame) == pytest.approx(30.0)


def test_translation_error_known_values():
    assert translation_error(np.array([1.0, 2.0, 2.0]), np.zeros(3)) == pytest.approx(3.0)
    assert translation_error(np.array([0.1, 0.0, 0.0]), np.array([0.1, 0.0, 0.0])) == 0.0
    assert translation_error([0.0, 0.03, 0.04], [0.0, 0.0, 0.0]) == pytest.approx(0.05)
