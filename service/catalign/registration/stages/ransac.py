"""Vectorised RANSAC for a rigid (or similarity) transform from putative correspondences.

Row ``i`` of ``src`` (model points) is matched to row ``i`` of ``dst`` (observed points); the
result maps ``src`` onto ``dst`` (``x_dst = s R x_src + t``), the model -> observation pose of
:mod:`catalign.geometry.se3`. Hypotheses are drawn, solved and scored hundreds at a time in numpy
(batched Kabsch / Umeyama on stacked 3x3 SVDs, one matrix product to score them all), so the
per-hypothesis Python overhead of a loop disappears. Cheap pre-checks prune a batch before it is
scored: degenerate triplets, edge lengths that disagree (Open3D's
``CorrespondenceCheckerBasedOnEdgeLength``), samples that their own transform does not fit, and,
given the world's up direction, rotations that would tip the chair over (the gravity prior a
robot has). The loop stops on the standard adaptive bound and the winner is refitted by least
squares on its inliers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.frames import MODEL_UP
from catalign.geometry.rigid_fit import umeyama, umeyama_batch

UpCheck = Callable[[np.ndarray], np.ndarray]
# Score at most this many (correspondence, hypothesis) residuals at once: 32 MiB of float64.
_SCORE_CHUNK = 1 << 22
# Batches double from this size up to ``batch``: easy problems stop after a few dozen draws.
_FIRST_BATCH = 64
# With scale: the sizes a query may have against its model. Outside them a hypothesis is the
# degenerate fit that shrinks the model onto a few query points (every one of them an inlier).
SCALE_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class RansacResult:
    """The best transform found, ``x_dst = s R x_src + t`` as a 4x4 matrix.

    ``inliers`` flags the correspondences within the inlier distance under ``transform``.
    ``iterations_run`` counts drawn hypotheses, pruned ones included. When no hypothesis reached
    ``min_inliers`` (for instance every one was refused by the up prior) ``transform`` is the
    identity, ``num_inliers`` is 0 and :attr:`found` is false.
    """

    transform: np.ndarray
    inliers: np.ndarray
    num_inliers: int
    iterations_run: int

    @property
    def found(self) -> bool:
        return self.num_inliers > 0

    @property
    def scale(self) -> float:
        return float(np.cbrt(np.linalg.det(self.transform[:3, :3])))

    @property
    def rotation(self) -> np.ndarray:
        return self.transform[:3, :3] / self.scale

    @property
    def translation(self) -> np.ndarray:
        return self.transform[:3, 3]


def ransac(
    src: np.ndarray,
    dst: np.ndarray,
    inlier_distance: float,
    *,
    seed: int,
    iterations: int = 100_000,
    batch: int = 512,
    up: np.ndarray | None = None,
    up_axis: tuple[float, float, float] | np.ndarray = MODEL_UP,
    up_tolerance_deg: float = 30.0,
    estimate_scale: bool = False,
    scale_range: tuple[float, float] = SCALE_RANGE,
    min_inliers: int = 3,
    confidence: float = 0.999,
    edge_ratio: float = 0.9,
    refine_rounds: int = 2,
) -> RansacResult:
    """Robustly fit ``x_dst = s R x_src + t`` to correspondences ``src[i] <-> dst[i]``.

    ``up``: the world up direction in ``dst``'s frame; hypotheses whose rotation takes
    ``up_axis`` (the model's up) further than ``up_tolerance_deg`` from it are refused before
    scoring. The tolerance is loose (30 degrees by default) because a hypothesis from three noisy
    points can be tilted by several degrees even when all three are inliers; the refit fixes that.
    ``edge_ratio``: sampled triplets whose matching edge lengths differ by more than this factor
    (their ratios, with ``estimate_scale``) are refused, as Open3D's edge-length checker does;
    0 disables it. ``scale_range``: with ``estimate_scale``, the scales a hypothesis may have.
    ``refine_rounds``: least-squares refits on the inliers, each re-selecting
    them. ``batch``: the most hypotheses drawn and scored at once (the first batches are
    smaller); ``iterations`` caps the draws, the adaptive bound usually stops far earlier.
    ``min_inliers``: fewer make no solution. Deterministic for a given ``seed``.
    """
    src, dst = _as_correspondences(src, dst)
    if not inlier_distance > 0:
        raise InvalidInputError(f"inlier_distance must be positive, got {inlier_distance}")
    if iterations < 1 or batch < 1:
        raise InvalidInputError("iterations and batch must be at least 1")
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be in (0, 1), got {confidence}")
    up_check = None if up is None else _up_check(up, up_axis, up_tolerance_deg)

    # Work in centred coordinates: smaller numbers, so scoring by expanded squares stays exact.
    src_mean, dst_mean = src.mean(axis=0), dst.mean(axis=0)
    x, y = src - src_mean, dst - dst_mean
    features = residual_terms(x, y)
    rng = np.random.default_rng(seed)
    n = len(x)
    best_count, best = max(min_inliers, 3) - 1, None
    drawn, needed, next_size = 0, iterations, min(batch, _FIRST_BATCH)
    while drawn < min(iterations, needed):
        size, next_size = min(next_size, iterations - drawn), min(2 * next_size, batch)
        drawn += size
        idx = _sample_triplets(rng, n, size)
        keep = _plausible_triplets(x[idx], y[idx], inlier_distance, edge_ratio, estimate_scale)
        if not keep.any():
            continue
        idx = idx[keep]
        scale, rotation, translation = umeyama_batch(x[idx], y[idx], estimate_scale=estimate_scale)
        # The three samples must fit their own transform (Open3D's distance checker).
        fitted = scale[:, None, None] * (x[idx] @ rotation.transpose(0, 2, 1))
        residual = np.linalg.norm(fitted + translation[:, None] - y[idx], axis=2)
        keep = residual.max(axis=1) < inlier_distance
        if up_check is not None:
            keep &= up_check(rotation)
        if estimate_scale:
            keep &= (scale >= scale_range[0]) & (scale <= scale_range[1])
        if not keep.any():
            continue
        scale, rotation, translation = scale[keep], rotation[keep], translation[keep]
        counts = count_inliers(features, scale, rotation, translation, inlier_distance)
        top = int(np.argmax(counts))
        if counts[top] > best_count:
            best_count = int(counts[top])
            best = (float(scale[top]), rotation[top], translation[top])
            needed = iterations_needed(best_count / n, confidence)

    if best is None:
        return RansacResult(np.eye(4), np.zeros(n, dtype=bool), 0, drawn)
    scale, rotation, translation = _refine(
        x,
        y,
        best,
        inlier_distance,
        scale_range if estimate_scale else None,
        refine_rounds,
        up_check,
    )
    inliers = _residuals(x, y, scale, rotation, translation) < inlier_distance
    # Back from centred coordinates: x_dst - m_dst = s R (x_src - m_src) + t.
    transform = np.eye(4)
    transform[:3, :3] = scale * rotation
    transform[:3, 3] = translation + dst_mean - scale * rotation @ src_mean
    return RansacResult(transform, inliers, int(inliers.sum()), drawn)


def _as_correspondences(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise InvalidInputError(
            "src and dst must be (N, 3) arrays with one row per correspondence, got shapes "
            f"{src.shape} and {dst.shape}"
        )
    if len(src) < 3:
        raise DegenerateInputError(
            f"RANSAC needs at least 3 correspondences to fix a pose, got {len(src)}"
        )
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise InvalidInputError("the correspondences hold NaN or infinite coordinates")
    return src, dst


def _up_check(up: np.ndarray, up_axis: np.ndarray, tolerance_deg: float) -> UpCheck:
    """A function telling which (H,3,3) rotations take ``up_axis`` to within the tolerance."""
    up = np.asarray(up, dtype=np.float64).reshape(-1)
    axis = np.asarray(up_axis, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or axis.shape != (3,):
        raise InvalidInputError("up and up_axis must be 3-vectors")
    if not (np.linalg.norm(up) > 0 and np.linalg.norm(axis) > 0):
        raise InvalidInputError("up and up_axis must be non-zero directions")
    up, axis = up / np.linalg.norm(up), axis / np.linalg.norm(axis)
    min_cos = math.cos(math.radians(tolerance_deg))

    def upright_enough(rotations: np.ndarray) -> np.ndarray:
        return rotations @ axis @ up >= min_cos

    return upright_enough


def _sample_triplets(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    """(size, 3) indices, distinct within each row, uniform over ordered triplets."""
    first = rng.integers(0, n, size)
    second = rng.integers(0, n - 1, size)
    second += second >= first
    low, high = np.minimum(first, second), np.maximum(first, second)
    third = rng.integers(0, n - 2, size)
    third += third >= low
    third += third >= high
    return np.stack([first, second, third], axis=1)


def _plausible_triplets(
    src: np.ndarray, dst: np.ndarray, min_height: float, edge_ratio: float, with_scale: bool
) -> np.ndarray:
    """Triplets worth solving: a triangle on both sides, and edge lengths that agree.

    The height onto the longest edge bounds every edge from below, so one test refuses both
    close and nearly collinear points: below the inlier distance the noise decides the rotation.
    Three copies of one point (one query point matched by three model points) have no height
    and no longest edge: refused too, else they fit a model shrunk to a point.
    """
    keep = np.ones(len(src), dtype=bool)
    lengths = []
    for points in (src, dst):
        edges = points[:, [1, 2, 0]] - points  # 0->1, 1->2, 2->0
        length = np.linalg.norm(edges, axis=2)
        twice_area = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
        longest = length.max(axis=1)
        keep &= (twice_area >= min_height * longest) & (longest >= min_height)
        lengths.append(length)
    if edge_ratio > 0:
        src_len, dst_len = lengths
        with np.errstate(divide="ignore", invalid="ignore"):
            if with_scale:
                ratio = dst_len / src_len
                keep &= ratio.min(axis=1) >= edge_ratio * ratio.max(axis=1)
            else:
                keep &= (
                    np.minimum(src_len, dst_len) >= edge_ratio * np.maximum(src_len, dst_len)
                ).all(axis=1)
    return keep


def residual_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N,18) terms of ``|s R x + t - y|^2`` per correspondence (see ``count_inliers``)."""
    outer = (y[:, :, None] * x[:, None, :]).reshape(len(x), 9)  # y_i x_j at 3i+j
    ones = np.ones((len(x), 1))
    return np.hstack(
        [(x**2).sum(1, keepdims=True), ones, (y**2).sum(1, keepdims=True), y, x, outer]
    )


def count_inliers(
    features: np.ndarray,
    scale: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    inlier_distance: float,
) -> np.ndarray:
    """Inliers of each of H hypotheses, all residuals from one (N,18) x (18,H) product.

    ``|s R x + t - y|^2 = s^2|x|^2 + |t|^2 + |y|^2 - 2 t.y + 2 s x.(R^T t) - 2 s vec(R).vec(y x^T)``
    """
    h = len(scale)
    coeffs = np.empty((h, 18))
    coeffs[:, 0] = scale**2
    coeffs[:, 1] = (translation**2).sum(1)
    coeffs[:, 2] = 1.0
    coeffs[:, 3:6] = -2.0 * translation
    coeffs[:, 6:9] = 2.0 * scale[:, None] * np.einsum("hji,hj->hi", rotation, translation)
    coeffs[:, 9:] = -2.0 * scale[:, None] * rotation.reshape(h, 9)
    limit = inlier_distance**2
    chunk = max(1, _SCORE_CHUNK // len(features))
    return np.concatenate(
        [(features @ coeffs[i : i + chunk].T < limit).sum(axis=0) for i in range(0, h, chunk)]
    )


def _residuals(
    x: np.ndarray, y: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray
) -> np.ndarray:
    return np.linalg.norm(scale * x @ rotation.T + translation - y, axis=1)


def iterations_needed(inlier_ratio: float, confidence: float, sample_size: int = 3) -> int:
    """Draws for ``confidence`` of at least one all-inlier sample: log(1-p) / log(1-w^k)."""
    all_inliers = inlier_ratio**sample_size
    if all_inliers >= 1.0:
        return 1
    if all_inliers <= 0.0:
        return np.iinfo(np.int64).max
    return math.ceil(math.log(1.0 - confidence) / math.log1p(-all_inliers))


def _refine(
    x: np.ndarray,
    y: np.ndarray,
    best: tuple[float, np.ndarray, np.ndarray],
    inlier_distance: float,
    scale_range: tuple[float, float] | None,
    rounds: int,
    up_check: UpCheck | None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares refits on the inliers, kept while they explain at least as many points
    (and stay upright, and within ``scale_range`` when the scale is estimated)."""
    inliers = _residuals(x, y, *best) < inlier_distance
    for _ in range(rounds):
        scale, rotation, translation = umeyama(
            x[inliers], y[inliers], estimate_scale=scale_range is not None
        )
        if up_check is not None and not up_check(rotation[None])[0]:
            break
        if scale_range is not None and not scale_range[0] <= scale <= scale_range[1]:
            break
        refit = _residuals(x, y, scale, rotation, translation) < inlier_distance
        if refit.sum() < inliers.sum():
            break
        best = (scale, rotation, translation)
        if np.array_equal(refit, inliers):
            break
        inliers = refit
    return best
