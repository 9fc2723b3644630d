"""Rigid transforms as 4x4 homogeneous matrices, and the pose errors the paper reports.

Convention (the service's, docs/architecture.md): a pose ``T`` maps model coordinates to
observation coordinates, ``x_obs = R @ x_model + t``; matrices are row-major numpy float64 arrays.
"""

from __future__ import annotations

import numpy as np


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build a 4x4 pose from a 3x3 rotation and a 3-vector."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def invert(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (or similarity-free) pose, without a general matrix inverse."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    return make_pose(rotation.T, -rotation.T @ translation)


def scale_of(pose: np.ndarray) -> float:
    """The scale of a similarity pose (``x_obs = s R x_model + t``): 1 for a rigid one."""
    return float(np.cbrt(np.linalg.det(pose[:3, :3])))


def split_scale(pose: np.ndarray) -> tuple[np.ndarray, float]:
    """A similarity pose as its rigid part and its scale."""
    scale = scale_of(pose)
    rigid = pose.copy()
    rigid[:3, :3] /= scale
    return rigid, scale


def compose(*poses: np.ndarray) -> np.ndarray:
    """``compose(A, B, C) = A @ B @ C``: apply C first."""
    out = np.eye(4)
    for pose in poses:
        out = out @ pose
    return out


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Apply ``pose`` to (N,3) points."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3) (unit quaternion from a 4-D Gaussian)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit direction ``a`` onto unit direction ``b``."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    cross = np.cross(a, b)
    sin, cos = np.linalg.norm(cross), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        helper = np.eye(3)[np.argmin(np.abs(a))]
        return axis_angle(np.cross(a, helper), np.pi)
    return axis_angle(cross, np.arctan2(sin, cos))


def rotation_error_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
    """Relative rotation error (RRE): the angle of ``r_est^T r_gt`` in degrees."""
    cos = (np.trace(r_est.T @ r_gt) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def translation_error(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Relative translation error (RTE): Euclidean distance, in the points' units."""
    return float(np.linalg.norm(np.asarray(t_est) - np.asarray(t_gt)))
