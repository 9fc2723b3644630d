"""One library entry as the arrays of its ``.npz`` file, and back: the file's layout, with every
array's type and shape checked on the way in (a damaged file is refused, not half-read).

The surface is stored in 12-bit and key points in 16-bit steps across a box, features as int8
multiples of one step and the distance grid in six bits (:mod:`~catalign.library.quantise`); an
entry made by :func:`~catalign.library.entry.describe_shape` already holds those values, so a
written entry reads back equal. The surface points are stored column by column (``surface_steps``,
3 by N), in which the compressor finds the first axis's sorted steps.

Entry files written before these narrowings (``point_steps`` rows, float32 ``keypoints``, the
grid's 255 levels) read as they were: a library need not be rewritten to be served.
"""

from __future__ import annotations

import numpy as np

from catalign.geometry.distance_grid import DistanceGrid
from catalign.library.entry import LibraryEntry
from catalign.library.npz import npz_bytes
from catalign.library.quantise import (
    POINT_STEPS,
    SURFACE_STEPS,
    feature_step,
    feature_steps,
    features_from_steps,
    grid_from_steps,
    grid_steps,
    point_steps,
    points_from_steps,
)

_STRING_FIELDS = ("model_id", "source", "source_sha256", "units")
_LARGE = ("surface_steps", "grid_steps")  # LZMA-compressed (npz.py)


def entry_bytes(entry: LibraryEntry) -> bytes:
    """An entry as ``.npz`` bytes, byte-reproducible (:mod:`~catalign.library.npz`)."""
    low, high = np.asarray(entry.bbox_min, np.float64), np.asarray(entry.bbox_max, np.float64)
    step = feature_step(entry.features)
    key_low, key_high = entry.grid.box
    arrays = {
        "model_id": np.array(entry.model_id),
        "surface_steps": np.ascontiguousarray(
            point_steps(entry.points, low, high, SURFACE_STEPS).T
        ),
        "keypoint_steps": point_steps(entry.keypoints, key_low, key_high),
        "feature_steps": feature_steps(entry.features, step),
        "feature_step": np.array(step),
        "descriptor": np.ascontiguousarray(entry.descriptor, dtype=np.float32),
        "bbox_min": low,
        "bbox_max": high,
        "size": np.asarray(entry.size, dtype=np.float64),
        "grid_steps": grid_steps(entry.grid.values),
        "grid_origin": np.asarray(entry.grid.origin, dtype=np.float64),
        "grid_cell_step": np.array([entry.grid.cell, entry.grid.step], dtype=np.float64),
        "source": np.array(entry.source),
        "source_sha256": np.array(entry.source_sha256),
        "units": np.array(entry.units),
    }
    return npz_bytes(arrays, large=_LARGE)


def entry_from_arrays(arrays: dict[str, np.ndarray]) -> LibraryEntry:
    """The entry an entry file's arrays hold, each checked for its type and shape."""
    strings = {name: _string(arrays[name], name) for name in _STRING_FIELDS}
    if "surface_steps" in arrays:
        steps = _array(arrays["surface_steps"], "surface_steps", np.uint16, None).T
        count = SURFACE_STEPS
        if steps.shape[1] != 3 or (steps.size and int(steps.max()) > count):
            raise ValueError(f"surface_steps has shape {steps.shape[::-1]} or exceeds {count}")
    else:  # written before the surface was stored by column, in 16-bit steps
        steps = _array(arrays["point_steps"], "point_steps", np.uint16, 3)
        count = POINT_STEPS
    grid = _grid(arrays)
    keypoints = _keypoints(arrays, grid)
    features = _array(arrays["feature_steps"], "feature_steps", np.int8, None)
    step = _scalar(arrays["feature_step"], "feature_step")
    descriptor = _array(arrays["descriptor"], "descriptor", np.float32, None, ndim=1)
    if len(steps) == 0 or len(keypoints) == 0 or len(features) != len(keypoints):
        raise ValueError(
            f"{len(steps)} points, {len(keypoints)} key points and {len(features)} features"
        )
    boxes = {n: _array(arrays[n], n, np.float64, None, ndim=1) for n in ("bbox_min", "bbox_max")}
    size = _array(arrays["size"], "size", np.float64, None, ndim=1)
    if any(a.shape != (3,) for a in (*boxes.values(), size)):
        raise ValueError("bbox_min, bbox_max and size must hold 3 values each")
    return LibraryEntry(
        grid=grid,
        points=_read_only(points_from_steps(steps, boxes["bbox_min"], boxes["bbox_max"], count)),
        keypoints=_read_only(keypoints),
        features=_read_only(features_from_steps(features, step)),
        descriptor=descriptor,
        size=size,
        **boxes,
        **strings,
    )


def _keypoints(arrays: dict[str, np.ndarray], grid: DistanceGrid) -> np.ndarray:
    """The key points (float64), from their steps across the grid's box or, in a file written
    before they were narrowed, from float32."""
    if "keypoint_steps" not in arrays:
        return _array(arrays["keypoints"], "keypoints", np.float32, 3).astype(np.float64)
    steps = _array(arrays["keypoint_steps"], "keypoint_steps", np.uint16, 3)
    return points_from_steps(steps, *grid.box).astype(np.float64)


def _grid(arrays: dict[str, np.ndarray]) -> DistanceGrid:
    if "grid_steps" in arrays:
        steps = _array(arrays["grid_steps"], "grid_steps", np.uint8, None, ndim=3)
        values = _read_only(grid_from_steps(steps))
    else:  # written before the grid was narrowed
        values = _array(arrays["grid"], "grid", np.uint8, None, ndim=3)
    origin = _array(arrays["grid_origin"], "grid_origin", np.float64, None, ndim=1)
    cell, step = _array(arrays["grid_cell_step"], "grid_cell_step", np.float64, None, ndim=1)
    if origin.shape != (3,) or not (cell > 0 and step > 0) or min(values.shape) < 2:
        raise ValueError("the distance grid's origin, cell or step is invalid")
    return DistanceGrid(values, origin, float(cell), float(step))


def _array(
    value: np.ndarray, name: str, dtype: type, columns: int | None, ndim: int = 2
) -> np.ndarray:
    if value.dtype != dtype or value.ndim != ndim or (columns and value.shape[1] != columns):
        raise ValueError(f"{name} has dtype {value.dtype} and shape {value.shape}")
    return _read_only(np.ascontiguousarray(value))


def _scalar(value: np.ndarray, name: str) -> float:
    """A positive, finite float64 stored as a 0-d array."""
    if value.dtype != np.float64 or value.ndim != 0 or not 0 < float(value) < np.inf:
        raise ValueError(f"{name} is {value!r}, not a positive number")
    return float(value)


def _read_only(value: np.ndarray) -> np.ndarray:
    value.flags.writeable = False
    return value


def _string(value: np.ndarray, name: str) -> str:
    if value.dtype.kind != "U" or value.ndim != 0:
        raise ValueError(f"{name} is not a string")
    return str(value[()])
