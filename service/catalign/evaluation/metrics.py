"""The paper's metrics for category-level alignment.

A category-level pose is compared in the shapes' canonical frames: the estimated pose of the
chosen library model is judged by where it puts that model's canonical frame (orientation, and
origin at its bounding-box centre, as in NCC) against where the ground truth puts the observed
instance's. For the same instance this is the plain pose error. The rotation error is to the
nearest pose equivalent under the observed instance's symmetry about its up (a rectangular
table turned half way round is as right), as CORSAIR and Scan2CAD measure it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import mannwhitneyu

from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller, yaw_of
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.se3 import transform, translation_error
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry
from catalign.registration.results import Orientation

RRE_THRESHOLDS_DEG = (10.0, 20.0, 30.0)
RTE_THRESHOLDS_M = (0.05, 0.10)
MATCH_TAU_M = 0.05
# Proposal quality: an estimated up within this of the truth, a heading within half a bin of
# the features' 45-degree headings.
UP_TOLERANCE_DEG = 15.0
HEADING_TOLERANCE_DEG = 22.5


@dataclass(frozen=True)
class PoseError:
    rre_deg: float
    rte_m: float


def canonical_pose_error(
    pose_est: np.ndarray,
    model_frame: NCCFrame,
    pose_gt: np.ndarray,
    observed_frame: NCCFrame,
    symmetry: YawSymmetry = NO_SYMMETRY,
) -> PoseError:
    """RRE and RTE between the estimated and true canonical frames in the observation; the
    RRE to the nearest of the true poses the observed instance's ``symmetry`` makes equal."""
    origin_est = transform(model_frame.centre[None], pose_est)[0]
    origin_gt = transform(observed_frame.centre[None], pose_gt)[0]
    return PoseError(
        rre_deg=symmetry.rotation_error_deg(pose_est[:3, :3], pose_gt[:3, :3]),
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


def proposal_hits(
    orientations: tuple[Orientation, ...],
    rotation_gt: np.ndarray,
    symmetry: YawSymmetry = NO_SYMMETRY,
) -> dict[str, bool | None]:
    """Whether the true up (of the observed chair under ``rotation_gt``) is within
    :data:`UP_TOLERANCE_DEG` of the first and of any of the first three estimated ups, and the
    true heading (the nearest one the observed shape's ``symmetry`` makes equal; any heading
    for a shape that looks the same at any yaw) within :data:`HEADING_TOLERANCE_DEG` of the
    first and of either of the first two proposed headings, under the searched up nearest the
    true one (a miss when none is within the up tolerance). None where nothing was estimated
    or proposed."""
    true_up = rotation_gt @ MODEL_UP
    ups = [o for o in orientations if o.up is not None]
    angles = [np.degrees(np.arccos(np.clip(o.up @ true_up, -1.0, 1.0))) for o in ups]
    estimated = bool(ups) and not ups[0].given
    hits: dict[str, bool | None] = {
        "up@1": bool(angles[0] <= UP_TOLERANCE_DEG) if estimated else None,
        "up@3": bool(min(angles[:3]) <= UP_TOLERANCE_DEG) if estimated else None,
        "heading@1": None,
        "heading@2": None,
    }
    if not ups or not ups[0].headings_proposed:
        return hits
    nearest = int(np.argmin(angles))
    if angles[nearest] > UP_TOLERANCE_DEG:
        return hits | {"heading@1": False, "heading@2": False}
    truth = yaw_of(leveller(ups[nearest].up) @ rotation_gt)
    # Radians to the nearest equivalent heading (a turn of ``step`` maps the shape onto itself).
    step = 2 * np.pi / max(symmetry.order, 1)
    off = [abs((h - truth + step / 2) % step - step / 2) for h in ups[nearest].headings]
    if symmetry.continuous:
        off = [0.0 for _ in off]
    near = [np.degrees(o) <= HEADING_TOLERANCE_DEG for o in off]
    return hits | {"heading@1": bool(near[0]), "heading@2": bool(any(near[:2]))}


# A right answer: the evaluation's tightest thresholds, what ``confidence`` is the probability of.
RIGHT_RRE_DEG = 10.0
RIGHT_RTE_M = 0.05
# An answer turned further than this from the truth is a turn (a quarter or half turn of a
# nearly symmetric chair), which the alternatives may hold the right pose for.
TURNED_DEG = 45.0
GATE = 0.8


def is_right(error: PoseError) -> bool:
    """Within 10 degrees and 5 cm: what ``confidence`` is the probability of."""
    return error.rre_deg < RIGHT_RRE_DEG and error.rte_m < RIGHT_RTE_M


def reliability_bins(
    probabilities: np.ndarray, right: np.ndarray, bins: int = 10
) -> list[tuple[float, float, int]]:
    """``(mean confidence, share right, count)`` of each non-empty equal-width confidence
    bin: the points of a reliability diagram."""
    p, y = np.asarray(probabilities, dtype=float), np.asarray(right, dtype=float)
    which = np.minimum((p * bins).astype(int), bins - 1)
    return [
        (float(p[which == b].mean()), float(y[which == b].mean()), int((which == b).sum()))
        for b in range(bins)
        if np.any(which == b)
    ]


def expected_calibration_error(
    probabilities: np.ndarray, right: np.ndarray, bins: int = 10
) -> float:
    """The mean gap between confidence and accuracy over equal-width confidence bins,
    weighted by the bins' shares of the answers."""
    points = reliability_bins(probabilities, right, bins)
    total = sum(count for _, _, count in points)
    return float(sum(abs(c - a) * count for c, a, count in points) / total)


def auroc(probabilities: np.ndarray, right: np.ndarray) -> float | None:
    """Area under the ROC curve of right against wrong answers: the chance that a right answer
    has the higher confidence (Mann-Whitney U over the two groups' sizes); None without both."""
    p, y = np.asarray(probabilities, dtype=float), np.asarray(right, dtype=bool)
    if y.all() or not y.any():
        return None
    u = mannwhitneyu(p[y], p[~y], alternative="two-sided").statistic
    return float(u / (y.sum() * (~y).sum()))


def gated(
    probabilities: np.ndarray, right: np.ndarray, threshold: float = GATE
) -> dict[str, float]:
    """Among answers with confidence at least ``threshold``: the share that is right
    (``precision``) and their share of all answers (``coverage``), in percent."""
    p, y = np.asarray(probabilities, dtype=float), np.asarray(right, dtype=bool)
    kept = p >= threshold
    return {
        "precision": float(y[kept].mean() * 100) if kept.any() else float("nan"),
        "coverage": float(kept.mean() * 100),
    }
