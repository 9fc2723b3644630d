from __future__ import annotations

import numpy as np
import pytest
import trimesh

from catalign.geometry.sampling import (
    sample_surface,
    subsample,
    voxel_downsample,
    voxel_grid,
    voxel_keys,
)


def test_samples_lie_on_the_mesh(rng):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    points = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), 3000, rng)
    assert points.shape == (3000, 3)
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert distance.max() < 1e-9


def test_area_weighting_on_two_triangles(rng):
    # two triangles on the plane z=0, areas 0.5 and 1.5 (ratio 1:3), disjoint in x
    vertices = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 0, 0], [2, 1, 0]], dtype=np.float64
    )
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    count = 40_000
    points = sample_surface(vertices, faces, count, rng)
    np.testing.assert_allclose(points[:, 2], 0.0)
    in_small = points[:, 0] <= 1.0
    # points are inside their triangles
    small, large = points[in_small], points[~in_small]
    assert (small[:, 0] + small[:, 1] <= 1.0 + 1e-12).all()
    assert ((large[:, 0] - 2.0) / 3.0 + large[:, 1] <= 1.0 + 1e-12).all()
    assert (points[:, :2] >= -1e-12).all()
    # the split is 1:3: expect 25% in the small triangle, binomial sd about 0.2%
    assert in_small.mean() == pytest.approx(0.25, abs=0.01)


def test_samples_are_uniform_within_a_triangle(rng):
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    points = sample_surface(vertices, np.array([[0, 1, 2]]), 20_000, rng)
    # centroid of a uniform triangle is the vertex mean; the half x<0.5 holds 3/4 of the area
    np.testing.assert_allclose(points.mean(axis=0), [1 / 3, 1 / 3, 0], atol=0.01)
    assert (points[:, 0] < 0.5).mean() == pytest.approx(0.75, abs=0.015)


def test_sample_surface_rejects_zero_area(rng):
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="zero surface area"):
        sample_surface(vertices, np.array([[0, 1, 2]]), 10, rng)


def test_voxel_downsample_known_case():
    points = np.array(
        [[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.5, 0.5], [1.7, 0.1, 0.9], [-0.5, 0.0, 0.0]]
    )
    centroids, inverse = voxel_downsample(points, 1.0)
    assert centroids.shape == (3, 3)
    assert inverse.shape == (5,)
    assert inverse[0] == inverse[1]
    assert inverse[2] == inverse[3]
    assert len({inverse[0], inverse[2], inverse[4]}) == 3
    np.testing.assert_allclose(centroids[inverse[0]], [0.2, 0.2, 0.2])
    np.testing.assert_allclose(centroids[inverse[2]], [1.6, 0.3, 0.7])
    np.testing.assert_allclose(centroids[inverse[4]], [-0.5, 0.0, 0.0])


def test_voxel_downsample_random_cloud(rng):
    points = rng.uniform(-1, 1, size=(5000, 3))
    voxel = 0.2
    centroids, inverse = voxel_downsample(points, voxel)
    keys = voxel_keys(points, voxel)
    occupied = {tuple(k) for k in keys}
    # one point per occupied voxel
    assert len(centroids) == len(occupied)
    assert inverse.min() == 0 and inverse.max() == len(centroids) - 1
    assert len(np.unique(inverse)) == len(centroids)
    # the inverse map is consistent: points of one voxel share a key, and each centroid is the
    # mean of its points and lies in that voxel
    for m in rng.choice(len(centroids), size=50, replace=False):
        members = inverse == m
        assert len({tuple(k) for k in keys[members]}) == 1
        np.testing.assert_allclose(centroids[m], points[members].mean(axis=0))
        np.testing.assert_array_equal(
            voxel_keys(centroids[m][None], voxel)[0], keys[np.flatnonzero(members)[0]]
        )
    # points with the same key map to the same voxel
    first = {}
    for key, voxel_index in zip(map(tuple, keys), inverse, strict=True):
        assert first.setdefault(key, voxel_index) == voxel_index


def test_voxel_keys_floor_negative_coordinates():
    keys = voxel_keys(np.array([[-0.01, 0.0, 0.99], [-1.0, 1.0, 2.5]]), 1.0)
    np.testing.assert_array_equal(keys, [[-1, 0, 0], [-1, 1, 2]])
    assert keys.dtype == np.int64


@pytest.mark.parametrize("size", [0.0, -0.1])
def test_voxel_size_must_be_positive(size):
    with pytest.raises(ValueError, match="positive"):
        voxel_downsample(np.zeros((3, 3)), size)


def test_subsample(rng):
    points = rng.normal(size=(1000, 3))
    picked = subsample(points, 100, rng)
    assert picked.shape == (100, 3)
    # without replacement, drawn from the input, in input order
    rows = [np.flatnonzero((points == p).all(axis=1))[0] for p in picked]
    assert len(set(rows)) == 100
    assert rows == sorted(rows)
    # fewer points than asked: all of them
    np.testing.assert_array_equal(subsample(points[:10], 100, rng), points[:10])
    np.testing.assert_array_equal(subsample(points, 1000, rng), points)


def test_subsample_is_seeded():
    points = np.arange(3000, dtype=float).reshape(1000, 3)
    a = subsample(points, 50, np.random.default_rng(5))
    b = subsample(points, 50, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)


def test_voxel_grid_matches_row_wise_unique_near_and_far(rng):
    """Packed keys (the fast path) and rows (far-apart coordinates) give np.unique's answer."""
    for scale in (1.0, 1e17):
        points = rng.uniform(-1, 1, size=(3000, 3)) * [1.0, 2.0, 0.5]
        points[:10] *= scale
        keys, centroids, inverse = voxel_grid(points, 0.1)
        expected, expected_inverse = np.unique(voxel_keys(points, 0.1), axis=0, return_inverse=True)
        np.testing.assert_array_equal(keys, expected)
        np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
        np.testing.assert_allclose(centroids[inverse[20]], points[inverse == inverse[20]].mean(0))
