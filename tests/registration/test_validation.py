from __future__ import annotations

import numpy as np
import pytest

from catalign.data.camera import random_camera
from catalign.data.shapes import procedural_shape
from catalign.data.views import random_object_pose, render_view
from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import random_rotation
from catalign.registration.prepare.validation import (
    DENSE_POINTS,
    FAR_RADIUS_M,
    FINE_CELLS,
    MAX_RECEIVED_VOXELS,
    MAX_VOXELS,
    MIN_VOXELS,
    validate_cloud,
)

VOXEL = 0.025


def box_surface(rng: np.random.Generator, n: int, extents=(0.4, 0.6, 0.3)) -> np.ndarray:
    """Points on the faces of a box: a small, clearly three-dimensional cloud."""
    points = rng.random((n, 3))
    axis = rng.integers(0, 3, size=n)
    points[np.arange(n), axis] = rng.integers(0, 2, size=n)
    return points * np.asarray(extents)


def test_accepts_lists_and_float32_and_returns_float64(rng):
    points = box_surface(rng, 3000)
    for given in (points.tolist(), points.astype(np.float32), points):
        checked = validate_cloud(given, voxel_size=VOXEL)
        assert checked.points.dtype == np.float64 and checked.points.shape == (3000, 3)
        assert checked.received == 3000 and checked.set_aside == 0
        # In the query's own frame (tests/registration/test_frame.py), every point kept.
        np.testing.assert_allclose(checked.points, checked.frame.points(points), atol=1e-6)
    checked = validate_cloud(points, voxel_size=VOXEL)
    assert checked.points is not points  # a copy the caller may keep
    assert checked.voxels == len(voxel_downsample(checked.points, VOXEL)[0])


def test_a_dense_scan_costs_what_a_sparse_one_does(rng):
    """A cloud over DENSE_POINTS reaches the engine as one centroid per fine cell."""
    dense = box_surface(rng, 3 * DENSE_POINTS)
    checked = validate_cloud(dense, voxel_size=VOXEL)
    in_frame = checked.frame.points(dense)
    np.testing.assert_allclose(checked.points, voxel_downsample(in_frame, VOXEL / FINE_CELLS)[0])
    assert len(checked.points) <= FINE_CELLS**3 * checked.voxels
    assert len(checked.points) < DENSE_POINTS / 3
    assert len(validate_cloud(dense[:DENSE_POINTS], voxel_size=VOXEL).points) == DENSE_POINTS


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((10, 2)),
        np.zeros(3),
        np.zeros((10, 3, 1)),
        [[0.0, 1.0, 2.0], [3.0, 4.0]],
        [["a", "b", "c"]],
        None,
    ],
)
def test_refuses_a_wrong_shape(points):
    with pytest.raises(InvalidInputError, match=r"\(N, 3\)") as caught:
        validate_cloud(points, voxel_size=VOXEL)
    assert not isinstance(caught.value, DegenerateInputError)


def test_refuses_an_empty_cloud():
    for empty in (np.empty((0, 3)), [], np.empty((0, 3), dtype=np.float32)):
        with pytest.raises(InvalidInputError, match="empty"):
            validate_cloud(empty, voxel_size=VOXEL)


def test_refuses_non_finite_points_and_says_how_many(rng):
    points = box_surface(rng, 1000)
    points[[3, 50]] = np.nan
    points[7, 2] = np.inf
    with pytest.raises(InvalidInputError, match="3 of 1000 points have NaN or infinite"):
        validate_cloud(points, voxel_size=VOXEL)


def test_refuses_more_than_max_points(rng):
    points = box_surface(rng, 1000)
    with pytest.raises(InvalidInputError, match="1000 points, more than the 999 allowed"):
        validate_cloud(points, voxel_size=VOXEL, max_points=999)
    assert validate_cloud(points, voxel_size=VOXEL, max_points=1000).received == 1000


def test_refuses_a_bad_voxel_size(rng):
    for voxel_size in (0.0, -1.0, float("nan"), "0.1"):
        with pytest.raises(InvalidInputError, match="voxel_size"):
            validate_cloud(box_surface(rng, 100), voxel_size=voxel_size)


def test_refuses_too_few_voxels_and_says_how_many(rng):
    blob = rng.normal(scale=0.002, size=(5000, 3))  # thousands of points, a handful of voxels
    with pytest.raises(DegenerateInputError, match=r"only \d+ voxels of 0.025 m, at least 50"):
        validate_cloud(blob, voxel_size=VOXEL)
    with pytest.raises(DegenerateInputError, match="at least 10000 are needed"):
        validate_cloud(box_surface(rng, 3000), voxel_size=VOXEL, min_points=10_000)


def test_refuses_a_noisy_flat_square(rng):
    square = np.c_[rng.uniform(-0.5, 0.5, size=(5000, 2)), rng.normal(scale=0.002, size=5000)]
    tilted = square @ random_rotation(rng).T + np.array([1.0, -2.0, 0.5])
    with pytest.raises(DegenerateInputError, match="lie on a plane"):
        validate_cloud(tilted, voxel_size=VOXEL)


