"""How an entry's arrays are narrowed before they are stored, and widened when read.

An entry keeps what serving needs at the precision serving needs it, so that a library of 10^5
models fits on one disk and an entry is one small read when it is shortlisted
(docs/benchmarks.md, "Entry size"):

* surface points as 16-bit steps across the model's bounding box (a 2 m model: 0.03 mm steps,
  far below the fit's 5 cm inlier distance) while features and the grid are computed from
  them, and stored in 12-bit steps (0.5 mm for 2 m, below a depth sensor's noise);
* features as 8-bit multiples of one step per entry, the power of two that fits the largest
  component in 127 steps (a power of two, so that the values are exact in float32 and narrow
  again to the same steps: learned unit features get steps of 1/128);
* of the key points only the subset matching reads (:func:`stored_rows`), as 16-bit steps
  across the distance grid's box (the model's grown by the grid's truncation, which reaches
  past the half voxel by which a voxel-centred key point can leave the model's box);
* the distance grid's levels in :data:`GRID_STEPS` steps instead of 255 (1.2 mm at a 2.5 cm
  voxel, beside the grid's own interpolation error of about a millimetre on average and a cell
  at worst; five bits lost 3 views of one evaluation report, docs/evaluation.md);
* the surface points in the order :func:`stored_surface` gives (along the box's first axis),
  in which the compressor finds the neighbours' shared high bits.

:func:`~catalign.library.entry.describe_shape` applies the narrowing itself, so an entry in
memory holds exactly the values its file gives back.
"""

from __future__ import annotations

import math

import numpy as np

from catalign.geometry.distance_grid import LEVELS, DistanceGrid

POINT_STEPS = 65_535  # uint16 steps across the bounding box
SURFACE_STEPS = 4_095  # the stored surface's 12-bit steps across it
FEATURE_STEPS = 127  # the largest int8 step
GRID_STEPS = 63  # six bits of the grid's 0..LEVELS
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


def point_steps(
    points: np.ndarray, low: np.ndarray, high: np.ndarray, count: int = POINT_STEPS
) -> np.ndarray:
    """``points`` (N,3) as uint16 steps from ``low`` to ``high``, ``count`` steps across."""
    span = _span(low, high)
    scaled = np.rint((np.asarray(points, np.float64) - low) / span * count)
    return np.clip(scaled, 0, count).astype(np.uint16)


def points_from_steps(
    steps: np.ndarray, low: np.ndarray, high: np.ndarray, count: int = POINT_STEPS
) -> np.ndarray:
    """The float32 points (N,3) that uint16 ``steps`` from ``low`` to ``high`` stand for."""
    return (low + steps.astype(np.float64) * (_span(low, high) / count)).astype(np.float32)


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


def narrowed_keypoints(keypoints: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``keypoints`` (float64) as their file gives them back, stored across ``low..high``."""
    return narrowed_points(keypoints, low, high).astype(np.float64)


def grid_steps(levels: np.ndarray) -> np.ndarray:
    """A distance grid's uint8 levels (0..``LEVELS``) in :data:`GRID_STEPS` steps."""
    scaled = np.rint(np.asarray(levels, np.float64) * (GRID_STEPS / LEVELS))
    return scaled.astype(np.uint8)


def grid_from_steps(steps: np.ndarray) -> np.ndarray:
    """The uint8 levels :func:`grid_steps` stand for: ``GRID_STEPS`` is ``LEVELS`` again
    ("far"), and the levels narrow back to the same steps."""
    if steps.size and int(steps.max()) > GRID_STEPS:
        raise ValueError(f"grid steps reach {int(steps.max())}, beyond {GRID_STEPS}")
    return _GRID_LEVELS[steps]


def narrowed_grid(grid: DistanceGrid) -> DistanceGrid:
    """A distance grid as its file gives it back."""
    return DistanceGrid(grid_from_steps(grid_steps(grid.values)), grid.origin, grid.cell, grid.step)


def stored_surface(points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The surface ``points`` (N,3) as their file gives them back: in :data:`SURFACE_STEPS`
    steps across the box ``low..high``, sorted along its first axis, then the others (the
    surface is an unordered sample; in this order it compresses by a sixth)."""
    narrowed = narrowed_points(points, low, high, SURFACE_STEPS)
    return narrowed[np.lexsort((narrowed[:, 2], narrowed[:, 1], narrowed[:, 0]))]


def narrowed_points(
    points: np.ndarray, low: np.ndarray, high: np.ndarray, count: int = POINT_STEPS
) -> np.ndarray:
    """``points`` as their file gives them back, stored in ``count`` steps across the box."""
    return points_from_steps(point_steps(points, low, high, count), low, high, count)


def narrowed_features(features: np.ndarray) -> np.ndarray:
    """``features`` as their file gives them back."""
    step = feature_step(features)
    return features_from_steps(feature_steps(features, step), step)


def _span(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The box's extent per axis; a flat axis spans one step's worth, not zero."""
    return np.maximum(np.asarray(high, np.float64) - low, 1e-9)


_GRID_LEVELS = np.rint(np.arange(GRID_STEPS + 1) * (LEVELS / GRID_STEPS)).astype(np.uint8)
