"""Closed-form rigid and similarity fits of corresponding points: Kabsch (rotation and
translation) and Umeyama (with a uniform scale), one at a time or batched over many triples,
each optionally weighted. RANSAC (:mod:`catalign.registration.stages.ransac`) solves its
hypotheses and refits its inliers with them.
"""

from __future__ import annotations

import numpy as np

from catalign.errors import InvalidInputError


def kabsch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation with ``dst ≈ R src + t`` (proper: det R = +1)."""
    _, rotation, translation = umeyama(src, dst, weights, estimate_scale=False)
    return rotation, translation


def umeyama(
    src: np.ndarray,
    dst: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    estimate_scale: bool = True,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991); ``s`` is 1 without scale."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise InvalidInputError(
            f"expected two (N, 3) arrays of the same shape, got {src.shape} and {dst.shape}"
        )
    if len(src) == 0:
        raise InvalidInputError("cannot fit a transform to zero points")
    if weights is None:
        weights = np.full(len(src), 1.0 / len(src))
    else:
        weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        if len(weights) != len(src) or np.any(weights < 0) or not weights.sum() > 0:
            raise InvalidInputError(
                "weights must be one non-negative number per point, with a positive sum"
            )
        weights = weights / weights.sum()
    scale, rotation, translation = _solve_batch(
        src[None], dst[None], weights[None], estimate_scale=estimate_scale
    )
    return float(scale[0]), rotation[0], translation[0]


def kabsch_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch for ``H`` independent problems at once: (H,k,3) pairs -> R (H,3,3), t (H,3)."""
    _, rotation, translation = umeyama_batch(src, dst, estimate_scale=False)
    return rotation, translation


def umeyama_batch(
    src: np.ndarray, dst: np.ndarray, *, estimate_scale: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Umeyama for ``H`` problems at once: (H,k,3) pairs -> s (H,), R (H,3,3), t (H,3)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 3 or src.shape[2] != 3 or src.shape != dst.shape or src.shape[1] == 0:
        raise InvalidInputError(
            f"expected two (H, k, 3) arrays of the same shape, k > 0, got {src.shape} and "
            f"{dst.shape}"
        )
    weights = np.full(src.shape[:2], 1.0 / src.shape[1])
    return _solve_batch(src, dst, weights, estimate_scale=estimate_scale)


def _solve_batch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray, *, estimate_scale: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted Umeyama on stacked problems; ``weights`` (H,k) sum to one per problem."""
    src_mean = np.einsum("hk,hki->hi", weights, src)
    dst_mean = np.einsum("hk,hki->hi", weights, dst)
    src_c = src - src_mean[:, None]
    dst_c = dst - dst_mean[:, None]
    cov = np.einsum("hk,hki,hkj->hij", weights, src_c, dst_c)  # sum w x y^T
    u, sigma, vt = np.linalg.svd(cov)
    # Reflection fix: flip the weakest axis when V U^T would be a reflection.
    d = np.where(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)) < 0, -1.0, 1.0)
    vt[:, 2] *= d[:, None]
    rotation = np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)
    if estimate_scale:
        variance = np.einsum("hk,hk->h", weights, (src_c**2).sum(axis=2))
        trace = sigma[:, 0] + sigma[:, 1] + d * sigma[:, 2]
        scale = np.divide(trace, variance, out=np.ones_like(trace), where=variance > 0)
    else:
        scale = np.ones(len(src))
    translation = dst_mean - scale[:, None] * np.einsum("hij,hj->hi", rotation, src_mean)
    return scale, rotation, translation
