"""Symmetry about the up axis, found from surface samples, and the rotation error it implies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from catalign.geometry.levelling import yaw_rotations
from catalign.geometry.se3 import rotation_error_deg
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry, find_yaw_symmetry


def surface(mesh: trimesh.Trimesh, count: int = 6000, seed: int = 0) -> np.ndarray:
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points)


def table(top: tuple[float, float], legs: list[tuple[float, float]]) -> trimesh.Trimesh:
    """A top (x, z extents) at 0.72 m on legs at the given (x, z) places."""
    parts = [trimesh.creation.box((top[0], 0.04, top[1]))]
    parts[0].apply_translation((0.0, 0.72, 0.0))
    for x, z in legs:
        leg = trimesh.creation.box((0.05, 0.7, 0.05))
        leg.apply_translation((x, 0.35, z))
        parts.append(leg)
    return trimesh.util.concatenate(parts)


def corners(half_x: float, half_z: float) -> list[tuple[float, float]]:
    return [(sx * half_x, sz * half_z) for sx in (-1, 1) for sz in (-1, 1)]


def test_a_rectangular_table_maps_onto_itself_turned_half_way():
    points = surface(table((1.4, 0.8), corners(0.6, 0.3)))
    assert find_yaw_symmetry(points) == YawSymmetry(2)


def test_a_square_table_maps_onto_itself_turned_a_quarter():
    points = surface(table((0.9, 0.9), corners(0.4, 0.4)))
    assert find_yaw_symmetry(points) == YawSymmetry(4)


def test_a_round_pedestal_table_maps_onto_itself_at_any_yaw():
    top = trimesh.creation.cylinder(radius=0.5, height=0.04, sections=96)
    top.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    top.apply_translation((0.0, 0.72, 0.0))
    post = trimesh.creation.cylinder(radius=0.05, height=0.7, sections=48)
    post.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    post.apply_translation((0.0, 0.35, 0.0))
    assert find_yaw_symmetry(surface(trimesh.util.concatenate([top, post]))).continuous


def test_a_drawer_on_one_side_breaks_the_symmetry():
    desk = table((1.4, 0.8), corners(0.6, 0.3))
    drawer = trimesh.creation.box((0.5, 0.25, 0.7))
    drawer.apply_translation((0.4, 0.55, 0.0))
    points = surface(trimesh.util.concatenate([desk, drawer]))
    assert find_yaw_symmetry(points) == NO_SYMMETRY


def test_the_symmetry_does_not_depend_on_where_the_shape_stands():
    points = surface(table((1.4, 0.8), corners(0.6, 0.3)))
    turned = points @ yaw_rotations(np.array([0.7]))[0].T + np.array([3.0, -1.0, 2.0])
    assert find_yaw_symmetry(turned) == YawSymmetry(2)


@pytest.mark.parametrize(
    ("shape", "order"),
    [
        (np.zeros((50, 3)), 0),  # one point, repeated
        (np.column_stack([np.zeros(50), np.linspace(0, 1, 50), np.zeros(50)]), 0),  # a pole
    ],
)
def test_degenerate_shapes_are_answered_not_refused(shape: np.ndarray, order: int):
    assert find_yaw_symmetry(shape).order == order


def test_a_flat_plate_gets_the_symmetry_of_its_outline():
    disc = trimesh.creation.cylinder(radius=0.4, height=1e-4, sections=128)
    disc.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    assert find_yaw_symmetry(surface(disc)).continuous
    plate = trimesh.creation.box((0.8, 1e-4, 0.5))
    assert find_yaw_symmetry(surface(plate)) == YawSymmetry(2)


def test_bad_points_are_refused():
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        find_yaw_symmetry(np.zeros((0, 3)))


def test_the_rotation_error_is_to_the_nearest_equivalent_pose():
    rng = np.random.default_rng(0)
    true = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    half = yaw_rotations(np.radians([180.0]))[0]
    small = yaw_rotations(np.radians([4.0]))[0]
    estimated = true @ half @ small
    assert rotation_error_deg(estimated, true) == pytest.approx(176.0, abs=1e-6)
    assert YawSymmetry(2).rotation_error_deg(estimated, true) == pytest.approx(4.0, abs=1e-6)
    assert YawSymmetry(4).rotation_error_deg(estimated, true) == pytest.approx(4.0, abs=1e-6)
    assert NO_SYMMETRY.rotation_error_deg(estimated, true) == pytest.approx(176.0, abs=1e-6)
    # Any yaw is equivalent under a continuous symmetry; a tilt is not.
    assert YawSymmetry(0).rotation_error_deg(true @ half, true) == pytest.approx(0.0, abs=1e-6)
    tilt = trimesh.transformations.rotation_matrix(np.radians(7.0), (1, 0, 0))[:3, :3]
    assert YawSymmetry(0).rotation_error_deg(true @ tilt @ half, true) == pytest.approx(
        7.0, abs=1e-4
    )


def test_the_symmetry_describes_its_turns():
    assert YawSymmetry(4).yaws_deg == [0.0, 90.0, 180.0, 270.0]
    assert (YawSymmetry(2).describe(), NO_SYMMETRY.describe()) == ("turns of 180 degrees", "none")
    assert YawSymmetry(0).yaws_deg == [] and YawSymmetry(0).describe() == "any yaw"
    with pytest.raises(ValueError):
        YawSymmetry(-1)


def test_shapenet_tables_are_often_symmetric_and_chairs_are_not(
    tables_root: Path, chairs_root: Path
):
    tables = sorted((tables_root / "pointclouds").glob("*.npy"))[:30]
    orders = [find_yaw_symmetry(np.load(f)).order for f in tables]
    assert sum(order != 1 for order in orders) >= 10
    chairs = sorted((chairs_root / "pointclouds").glob("*.npy"))[:10]
    assert all(find_yaw_symmetry(np.load(f)) == NO_SYMMETRY for f in chairs)
