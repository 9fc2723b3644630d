"""Surface sampling and voxel down-sampling.

Area-weighted sampling turns a mesh into the uniform surface points that features, the EMD and
the library use; voxel down-sampling makes point density independent of the sensor.
"""

from __future__ import annotations

import numpy as np


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
) -> np.ndarray:
    """Sample ``count`` points uniformly by area on a triangle mesh."""
    triangles = vertices[faces]
    areas = 0.5 * np.linalg.norm(
        np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1
    )
    total = areas.sum()
    if total <= 0:
        raise ValueError("the mesh has zero surface area")
    chosen = rng.choice(len(faces), size=count, p=areas / total)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    tri = triangles[chosen]
    return tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])


def subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``count`` points drawn without replacement (all of them when there are fewer)."""
    if len(points) <= count:
        return points
    return points[np.sort(rng.choice(len(points), size=count, replace=False))]


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer voxel coordinates (N,3) of each point: ``floor(p / voxel_size)``."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    return np.floor(points / voxel_size).astype(np.int64)


def occupied_voxels(points: np.ndarray, voxel_size: float) -> int:
    """How many voxels of ``voxel_size`` the points occupy."""
    return len(np.unique(voxel_keys(points, voxel_size), axis=0))


def voxel_grid(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occupied voxels of a cloud: ``(keys (M,3) int64 sorted, centroids (M,3), inverse (N,))``.

    ``inverse[i]`` is the voxel of point ``i``; a centroid is the mean of its voxel's points.
    """
    keys = voxel_keys(points, voxel_size)
    low = keys.min(axis=0)
    span = keys.max(axis=0) - low + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:
        # One int64 per voxel, ordered as the rows are lexicographically: np.unique on rows
        # (axis=0) sorts structured values and measured several times slower.
        shifted = keys - low
        packed = (shifted[:, 0] * span[1] + shifted[:, 1]) * span[2] + shifted[:, 2]
        _, first, inverse, counts = np.unique(
            packed, return_index=True, return_inverse=True, return_counts=True
        )
        unique = keys[first]
    else:  # coordinates too far apart to pack
        unique, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack(
        [np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)],
        axis=1,
    )
    return unique, sums / counts[:, None], inverse


def voxel_downsample(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the centroid of the voxel's points.

    Returns ``(centroids (M,3), inverse (N,))`` where ``inverse[i]`` is the voxel of point ``i``.
    """
    _, centroids, inverse = voxel_grid(points, voxel_size)
    return centroids, inverse
