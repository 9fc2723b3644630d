"""The paper's metrics for category-level alignment.

A category-level pose is compared in the shapes' canonical frames: the estimated pose of the
chosen library model is judged by where it puts that model's canonical frame (orientation, and
origin at its bounding-box centre, as in NCC) against where the ground truth puts the observed
instance's. For the same instance this is the plain pose error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.geometry.ncc import NCCFrame
from catalign.geometry.se3 import rotation_error_deg, transform, translation_error

RRE_THRESHOLDS_DEG = (10.0, 20.0, 30.0)
RTE_THRESHOLDS_M = (0.05, 0.10)
MATCH_TAU_M = 0.05


@dataclass(frozen=True)
class PoseError:
    rre_deg: float
    rte_m: float


def canonical_pose_error(
    pose_est: np.ndarray,
    model_frame: NCCFrame,
    pose_gt: np.ndarray,
    observed_frame: NCCFrame,
) -> PoseError:
    """RRE and RTE between the estimated and true canonical frames in the observation."""
    origin_est = transform(model_frame.centre[None], pose_est)[0]
    origin_gt = transform(observed_frame.centre[None], pose_gt)[0]
    return PoseError(
        rre_deg=rotation_error_deg(pose_est[:3, :3], pose_gt[:3, :3]),
        rte_m=translation_error(origin_est, origin_gt),
    )


def match_accuracy(
    query_points: np.ndarray,
    model_points: np.ndarray,
    model_frame: NCCFrame,
    pose_gt: np.ndarray,
    observed_frame: NCCFrame,
    tau: float = MATCH_TAU_M,
) -> float:
    """Fraction of correspondences whose model point, carried into the observed instance
    through NCC and placed by the true pose, lands within ``tau`` of its query point."""
    if len(query_points) == 0:
        return 0.0
    carried = observed_frame.from_ncc(model_frame.to_ncc(model_points))
    residual = np.linalg.norm(transform(carried, pose_gt) - query_points, axis=1)
    return float((residual < tau).mean())


def success_rates(errors: list[PoseError]) -> dict[str, float]:
    """Percent of cases under each RRE and RTE threshold."""
    rre = np.array([e.rre_deg for e in errors])
    rte = np.array([e.rte_m for e in errors])
    rates = {f"RRE<{t:g}": float((rre < t).mean() * 100) for t in RRE_THRESHOLDS_DEG}
    rates |= {f"RTE<{t * 100:g}cm": float((rte < t).mean() * 100) for t in RTE_THRESHOLDS_M}
    return rates
