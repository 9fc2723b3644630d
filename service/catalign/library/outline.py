"""Outlines: each entry's coarse distance field, small enough to keep every entry's in memory.

A global descriptor ranks a partial view against whole models only roughly: among thousands of
chairs the view's own model is rarely first, though usually among the first few hundred. What
tells the own model apart is that the view lies on its surface. So every record carries its
entry's **outline**, the surface's distance field on 5 cm cells, truncated at 10 cm and kept in
4-bit levels (about 4 KB for a chair), and the shortlist re-ranks its best few hundred by the
mean distance of the view's key points to each outline (:func:`fit_distances`).

Outlines are anchored as the retrieval encoders' positions are
(:func:`~catalign.geometry.levelling.floor_anchor`): the middle of the extent across the floor
and the lowest point. A partial view's anchor is not its model's (it sees the front, or not the
feet), so a view is tried at every shift of whole cells up to :data:`SHIFT_CELLS` across the
floor and :data:`LIFT_CELLS` along the up, and keeps its best.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from catalign.geometry.distance_grid import LEVELS, DistanceGrid
from catalign.geometry.levelling import floor_anchor

OUTLINE_CELL = 0.05  # metres: finer cells cost memory at 10^5 entries, coarser lose the fit
OUTLINE_TRUNCATION = 0.10  # distances past this say only "off the surface"
OUTLINE_LEVELS = 15  # 4 bits a cell
MAX_OUTLINE_CELLS = 200_000  # a model far larger than furniture gets coarser cells
SHIFT_CELLS = 5  # shifts across the floor, in cells each way (25 cm)
LIFT_CELLS = 1  # shifts along the up (5 cm): the feet may be hidden
FIT_POINTS = 48  # view points read per shift
_HEADER = struct.Struct("<4f3H")  # origin (3), cell, shape (3)


@dataclass(frozen=True, eq=False)
class Outline:
    """A coarse truncated distance field in the entry's anchored frame: cell ``(i, j, k)`` is at
    ``origin + cell * (i, j, k)`` and holds the distance in steps of
    ``OUTLINE_TRUNCATION / OUTLINE_LEVELS`` (``OUTLINE_LEVELS``: that far or farther)."""

    origin: np.ndarray
    cell: float
    levels: np.ndarray

    def to_bytes(self) -> bytes:
        """The record's form: a header, then two cells a byte (x slowest)."""
        flat = self.levels.astype(np.uint8).ravel()
        if len(flat) % 2:
            flat = np.append(flat, np.uint8(OUTLINE_LEVELS))
        packed = flat[0::2] | (flat[1::2] << 4)
        header = _HEADER.pack(*map(float, self.origin), self.cell, *self.levels.shape)
        return header + packed.astype(np.uint8).tobytes()

    @classmethod
    def from_bytes(cls, data: bytes) -> Outline:
        """Parse a record's outline; ValueError when it is not one."""
        if len(data) < _HEADER.size:
            raise ValueError(f"an outline of {len(data)} bytes is shorter than its header")
        *origin, cell, x, y, z = _HEADER.unpack_from(data)
        cells = x * y * z
        packed = np.frombuffer(data, dtype=np.uint8, offset=_HEADER.size)
        if not (np.isfinite(origin).all() and np.isfinite(cell) and cell > 0 and cells > 0):
            raise ValueError("an outline's header holds no grid")
        if len(packed) != (cells + 1) // 2:
            raise ValueError(f"an outline of {x}x{y}x{z} cells holds {len(packed)} bytes")
        flat = np.empty(2 * len(packed), dtype=np.uint8)
        flat[0::2], flat[1::2] = packed & 15, packed >> 4
        return cls(np.array(origin), float(cell), flat[:cells].reshape(x, y, z))


def outline_of(points: np.ndarray) -> Outline:
    """The outline of a surface (an entry's points, in its frame, +Y up)."""
    points = np.asarray(points, dtype=np.float64)
    anchored = points - floor_anchor(points)
    span = np.ptp(anchored, axis=0) + 2 * OUTLINE_TRUNCATION
    cell = max(OUTLINE_CELL, float(np.cbrt(np.prod(span + OUTLINE_CELL) / MAX_OUTLINE_CELLS)))
    grid = DistanceGrid.around(anchored, cell=cell, truncation=OUTLINE_TRUNCATION)
    levels = np.rint(grid.values.astype(np.float64) * (OUTLINE_LEVELS / LEVELS))
    return Outline(grid.origin, grid.cell, levels.astype(np.uint8))


def fit_distances(outlines: Sequence[Outline], points: np.ndarray) -> np.ndarray:
    """(C,) metres: for each outline, the least mean distance of ``points`` (a view's key points
    in the canonical frame, any anchor) to it over the shifts; the truncation for no points."""
    points = np.asarray(points, dtype=np.float64)
    if len(outlines) == 0 or len(points) == 0:
        return np.full(len(outlines), OUTLINE_TRUNCATION)
    chosen = points[np.linspace(0, len(points) - 1, min(FIT_POINTS, len(points))).astype(int)]
    chosen = chosen - floor_anchor(points)
    margin = np.array([SHIFT_CELLS, LIFT_CELLS, SHIFT_CELLS])
    shape = np.max([o.levels.shape for o in outlines], axis=0) + 2 * margin
    padded = np.full((len(outlines), *shape), OUTLINE_LEVELS, dtype=np.uint8)
    cells = np.empty((len(outlines), len(chosen), 3), dtype=np.int64)
    for row, outline in enumerate(outlines):
        x, y, z = outline.levels.shape
        padded[row, margin[0] : margin[0] + x, margin[1] : margin[1] + y,
               margin[2] : margin[2] + z] = outline.levels  # fmt: skip
        # Each point's cell, a point beyond the grid moved onto its edge (at the truncation),
        # so that every shift stays in the padded grid.
        found = np.rint((chosen - outline.origin) / outline.cell).astype(np.int64)
        cells[row] = np.clip(found, 0, np.array([x, y, z]) - 1) + margin
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    base = cells @ strides + (np.arange(len(outlines)) * int(np.prod(shape)))[:, None]
    steps = [np.arange(-m, m + 1) for m in margin]
    shifts = np.stack(np.meshgrid(*steps, indexing="ij"), axis=-1).reshape(-1, 3) @ strides
    levels = padded.ravel()[base[:, None, :] + shifts[None, :, None]]  # (C, shifts, points)
    best = levels.sum(axis=2, dtype=np.int32).min(axis=1)
    return best * (OUTLINE_TRUNCATION / OUTLINE_LEVELS / len(chosen))
