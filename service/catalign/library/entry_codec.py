"""One library entry as the arrays of its ``.npz`` file, and back: the file's layout, with every
array's type and shape checked on the way in (a damaged file is refused, not half-read)."""

from __future__ import annotations

import numpy as np

from catalign.geometry.distance_grid import DistanceGrid
from catalign.library.entry import LibraryEntry
from catalign.library.npz import npz_bytes

_STRING_FIELDS = ("model_id", "source", "source_sha256", "units")


def entry_bytes(entry: LibraryEntry) -> bytes:
    """An entry as ``.npz`` bytes (uncompressed, byte-reproducible, each array aligned so that
    readers can map it: :mod:`~catalign.library.npz`)."""
    arrays = {
        "model_id": np.array(entry.model_id),
        "points": np.ascontiguousarray(entry.points, dtype=np.float32),
        "keypoints": np.ascontiguousarray(entry.keypoints, dtype=np.float64),
        "features": np.ascontiguousarray(entry.features, dtype=np.float32),
        "descriptor": np.ascontiguousarray(entry.descriptor, dtype=np.float32),
        "bbox_min": np.asarray(entry.bbox_min, dtype=np.float64),
        "bbox_max": np.asarray(entry.bbox_max, dtype=np.float64),
        "size": np.asarray(entry.size, dtype=np.float64),
        "grid": np.ascontiguousarray(entry.grid.values, dtype=np.uint8),
        "grid_origin": np.asarray(entry.grid.origin, dtype=np.float64),
        "grid_cell_step": np.array([entry.grid.cell, entry.grid.step], dtype=np.float64),
        "source": np.array(entry.source),
        "source_sha256": np.array(entry.source_sha256),
        "units": np.array(entry.units),
    }
    return npz_bytes(arrays)


def entry_from_arrays(arrays: dict[str, np.ndarray]) -> LibraryEntry:
    """The entry an entry file's arrays hold, each checked for its type and shape."""
    strings = {name: _string(arrays[name], name) for name in _STRING_FIELDS}
    points = _array(arrays["points"], "points", np.float32, 3)
    keypoints = _array(arrays["keypoints"], "keypoints", np.float64, 3)
    features = _array(arrays["features"], "features", np.float32, None)
    descriptor = _array(arrays["descriptor"], "descriptor", np.float32, None, ndim=1)
    if len(points) == 0 or len(keypoints) == 0 or len(features) != len(keypoints):
        raise ValueError(
            f"{len(points)} points, {len(keypoints)} key points and {len(features)} features"
        )
    boxes = {n: _array(arrays[n], n, np.float64, None, ndim=1) for n in ("bbox_min", "bbox_max")}
    size = _array(arrays["size"], "size", np.float64, None, ndim=1)
    if any(a.shape != (3,) for a in (*boxes.values(), size)):
        raise ValueError("bbox_min, bbox_max and size must hold 3 values each")
    return LibraryEntry(
        grid=_grid(arrays),
        points=points,
        keypoints=keypoints,
        features=features,
        descriptor=descriptor,
        size=size,
        **boxes,
        **strings,
    )


def _grid(arrays: dict[str, np.ndarray]) -> DistanceGrid:
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
    value = np.ascontiguousarray(value)
    value.flags.writeable = False
    return value


def _string(value: np.ndarray, name: str) -> str:
    if value.dtype.kind != "U" or value.ndim != 0:
        raise ValueError(f"{name} is not a string")
    return str(value[()])