@pytest.mark.parametrize("noise", [0.0, 0.002])
def test_refuses_a_line(rng, noise: float):
    # 2.5 m: in the query's own frame the line runs along a grid axis, one voxel per 2.5 cm,
    # and needs more than MIN_VOXELS of them to be judged by its shape.
    line = rng.uniform(0.0, 2.5, size=(2000, 1)) * np.array([[0.3, -0.8, 0.5]])
    line += rng.normal(scale=noise, size=line.shape)
    with pytest.raises(DegenerateInputError, match="lie on a line"):
        validate_cloud(line, voxel_size=VOXEL)


def test_accepts_a_large_plane_with_an_object_on_it(rng):
    """Thin relative to its size (2.7 % of the extent) but with relief of many voxels: a wall or
    floor with a 30 cm box in front of it can still be registered."""
    floor = np.c_[rng.uniform(-1.2, 1.2, size=(100_000, 2)), np.zeros(100_000)]
    validate_cloud(np.r_[floor, box_surface(rng, 20_000, (0.3, 0.3, 0.3))], voxel_size=VOXEL)


def test_accepts_partial_views_of_procedural_chairs():
    for seed in range(31):
        shape = procedural_shape(seed)
        rng = np.random.default_rng(seed)
        pose = random_object_pose(rng, "upright", height=shape.height / 2)
        points = render_view(shape, pose, random_camera(pose[:3, 3], rng), rng)
        checked = validate_cloud(points, voxel_size=VOXEL)
        assert checked.received == len(points) and checked.set_aside == 0


def chair_view(seed: int = 3) -> np.ndarray:
    shape = procedural_shape(seed)
    rng = np.random.default_rng(seed)
    pose = random_object_pose(rng, "upright", height=shape.height / 2)
    return render_view(shape, pose, random_camera(pose[:3, 3], rng), rng)


@pytest.mark.parametrize("far", [[30_000.0, 0.0, 0.0], [3.4e38, -3.4e38, 3.4e38], [1e308] * 3])
def test_sets_aside_a_far_point_and_counts_it(far: list[float]):
    """A depth sensor's stray return (30 km, float32's maximum) is dropped, not hashed."""
    view = chair_view()
    checked = validate_cloud(np.r_[view, [far]], voxel_size=VOXEL)
    assert checked.set_aside == 1 and checked.received == len(view) + 1
    assert np.abs(checked.points).max() < 10


def test_refuses_a_cloud_mostly_far_from_its_centre(rng):
    """Two chairs 30 m apart are not one chair: refused with the reason, not voxelised."""
    view = chair_view()
    with pytest.raises(InvalidInputError, match=f"more than {FAR_RADIUS_M:g} m from the"):
        validate_cloud(np.r_[view, view + np.array([30.0, 0.0, 0.0])], voxel_size=VOXEL)


def test_refuses_a_cloud_in_millimetres():
    with pytest.raises(InvalidInputError, match="in metres"):
        validate_cloud(chair_view() * 1000.0, voxel_size=VOXEL)


def test_refuses_a_cloud_far_from_the_origin():
    with pytest.raises(InvalidInputError, match="from the origin"):
        validate_cloud(chair_view() + 1e9, voxel_size=VOXEL)


@pytest.mark.parametrize("count", [60_000, 500_000])
def test_refuses_a_volume_of_random_points_quickly(rng, count: int):
    """Random points filling a 2 m cube (the denial of service: minutes and 10 GB before) are
    more voxels than any chair view, and refused before any feature is computed."""
    cube = rng.uniform(0.0, 2.0, size=(count, 3))
    with pytest.raises(InvalidInputError, match=f"at most {MAX_RECEIVED_VOXELS}"):
        validate_cloud(cube, voxel_size=VOXEL)


def test_what_is_left_to_describe_is_bounded_after_cleanup(rng):
    """A cloud may arrive with floor around the chair (up to MAX_RECEIVED_VOXELS), but what
    is left once the floor is set aside must fit the features' budget (MAX_VOXELS)."""
    slab = rng.uniform(0.0, 2.0, size=(25_000, 3)) * np.array([1.0, 1.0, 0.5])
    cloud = validate_cloud(slab, voxel_size=VOXEL)
    assert MAX_VOXELS < cloud.voxels <= MAX_RECEIVED_VOXELS
    with pytest.raises(InvalidInputError, match=f"at most {MAX_VOXELS}"):
        cloud.without(np.zeros(len(cloud.points), dtype=bool), VOXEL, MIN_VOXELS)
    low = cloud.points[:, 2] < cloud.points[:, 2].min() + 0.1
    kept = cloud.without(~low, VOXEL, MIN_VOXELS)
    assert kept.set_aside == cloud.set_aside + int((~low).sum())
    assert kept.voxels <= MAX_VOXELS
