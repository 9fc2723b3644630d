"""How an entry's arrays are narrowed before they are stored, and widened when read.

An entry keeps what serving needs at the precision serving needs it, so that a library of 10^5
models fits on one disk and an entry is one small read when it is shortlisted
(docs/benchmarks.md, "Entry size"):

* surface points as 16-bit steps across the model's bounding box (a 2 m model: 0.03 mm steps,
  far below the fit's 5 cm inlier distance);
* features as 8-bit multiples of one step per entry, the power of two that fits the largest
  component in 127 steps (a power of two, so that the values are exact in float32 and narrow
  again to the same steps: learned unit features get steps of 1/128);
* of the key points only the subset matching reads (:func:`stored_rows`).

:func:`~catalign.library.entry.describe_shape` applies the narrowing itself, so an entry in
memory holds exactly the values its file gives back.
"""

from __future__ import annotations

import math

import numpy as np

POINT_STEPS = 65_535  # uint16 steps across the bounding box
FEATURE_STEPS = 127  # the largest int8 step
# Key points an entry keeps: the most matching reads of a model (the engine's ``model_points``
# default). Fewer matched points barely move the pose (registration.stages.match).
STORED_KEYPOINTS = 1_000
_SUBSET_SEED = 0  # the same rows for a model whatever the query


def stored_rows(count: int, limit: int | None) -> np.ndarray:
    """Which of ``count`` key points a subset of at most ``limit`` (None: all) keeps: a fixed
    random subset in ascending order, the same for the same count. Taking ``limit`` rows of a
    set already cut to ``limit`` keeps all of them, so the library's cut and the matcher's
    agree."""
    rows = np.arange(count)
    if limit is None or count <= limit:
        return rows
    return np.sort(np.random.default_rng(_SUBSET_SEED).permutation(rows)[:limit])


def point_steps(points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``points`` (N,3) as uint16 steps from ``low`` to ``high``."""
    span = _span(low, high)
    scaled = np.rint((np.asarray(points, np.float64) - low) / span * POINT_STEPS)
    return np.clip(scaled, 0, POINT_STEPS).astype(np.uint16)


def points_from_steps(steps: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The float32 points (N,3) that uint16 ``steps`` from ``low`` to ``high`` stand for."""
    return (low + steps.astype(np.float64) * (_span(low, high) / POINT_STEPS)).astype(np.float32)


def feature_step(features: np.ndarray) -> float:
    """The step an entry's features are stored in: the least power of two that fits their
    largest component in :data:`FEATURE_STEPS` steps."""
    largest = float(np.max(np.abs(features), initial=0.0))
    if largest == 0.0:
        return 1.0
    return float(2.0 ** math.ceil(math.log2(largest / FEATURE_STEPS)))


def feature_steps(features: np.ndarray, step: float) -> np.ndarray:
    """``features`` as int8 multiples of ``step``."""
    scaled = np.rint(np.asarray(features, np.float64) / step)
    return np.clip(scaled, -FEATURE_STEPS, FEATURE_STEPS).astype(np.int8)


def features_from_steps(steps: np.ndarray, step: float) -> np.ndarray:
    """The float32 features int8 multiples of ``step`` stand for (exact: 7 bits times a power
    of two)."""
    return steps.astype(np.float32) * np.float32(step)


def narrowed_points(points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``points`` as their file gives them back."""
    return points_from_steps(point_steps(points, low, high), low, high)


def narrowed_features(features: np.ndarray) -> np.ndarray:
    """``features`` as their file gives them back."""
    step = feature_step(features)
    return features_from_steps(feature_steps(features, step), step)


def _span(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The box's extent per axis; a flat axis spans one step's worth, not zero."""
    return np.maximum(np.asarray(high, np.float64) - low, 1e-9)
