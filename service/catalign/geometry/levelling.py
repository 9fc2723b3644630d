"""Levelling: turning an observation's up onto the models' (+Y), and yaws about it.

Library models stand on +Y (:data:`~catalign.frames.MODEL_UP`); once an observation is levelled
by :func:`leveller`, a pose of an upright model is a yaw about +Y and a shift.
"""

from __future__ import annotations

import numpy as np

from catalign.errors import InvalidInputError
from catalign.frames import MODEL_UP
from catalign.geometry.se3 import rotation_between


def leveller(up: np.ndarray) -> np.ndarray:
    """The rotation that turns the observation's ``up`` onto the models' up (+Y)."""
    up = np.asarray(up, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or not np.linalg.norm(up) > 0 or not np.isfinite(up).all():
        raise InvalidInputError(f"up must be a finite non-zero 3-vector, got {up.tolist()}")
    return rotation_between(up, MODEL_UP)


def yaw_rotations(yaws: np.ndarray) -> np.ndarray:
    """(H,3,3) rotations by ``yaws`` radians about +Y."""
    yaws = np.asarray(yaws, dtype=np.float64).reshape(-1)
    cos, sin = np.cos(yaws), np.sin(yaws)
    rotations = np.zeros((len(yaws), 3, 3))
    rotations[:, 0, 0] = rotations[:, 2, 2] = cos
    rotations[:, 0, 2] = sin
    rotations[:, 2, 0] = -sin
    rotations[:, 1, 1] = 1.0
    return rotations


def yaw_of(levelled: np.ndarray) -> float:
    """The yaw about +Y (radians) of the rotation about +Y nearest, in the Frobenius sense, to a
    levelled rotation (3,3): a chair's heading once its up is +Y."""
    return float(np.arctan2(levelled[0, 2] - levelled[2, 0], levelled[0, 0] + levelled[2, 2]))


def level_pose(pose: np.ndarray, turn: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """The upright pose nearest to a model -> observation ``pose``: the model's +Y along the
    observation's up (``turn`` is :func:`leveller`'s), the yaw the nearest (in the Frobenius
    sense) to the pose's, and the model point ``pivot`` left where the pose put it.

    ICP onto another instance tilts the model to hug a differently shaped chair; when gravity is
    known that tilt is fitting error, not pose."""
    rotation = turn.T @ yaw_rotations(yaw_of(turn @ pose[:3, :3]))[0]
    upright = np.eye(4)
    upright[:3, :3] = rotation
    upright[:3, 3] = pose[:3, :3] @ pivot + pose[:3, 3] - rotation @ pivot
    return upright


def even_headings(count: int) -> tuple[float, ...]:
    """``count`` headings evenly spaced over the full turn, from zero."""
    return tuple(2 * np.pi * k / count for k in range(count))


def floor_anchor(points: np.ndarray) -> np.ndarray:
    """The point a levelled view and its upright model share best: the middle of the extent
    across the floor (x and z) and the lowest point along the up (+Y)."""
    low, high = points.min(axis=0), points.max(axis=0)
    return np.array([(low[0] + high[0]) / 2, low[1], (low[2] + high[2]) / 2])
