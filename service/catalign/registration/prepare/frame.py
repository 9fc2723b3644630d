"""The query's own frame: the engine works where the answer cannot depend on where the sensor
stood.

Voxel grids, the orientation networks and RANSAC's draws all see coordinates, so the same chair
seen from a sensor moved by a rigid motion would otherwise get another voxelisation, other
proposals and, where two library models fit almost equally, another model. The engine therefore
moves every query into a frame fixed by the cloud itself, and the answer back:

- the origin is the centroid of the points;
- with ``up``, the cloud is levelled (its up onto the models' +Y) and turned about +Y so that
  the principal axes of its footprint are +X and +Z;
- without ``up``, its principal axes are +X, +Y, +Z;

each axis pointing to the side with the longer tail, but for the least skewed one, which
makes the frame right-handed.

:func:`~catalign.registration.prepare.validation.validate_cloud` moves the points there before it
lays any grid on them, so the answer is equivariant to rigid motions of the query, up to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller, yaw_of
from catalign.geometry.se3 import axis_angle, make_pose
from catalign.registration.results import Orientation, RegistrationResult


@dataclass(frozen=True)
class QueryFrame:
    """``rotation`` (observation -> query frame) and ``centre`` (the query frame's origin in
    the observation): a point ``p`` of the observation is ``rotation @ (p - centre)`` here."""

    rotation: np.ndarray
    centre: np.ndarray

    def points(self, points: np.ndarray) -> np.ndarray:
        """Observation points in the query frame."""
        return (points - self.centre) @ self.rotation.T

    def direction(self, vector: np.ndarray | None) -> np.ndarray | None:
        """An observation direction (``up``) in the query frame."""
        return None if vector is None else self.rotation @ np.asarray(vector, dtype=np.float64)

    def result(self, result: RegistrationResult) -> RegistrationResult:
        """An answer found in the query frame, in the observation's."""
        back = make_pose(self.rotation.T, self.centre)
        matched = result.correspondences
        return replace(
            result,
            pose=back @ result.pose,
            correspondences=None
            if matched is None
            else (matched[0] @ self.rotation + self.centre, matched[1]),
            orientations=tuple(self._orientation(o) for o in result.orientations),
            orientation=self._orientation(result.orientation),
            alternatives=tuple(replace(a, pose=back @ a.pose) for a in result.alternatives),
        )

    def _orientation(self, orientation: Orientation | None) -> Orientation | None:
        """An orientation searched in the query frame, in the observation's: its up turned
        back, its headings (yaws about up after :func:`~catalign.geometry.levelling.leveller`)
        shifted by the yaw between the two frames' levellings, its floor's height measured
        from the observation's origin."""
        if orientation is None or orientation.up is None:
            return orientation
        up = self.rotation.T @ orientation.up
        shift = yaw_of(leveller(orientation.up) @ self.rotation @ leveller(up).T)
        floor = orientation.floor_level
        return replace(
            orientation,
            up=up,
            headings=tuple(h - shift for h in orientation.headings),
            proposed_headings=tuple((h - shift, m) for h, m in orientation.proposed_headings),
            floor_level=None if floor is None else floor + float(up @ self.centre),
        )


IDENTITY = QueryFrame(np.eye(3), np.zeros(3))
"""The frame of points that are already in their own frame."""


def query_frame(points: np.ndarray, up: np.ndarray | None) -> QueryFrame:
    """The frame of a query's ``points`` (N,3), with the world's ``up`` in the observation
    frame when known (module docstring)."""
    centre = points.mean(axis=0)
    centred = points - centre
    if up is None:
        return QueryFrame(_principal_axes(centred), centre)
    level = leveller(up)
    levelled = centred @ level.T
    # The footprint's principal axis, in the (x, z) plane that +Y turns: a yaw of `angle`
    # about +Y takes +X to (cos, 0, -sin), so the axis at `angle` goes onto +X by turning back.
    footprint = levelled[:, [0, 2]]
    axis = _principal_axes(footprint)[0]
    angle = np.arctan2(-axis[1], axis[0])
    return QueryFrame(axis_angle(MODEL_UP, -angle) @ level, centre)


def _principal_axes(centred: np.ndarray) -> np.ndarray:
    """The principal axes of ``centred`` points (D,D rows, largest spread first), each pointing
    to the side with the longer tail (positive third moment), the least skewed one turned back
    where that is needed for a right-handed frame.

    A chair is mirror-symmetric from side to side, so its third moment across is about zero and
    that axis's sign is noise: the handedness fixes it from the skewed axes (its height and
    depth) instead.
    """
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes = vectors.T[::-1].copy()
    tails = ((centred @ axes.T) ** 3).sum(axis=0)
    axes[tails < 0] *= -1
    if np.linalg.det(axes) < 0:
        axes[np.argmin(np.abs(tails))] *= -1
    return axes
