"""Checks on a query cloud before any work is spent on it, with messages a caller can act on.

:func:`validate_cloud` turns whatever array-like a caller sent into the cloud the engine works
on, or refuses it: :class:`~catalign.errors.InvalidInputError` for a wrong shape, an empty cloud,
non-finite values, too many points, or a cloud that cannot be one chair in metres;
:class:`~catalign.errors.DegenerateInputError` for clouds that are well formed but cannot fix a
pose: too few occupied voxels, or points on a line or a plane.

The checks also bound the work any later stage can be asked to do, whatever the input:

* **far points are set aside**: points more than :data:`FAR_RADIUS_M` from the cloud's robust
  centre (its coordinate-wise median) are not part of a segmented chair (a depth sensor's stray
  returns, a point at float32's maximum) and would stretch the voxel grid over kilometres; they
  are dropped and counted. If more than :data:`MAX_FAR_SHARE` of the cloud is that far out, the
  cloud is not one chair in metres, and it is refused;
* **the grid is bounded**: a chair's partial view occupies a few hundred to about 5,500 voxels of
  2.5 cm (ray-cast views of 40 procedural chairs, ten real ScanNet chairs); a cloud that
  occupies more than :data:`MAX_RECEIVED_VOXELS` is a scene or a volume, and is refused at
  once; one that still occupies more than :data:`MAX_VOXELS` once its floor and detached
  clusters are set aside (:meth:`CheckedCloud.without`) is refused before the features are
  computed on it;
* **the query's own frame comes first**: the points kept are moved into the frame of
  :mod:`~catalign.registration.prepare.frame` before any grid is laid on them, so neither the
  down-sampling below nor the voxel counts the checks judge depend on where the sensor stood;
* **dense clouds are down-sampled**: a cloud of more than :data:`DENSE_POINTS` points reaches
  the engine as one point per cell of a quarter voxel (the centroid of its points; a depth
  camera's points are about that far apart at 2 m), so a dense scan of a chair costs about what
  a sparse one does. Sparser clouds (every view of the evaluation, up to 58,000 points) are
  left as they are: down-sampling them too measured 2 to 3 cases worse in 108 at RRE<10
  (``bench/tradeoff.py --configs default fine_cells=none``), since the features' voxel
  centroids then weigh cells instead of points.

Shape is judged on the voxel-downsampled cloud (what the features see, and independent of how
densely the sensor sampled each part) by the spreads along its principal axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from numbers import Real

import numpy as np

from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.geometry.sampling import occupied_voxels, voxel_downsample
from catalign.limits import MIN_VOXELS
from catalign.registration.prepare.frame import IDENTITY, QueryFrame, query_frame

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
# Points farther than this from the cloud's median are set aside (views of chairs: 1.3 m at
# most; real scans: 0.7 m; room for floor or a neighbour's part around the chair).
FAR_RADIUS_M = 3.0
# More than this share of the cloud that far out: not one chair in metres.
MAX_FAR_SHARE = 0.2
# Occupied voxels the features may be asked to describe: about twice the largest chair view
# measured; the largest query then takes about 2.5 s on one core.
MAX_VOXELS = 12_000
# Occupied voxels a query may arrive with: floor kept around the chair adds as much again as the
# chair (12,300 voxels in all for a close view of the evaluation's floor setting), and the floor
# is set aside before the features run; finding it costs little.
MAX_RECEIVED_VOXELS = 3 * MAX_VOXELS
# Cells per voxel edge of the grid dense clouds are down-sampled to, and what counts as dense.
FINE_CELLS = 4
DENSE_POINTS = 100_000
# Coordinates farther from the origin than this lose the precision a pose needs.
MAX_RANGE_M = 10_000.0


@dataclass(frozen=True)
class CheckedCloud:
    """The cloud the engine works on, and what the checks did to the caller's points.

    ``points`` are float64 (M, 3): the points kept (one per fine cell for a dense cloud), in
    the query's own ``frame``; ``received`` counts the caller's points, ``set_aside`` those
    dropped (far outliers, and floor or detached clusters once :meth:`without` has removed
    them), ``voxels`` the occupied voxels of the kept points.
    """

    points: np.ndarray
    received: int
    set_aside: int
    voxels: int
    frame: QueryFrame = IDENTITY

    def without(
        self, mask: np.ndarray, voxel_size: float, min_points: int, max_voxels: int = MAX_VOXELS
    ) -> CheckedCloud:
        """The cloud less the points of ``mask`` (the floor, a detached cluster), counted as set
        aside; refused like any cloud when fewer than ``min_points`` or more than
        ``max_voxels`` (what the features may describe) voxels remain."""
        kept = self.points[~mask] if mask.any() else self.points
        voxels = occupied_voxels(kept, voxel_size) if mask.any() else self.voxels
        if voxels < min_points:
            raise DegenerateInputError(
                f"after setting aside {int(mask.sum())} points of floor or of detached clusters, "
                f"the object occupies only {voxels} voxels of {voxel_size:g} m, at least "
                f"{min_points} are needed"
            )
        if voxels > max_voxels:
            raise _too_many_voxels(str(voxels), voxel_size, max_voxels)
        set_aside = self.set_aside + int(mask.sum())
        return replace(self, points=kept, set_aside=set_aside, voxels=voxels)


def validate_cloud(
    points: object,
    *,
    voxel_size: float,
    up: np.ndarray | None = None,
    min_points: int = MIN_VOXELS,
    max_points: int | None = None,
    max_voxels: int = MAX_RECEIVED_VOXELS,
    far_radius: float = FAR_RADIUS_M,
    fine_cells: int | None = FINE_CELLS,
    dense_points: int = DENSE_POINTS,
) -> CheckedCloud:
    """The query as the engine should see it, or a typed error that says what is wrong with it.

    ``min_points`` counts occupied voxels of ``voxel_size``, not raw points: a thousand points in
    one voxel are one point to the features. The default of 50 is a patch of about 0.03 m² at
    2.5 cm voxels, far less than any partial view of a chair (over 100 voxels even at 5 cm), and
    too little surface for descriptors that look five voxels around. ``up`` (the world's up in
    the caller's frame, when known) orients the query's own frame. ``max_points`` (when given)
    refuses larger clouds before any work is done on them; ``max_voxels`` and ``far_radius``
    bound the grid (module docstring); ``fine_cells`` is the down-sampling grid's cells per
    voxel edge for clouds of more than ``dense_points`` points (None: never down-sampled).
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

    kept = _without_far_points(cloud, far_radius)
    frame = query_frame(kept, up)
    kept = frame.points(kept)
    fine = kept
    if fine_cells is not None and len(kept) > dense_points:
        fine, _ = voxel_downsample(kept, voxel_size / fine_cells)
        # Fine cells nest in voxels, so a voxel holds at most fine_cells³ of them: refuse early.
        if len(fine) > fine_cells**3 * max_voxels:
            raise _too_many_voxels(f"over {max_voxels}", voxel_size, max_voxels)
    centroids, _ = voxel_downsample(fine, voxel_size)
    if len(centroids) > max_voxels:
        raise _too_many_voxels(str(len(centroids)), voxel_size, max_voxels)
    if len(centroids) < min_points:
        raise DegenerateInputError(
            f"the point cloud occupies only {len(centroids)} voxels of {voxel_size:g} m, at "
            f"least {min_points} are needed (is the object too far away or mostly hidden?)"
        )
    _check_not_flat(centroids, voxel_size)
    return CheckedCloud(
        points=fine,
        received=len(cloud),
        set_aside=len(cloud) - len(kept),
        voxels=len(centroids),
        frame=frame,
    )


def _without_far_points(cloud: np.ndarray, radius: float) -> np.ndarray:
    """``cloud`` without the points farther than ``radius`` from its median, or
    InvalidInputError when too many are, or when the cloud is too far from the origin."""
    centre = np.median(cloud, axis=0)
    if (reach := float(np.abs(centre).max())) > MAX_RANGE_M:
        raise InvalidInputError(
            f"the cloud's centre is {reach:.3g} m from the origin along an axis, farther than "
            f"{MAX_RANGE_M:g} m; send it in the sensor's frame, in metres"
        )
    with np.errstate(over="ignore"):  # a coordinate near float64's maximum: infinitely far
        near = np.linalg.norm(cloud - centre, axis=1) <= radius
    far = len(cloud) - int(near.sum())
    if far > MAX_FAR_SHARE * len(cloud):
        raise InvalidInputError(
            f"{far} of {len(cloud)} points lie more than {radius:g} m from the cloud's centre; "
            "a segmented chair in metres has few such stray points (at most "
            f"{MAX_FAR_SHARE:.0%}): crop the cloud to the object and send it in metres"
        )
    return cloud if far == 0 else cloud[near]


def _too_many_voxels(count: str, voxel_size: float, max_voxels: int) -> InvalidInputError:
    return InvalidInputError(
        f"the point cloud occupies {count} voxels of {voxel_size:g} m, more than a view of one "
        f"chair can (at most {max_voxels}); crop it to the object and send it in metres"
    )


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
