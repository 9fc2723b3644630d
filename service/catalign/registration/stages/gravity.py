"""Pose hypotheses when gravity is known: a turn about the up axis and a shift, from two matches.

A robot knows which way is up and library chairs stand on +Y, so once the observation is
*levelled* (its up turned onto +Y) the model -> observation pose has four degrees of freedom.
Two correspondences fix it where a free rotation needs three: with a share ``w`` of correct
matches a clean sample comes with probability ``w**2`` instead of ``w**3``. At the few percent
that cross-instance features reach, that is the difference between 200 draws and 10,000.

Hypotheses are drawn, solved and counted in batches (the counting is
:func:`~catalign.registration.stages.ransac.count_inliers`), and the best *distinct* ones are kept:
inlier counts alone confuse a chair's front with its back, so the caller checks a few of them
against the model's surface (:mod:`catalign.registration.stages.surface_checks`) before choosing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.errors import InvalidInputError
from catalign.geometry.levelling import yaw_rotations
from catalign.registration.stages.ransac import count_inliers, residual_terms

# Only the best poses by inlier count are worth suppressing among: the rest never get checked.
_SUPPRESSION_WINDOW = 256
# Two poses whose yaws differ by more than this are distinct, wherever they put the model.
DISTINCT_YAW_DEG = 15.0


@dataclass(frozen=True)
class YawPoses:
    """Hypotheses ``x_dst = R(yaw) x_src + t`` in the levelled frame, best first."""

    yaws: np.ndarray
    translations: np.ndarray
    inliers: np.ndarray

    def __len__(self) -> int:
        return len(self.yaws)

    @property
    def rotations(self) -> np.ndarray:
        return yaw_rotations(self.yaws)


def two_point_poses(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw and translation of ``H`` pairs of matches, (H,2,3) each: the turn that aligns the
    horizontal parts of the two difference vectors, and the shift that joins the midpoints."""
    d_src = src[:, 1] - src[:, 0]
    d_dst = dst[:, 1] - dst[:, 0]
    # R(yaw) maps the horizontal vector (x, z) at angle atan2(z, x) to angle atan2(z, x) - yaw.
    yaws = np.arctan2(d_src[:, 2], d_src[:, 0]) - np.arctan2(d_dst[:, 2], d_dst[:, 0])
    rotations = yaw_rotations(yaws)
    translations = dst.mean(axis=1) - np.einsum("hij,hj->hi", rotations, src.mean(axis=1))
    return yaws, translations


def plausible_pairs(
    src: np.ndarray, dst: np.ndarray, inlier_distance: float, min_separation: float
) -> np.ndarray:
    """Pairs worth solving: far enough apart horizontally that noise does not decide the yaw,
    and with horizontal lengths and height differences that a rigid turn about +Y preserves."""
    d_src = src[:, 1] - src[:, 0]
    d_dst = dst[:, 1] - dst[:, 0]
    flat_src = np.hypot(d_src[:, 0], d_src[:, 2])
    flat_dst = np.hypot(d_dst[:, 0], d_dst[:, 2])
    return (
        (np.minimum(flat_src, flat_dst) >= min_separation)
        & (np.abs(flat_src - flat_dst) < inlier_distance)
        & (np.abs(d_src[:, 1] - d_dst[:, 1]) < inlier_distance)
    )


def yaw_ransac(
    src: np.ndarray,
    dst: np.ndarray,
    inlier_distance: float,
    *,
    seed: int,
    draws: int = 2_000,
    keep: int = 8,
    min_separation: float | None = None,
    distinct_yaw_deg: float = DISTINCT_YAW_DEG,
) -> YawPoses:
    """The ``keep`` best distinct four-degree-of-freedom poses for matches ``src[i] <-> dst[i]``
    (model and levelled observation points), by correspondence inliers within ``inlier_distance``.

    ``draws`` pairs are sampled (deterministic for ``seed``); those :func:`plausible_pairs`
    refuses are dropped before solving. Two poses are distinct when their yaws differ by more
    than ``distinct_yaw_deg`` or their translations by more than ``2 * inlier_distance``.
    ``min_separation`` defaults to ``3 * inlier_distance``. Empty when nothing was plausible.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise InvalidInputError(
            f"src and dst must be matching (N, 3) arrays, got {src.shape} and {dst.shape}"
        )
    if not inlier_distance > 0:
        raise InvalidInputError(f"inlier_distance must be positive, got {inlier_distance}")
    empty = YawPoses(np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    if len(src) < 2:
        return empty
    separation = 3.0 * inlier_distance if min_separation is None else min_separation

    rng = np.random.default_rng(seed)
    first = rng.integers(0, len(src), draws)
    second = rng.integers(0, len(src) - 1, draws)
    second += second >= first
    pairs = np.stack([first, second], axis=1)
    pairs = pairs[plausible_pairs(src[pairs], dst[pairs], inlier_distance, separation)]
    if len(pairs) == 0:
        return empty
    yaws, translations = two_point_poses(src[pairs], dst[pairs])
    # Count in centred coordinates, as the three-point RANSAC does: small numbers stay exact.
    src_mean, dst_mean = src.mean(axis=0), dst.mean(axis=0)
    rotations = yaw_rotations(yaws)
    centred_t = translations - dst_mean + rotations @ src_mean
    counts = count_inliers(
        residual_terms(src - src_mean, dst - dst_mean),
        np.ones(len(yaws)),
        rotations,
        centred_t,
        inlier_distance,
    )
    order = np.argsort(-counts, kind="stable")
    chosen = distinct_poses(
        yaws[order], translations[order], keep, distinct_yaw_deg, inlier_distance
    )
    return YawPoses(yaws[order][chosen], translations[order][chosen], counts[order][chosen])


def distinct_poses(
    yaws: np.ndarray, translations: np.ndarray, keep: int, yaw_deg: float, inlier_distance: float
) -> list[int]:
    """Greedy suppression: indices (in the given order) of up to ``keep`` distinct poses among
    the first :data:`_SUPPRESSION_WINDOW`. Each pose kept suppresses the ones close to it in one
    array operation, so the work grows with ``keep``, not with the window."""
    window = min(len(yaws), _SUPPRESSION_WINDOW)
    yaws, translations = yaws[:window], translations[:window]
    limit, reach = np.radians(yaw_deg), (2 * inlier_distance) ** 2
    chosen: list[int] = []
    open_ = np.ones(window, dtype=bool)
    while len(chosen) < keep and open_.any():
        i = int(np.argmax(open_))
        chosen.append(i)
        turn = np.abs((yaws - yaws[i] + np.pi) % (2 * np.pi) - np.pi)
        shift = ((translations - translations[i]) ** 2).sum(axis=1)
        open_ &= ~((turn <= limit) & (shift <= reach))
    return chosen
