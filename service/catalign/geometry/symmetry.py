"""Symmetry about the up axis: the turns under which a model maps onto its own surface.

A rectangular table turned half way round, a square one a quarter turn and a round one at any
yaw look the same from every side, so poses that differ by such a turn are equally right. A
library entry's symmetry is found once, from its own surface samples, when it is described:
each candidate yaw turns the samples about the vertical axis through their horizontal centroid
and counts the share that land on the surface again. Evaluation scores the rotation error to the
nearest equivalent pose (as CORSAIR and Scan2CAD do) and the decision never offers a symmetric
turn of the chosen model as an alternative answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from catalign.geometry.levelling import yaw_of, yaw_rotations
from catalign.geometry.se3 import rotation_error_deg

# Orders tried, largest first: the first whose every turn maps the surface onto itself wins.
ORDERS = (8, 6, 5, 4, 3, 2)
# Yaws (degrees) that must all map the surface onto itself for a continuous symmetry.
CONTINUOUS_STEP_DEG = 15.0
# Share of turned samples that must land within the tolerance of the surface.
MIN_SHARE = 0.9
# The tolerance, as a share of the samples' bounding-box diagonal.
TOLERANCE_SHARE = 0.02
# Samples turned per candidate yaw (more cost time and add nothing to the share's precision).
PROBE_POINTS = 2000
# A shape narrower than this (metres, about its axis) is a pole: it maps onto itself at any yaw.
MIN_RADIUS_M = 1e-6


@dataclass(frozen=True)
class YawSymmetry:
    """The turns about the models' up (+Y) under which a model looks the same.

    ``order`` 1: none; n >= 2: every turn of 360/n degrees; 0: any yaw (continuous).
    """

    order: int = 1

    def __post_init__(self) -> None:
        if self.order < 0:
            raise ValueError(f"a symmetry order is 0 (continuous) or positive, got {self.order}")

    @property
    def continuous(self) -> bool:
        return self.order == 0

    @property
    def yaws_deg(self) -> list[float]:
        """The equivalent turns in degrees; empty for a continuous symmetry (any yaw)."""
        if self.continuous:
            return []
        return [360.0 * k / self.order for k in range(self.order)]

    def describe(self) -> str:
        if self.continuous:
            return "any yaw"
        if self.order == 1:
            return "none"
        return f"turns of {360.0 / self.order:g} degrees"

    def rotation_error_deg(self, estimated: np.ndarray, true: np.ndarray) -> float:
        """Rotation error (degrees) from ``estimated`` to the nearest pose equivalent to ``true``
        (rotations (3,3) from the model's frame): ``true`` composed with each symmetric turn."""
        estimated = np.asarray(estimated, dtype=np.float64)
        true = np.asarray(true, dtype=np.float64)
        if self.continuous:
            nearest = yaw_of(true.T @ estimated)
            turns = yaw_rotations(np.array([nearest]))
        else:
            turns = yaw_rotations(np.radians(self.yaws_deg))
        return min(rotation_error_deg(estimated, true @ turn) for turn in turns)

    def same_pose(self, first: np.ndarray, second: np.ndarray, within_deg: float) -> bool:
        """Whether two rotations of the model are one pose up to a symmetric turn."""
        return self.rotation_error_deg(first, second) < within_deg


NO_SYMMETRY = YawSymmetry(1)


def landing_share(points: np.ndarray, yaw_deg: float, *, tolerance: float, seed: int = 0) -> float:
    """Share of ``points`` that land within ``tolerance`` of the points once turned by ``yaw_deg``
    about the vertical axis through their horizontal centroid."""
    points = np.asarray(points, dtype=np.float64)
    tree, probes, axis = _prepared(points, seed)
    return _share(tree, probes, axis, yaw_deg, tolerance)


def find_yaw_symmetry(points: np.ndarray, *, seed: int = 0) -> YawSymmetry:
    """The symmetry of a surface (N,3 samples in the models' frame, +Y up) about its up axis.

    Degenerate shapes are answered, not refused: a pole or a single point maps onto itself at
    any yaw, and a flat plate gets the symmetry of its outline.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"find_yaw_symmetry needs (N,3) points, got shape {points.shape}")
    tree, probes, axis = _prepared(points, seed)
    horizontal = (points - axis)[:, [0, 2]]
    if np.linalg.norm(horizontal, axis=1).max() < MIN_RADIUS_M:
        return YawSymmetry(0)
    tolerance = TOLERANCE_SHARE * float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    shares: dict[float, float] = {}

    def maps_onto_itself(yaw_deg: float) -> bool:
        key = round(yaw_deg % 360.0, 6)
        if key not in shares:
            shares[key] = _share(tree, probes, axis, key, tolerance)
        return shares[key] >= MIN_SHARE

    # A shape that fails a half turn can still have odd orders (3, 5); try the cheap ones first.
    continuous_yaws = np.arange(CONTINUOUS_STEP_DEG, 360.0, CONTINUOUS_STEP_DEG)
    if all(maps_onto_itself(yaw) for yaw in continuous_yaws):
        return YawSymmetry(0)
    for order in ORDERS:
        if all(maps_onto_itself(360.0 * k / order) for k in range(1, order)):
            return YawSymmetry(order)
    return NO_SYMMETRY


def _prepared(points: np.ndarray, seed: int) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    count = min(len(points), PROBE_POINTS)
    probes = points[rng.choice(len(points), size=count, replace=False)]
    axis = points.mean(axis=0)
    axis[1] = 0.0
    return cKDTree(points), probes, axis


def _share(
    tree: cKDTree, probes: np.ndarray, axis: np.ndarray, yaw_deg: float, tolerance: float
) -> float:
    turn = yaw_rotations(np.radians([yaw_deg]))[0]
    turned = (probes - axis) @ turn.T + axis
    distances, _ = tree.query(turned, k=1, distance_upper_bound=tolerance)
    return float(np.isfinite(distances).mean())
