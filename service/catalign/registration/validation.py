"""Checks on a query cloud before any work is spent on it, with messages a caller can act on.

:func:`validate_cloud` turns whatever array-like a caller sent into a float64 (N,3) array, or
refuses it: :class:`~catalign.errors.InvalidInputError` for a wrong shape, an empty cloud,
non-finite values or too many points; :class:`~catalign.errors.DegenerateInputError` for clouds
that are well formed but cannot fix a pose: too few occupied voxels, or points on a line or a
plane. Shape is judged on the voxel-downsampled cloud (what the features see, and independent of
how densely the sensor sampled each part) by the spreads along its principal axes.
"""

from __future__ import annotations

import math
from numbers import Real

import numpy as np

from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.geometry.sampling import voxel_downsample

# A principal spread below this share of the largest one is flat relative to the cloud's size.
# Ray-cast views of procedural chairs (seat, back and legs) have ratios of 0.34 (second axis)
# and 0.18 (third axis) at the least, so 2 % and 3 % leave a wide margin.
LINE_RATIO = 0.02
PLANE_RATIO = 0.03
# ... and it must also be flat at the resolution the features see: the width of a uniform slab
# with that spread (sqrt(12) sigma) under one voxel. A large cloud with real relief of several
# voxels (a wall with a chair in front of it) is not a plane, even if the relief is thin
# relative to its extent.
SLAB_WIDTH_PER_SIGMA = math.sqrt(12.0)


def validate_cloud(
    points: object,
    *,
    voxel_size: float,
    min_points: int = 50,
    max_points: int | None = None,
) -> np.ndarray:
    """The query as a float64 (N,3) array, or a typed error that says what is wrong with it.

    ``min_points`` counts occupied voxels of ``voxel_size``, not raw points: a thousand points in
    one voxel are one point to the features. The default of 50 is a patch of about 0.03 m² at
    2.5 cm voxels, far less than any partial view of a chair (over 100 voxels even at 5 cm), and
    too little surface for descriptors that look five voxels around. ``max_points`` (when given)
    refuses larger clouds before any work is done on them.
    """
    if not (isinstance(voxel_size, Real) and math.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidInputError(f"voxel_size must be a positive number, got {voxel_size!r}")
    try:
        cloud = np.array(points, dtype=np.float64, order="C")
    except (TypeError, ValueError) as error:
        raise InvalidInputError(
            f"points must be an (N, 3) array of numbers; could not read them ({error})"
        ) from None
    if cloud.size == 0:
        raise InvalidInputError("the point cloud is empty")
    if cloud.ndim != 2 or cloud.shape[1] != 3:
        raise InvalidInputError(
            f"points must be an (N, 3) array of x, y, z rows, got shape {cloud.shape}"
        )
    if max_points is not None and len(cloud) > max_points:
        raise InvalidInputError(
            f"the point cloud has {len(cloud)} points, more than the {max_points} allowed"
        )
    bad = int((~np.isfinite(cloud).all(axis=1)).sum())
    if bad:
        raise InvalidInputError(
            f"{bad} of {len(cloud)} points have NaN or infinite coordinates; remove them first"
        )

    centroids, _ = voxel_downsample(cloud, voxel_size)
    if len(centroids) < min_points:
        raise DegenerateInputError(
            f"the point cloud occupies only {len(centroids)} voxels of {voxel_size:g} m, at "
            f"least {min_points} are needed (is the object too far away or mostly hidden?)"
        )
    _check_not_flat(centroids, voxel_size)
    return cloud


def _check_not_flat(centroids: np.ndarray, voxel_size: float) -> None:
    """Refuse points whose second (line) or third (plane) principal spread is negligible."""
    spread = np.linalg.svd(centroids - centroids.mean(axis=0), compute_uv=False)
    spread /= math.sqrt(len(centroids))  # standard deviations along the principal axes
    for axis, ratio, shape in ((1, LINE_RATIO, "line"), (2, PLANE_RATIO, "plane")):
        width = SLAB_WIDTH_PER_SIGMA * spread[axis]
        if spread[axis] < ratio * spread[0] and width < voxel_size:
            extent = SLAB_WIDTH_PER_SIGMA * spread[0]
            raise DegenerateInputError(
                f"the points lie on a {shape} (about {width * 100:.1f} cm thick for "
                f"{extent:.2f} m of extent); a {shape} cannot fix a pose, the view must show "
                "more of the object"
            )
