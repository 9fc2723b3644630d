"""Two-point pose search under gravity and the layout check that ranks its poses."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.errors import InvalidInputError
from catalign.geometry.levelling import level_pose, leveller, yaw_rotations
from catalign.geometry.se3 import axis_angle, rotation_error_deg
from catalign.registration.stages.gravity import (
    distinct_poses,
    plausible_pairs,
    two_point_poses,
    yaw_ransac,
)
from catalign.registration.stages.surface_checks import LayoutCheck, top_offset

UP = np.array([0.0, 1.0, 0.0])


def _yaw_pose(yaw: float, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return axis_angle(UP, yaw), translation


def test_yaw_rotations_turn_about_plus_y() -> None:
    for yaw in (-2.0, 0.3, 3.0):
        assert np.allclose(yaw_rotations(np.array([yaw]))[0], axis_angle(UP, yaw))


def test_two_matches_fix_yaw_and_translation_exactly() -> None:
    rng = np.random.default_rng(0)
    rotation, translation = _yaw_pose(1.2, np.array([0.3, -0.1, 2.0]))
    src = rng.uniform(-0.5, 0.5, (20, 2, 3))
    dst = src @ rotation.T + translation
    yaws, translations = two_point_poses(src, dst)
    assert np.allclose(yaw_rotations(yaws), rotation, atol=1e-9)
    assert np.allclose(translations, translation, atol=1e-9)


def test_pairs_that_a_turn_about_up_cannot_explain_are_refused() -> None:
    src = np.array([[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]] * 3)
    dst = src.copy()
    dst[1, 1, 1] = 0.2  # height difference changed: no yaw explains it
    dst[2, 1, 0] = 0.8  # horizontal length changed
    assert plausible_pairs(src, dst, 0.05, 0.15).tolist() == [True, False, False]
    # too close horizontally for the noise not to decide the yaw
    assert not plausible_pairs(src * 0.2, dst[:1] * 0.2, 0.05, 0.15)[0]


def test_yaw_ransac_finds_the_pose_among_mostly_wrong_matches() -> None:
    rng = np.random.default_rng(1)
    rotation, translation = _yaw_pose(-2.3, np.array([1.0, 0.2, -0.4]))
    model = rng.uniform(-0.4, 0.4, (600, 3))
    observed = model @ rotation.T + translation + rng.normal(0, 0.005, model.shape)
    wrong = rng.random(len(model)) < 0.92  # 8% correct matches, as cross-instance features give
    observed[wrong] = rng.permutation(observed[wrong])
    poses = yaw_ransac(model, observed, 0.05, seed=0, draws=2_000, keep=4)
    assert rotation_error_deg(poses.rotations[0], rotation) < 2.0
    assert np.linalg.norm(poses.translations[0] - translation) < 0.02
    assert poses.inliers[0] >= 0.07 * len(model)
    assert list(poses.inliers) == sorted(poses.inliers, reverse=True)
    # the kept poses are distinct from each other
    turns = np.degrees(np.abs(np.angle(np.exp(1j * (poses.yaws[1:] - poses.yaws[0])))))
    shifts = np.linalg.norm(poses.translations[1:] - poses.translations[0], axis=1)
    assert np.all((turns > 15.0) | (shifts > 0.1))


def test_yaw_ransac_is_deterministic_and_empty_without_plausible_pairs() -> None:
    rng = np.random.default_rng(2)
    src = rng.uniform(-0.5, 0.5, (100, 3))
    dst = rng.uniform(-0.5, 0.5, (100, 3))
    first = yaw_ransac(src, dst, 0.05, seed=3)
    again = yaw_ransac(src, dst, 0.05, seed=3)
    assert np.array_equal(first.yaws, again.yaws)
    assert len(yaw_ransac(src[:1], dst[:1], 0.05, seed=0)) == 0
    collapsed = np.zeros((10, 3))
    assert len(yaw_ransac(collapsed, collapsed, 0.05, seed=0)) == 0
    with pytest.raises(InvalidInputError, match="inlier_distance"):
        yaw_ransac(src, dst, 0.0, seed=0)


def test_distinct_poses_match_a_pairwise_greedy_suppression() -> None:
    rng = np.random.default_rng(5)
    yaws = rng.uniform(-np.pi, np.pi, 300)
    yaws[1::7] = yaws[::7][: len(yaws[1::7])] + 0.1  # near-copies to suppress
    translations = rng.normal(scale=0.05, size=(300, 3))
    translations[1::7] = translations[::7][: len(translations[1::7])] + 0.01
    expected: list[int] = []
    for i in range(256):  # the suppression window
        turn = np.abs(np.angle(np.exp(1j * (yaws[expected] - yaws[i]))))
        shift = np.linalg.norm(translations[expected] - translations[i], axis=1)
        if not np.any((turn <= np.radians(15.0)) & (shift <= 0.1)):
            expected.append(i)
    for keep in (1, 8, 300):
        assert distinct_poses(yaws, translations, keep, 15.0, 0.05) == expected[:keep]


def test_leveller_turns_up_onto_plus_y() -> None:
    for up in ([0, 0, 1.0], [0, -1.0, 0], [0.3, 0.4, -0.2]):
        up = np.asarray(up)
        assert np.allclose(leveller(up) @ (up / np.linalg.norm(up)), UP)
    with pytest.raises(InvalidInputError, match="up"):
        leveller(np.zeros(3))


def test_level_pose_removes_tilt_and_keeps_yaw_and_pivot() -> None:
    up = np.array([0.0, 0.0, 1.0])  # a robot's world: +Z up
    turn = leveller(up)
    pivot = np.array([0.1, 0.4, -0.2])
    upright = np.eye(4)
    upright[:3, :3] = turn.T @ axis_angle(UP, 0.7)
    upright[:3, 3] = [1.0, 2.0, 0.3]
    # an upright pose is its own nearest
    assert np.allclose(level_pose(upright, turn, pivot), upright, atol=1e-12)
    # a tilt of 6 degrees about the model's own x axis is undone, the yaw kept
    tilted = upright.copy()
    tilted[:3, :3] = upright[:3, :3] @ axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(6))
    levelled = level_pose(tilted, turn, pivot)
    assert np.allclose(levelled[:3, :3] @ UP, up, atol=1e-12)
    assert rotation_error_deg(levelled[:3, :3], upright[:3, :3]) < 1e-9

    # the pivot stays where the tilted pose put it
    def image(pose: np.ndarray) -> np.ndarray:
        return pose[:3, :3] @ pivot + pose[:3, 3]

    assert np.allclose(image(levelled), image(tilted))


def _box_chair(rng: np.random.Generator) -> np.ndarray:
    """A seat slab at half height and a backrest rising from its +Z edge (+Y up)."""
    seat = rng.uniform([-0.25, 0.43, -0.25], [0.25, 0.47, 0.25], (800, 3))
    back = rng.uniform([-0.25, 0.47, 0.21], [0.25, 0.95, 0.25], (800, 3))
    return np.concatenate([seat, back])


def test_top_offset_points_to_the_backrest() -> None:
    offset = top_offset(_box_chair(np.random.default_rng(0)), UP)
    assert offset[1] == 0.0
    assert offset[2] > 0.1 and abs(offset[0]) < 0.02


def test_layout_check_favours_the_heading_whose_top_leans_the_observed_way() -> None:
    chair = _box_chair(np.random.default_rng(1))
    model_offset = top_offset(chair, UP)
    up = np.array([0.0, 0.0, 1.0])  # observed in a +Z-up world, turned by 0.4 rad
    pose = np.eye(4)
    pose[:3, :3] = axis_angle(up, 0.4) @ leveller(up).T
    observed = chair @ pose[:3, :3].T
    check = LayoutCheck(observed, up, weight=0.1)
    turned = pose.copy()
    turned[:3, :3] = axis_angle(up, np.pi) @ pose[:3, :3]
    aside = pose.copy()
    aside[:3, :3] = axis_angle(up, np.pi / 2) @ pose[:3, :3]
    factors = check.factor(model_offset, np.stack([pose, turned, aside]))
    assert factors == pytest.approx([1.1, 0.9, 1.0], abs=1e-6)
    # a stool's top leans nowhere: no opinion
    stool = np.random.default_rng(2).uniform(-0.2, 0.2, (500, 3))
    assert LayoutCheck(stool, UP).factor(model_offset, pose[None])[0] == pytest.approx(
        1.0, abs=0.05
    )
