"""Outlines: each entry's coarse distance field, small enough to keep every entry's in memory.

A global descriptor ranks a partial view against whole models only roughly: among thousands of
chairs the view's own model is rarely first, though usually among the first few hundred. What
tells the own model apart is that the view lies on its surface. So every record carries its
entry's **outline**, the surface's distance field on 5 cm cells, truncated at 10 cm and kept in
4-bit levels (about 4 KB for a chair), and the shortlist re-ranks its best few hundred by the
mean distance of the view's key points to each outline (:func:`fit_outlines`). The best few
of those are read once more, finer (:func:`lying_shares`): the share of the view's points that
lie on the outline, read between cells and at half-cell offsets, which tells near twins apart
where a mean of nearest-cell reads does not.

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
from typing import NamedTuple

import numpy as np
from scipy.ndimage import map_coordinates

from catalign.geometry.distance_grid import LEVELS, DistanceGrid
from catalign.geometry.levelling import floor_anchor

OUTLINE_CELL = 0.05  # metres: finer cells cost memory at 10^5 entries, coarser lose the fit
OUTLINE_TRUNCATION = 0.10  # distances past this say only "off the surface"
OUTLINE_LEVELS = 15  # 4 bits a cell
MAX_OUTLINE_CELLS = 200_000  # a model far larger than furniture gets coarser cells
SHIFT_CELLS = 5  # shifts across the floor, in cells each way (25 cm)
LIFT_CELLS = 1  # shifts along the up (5 cm): the feet may be hidden
FIT_POINTS = 48  # view points read per shift
SHARE_POINTS = 100  # view points read per offset by lying_shares
# lying_shares' offsets around the best whole-cell shift, in cells along each axis
SHARE_OFFSETS = np.stack(np.meshgrid(*[(-0.5, 0.0, 0.5)] * 3, indexing="ij"), -1).reshape(-1, 3)
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


class OutlineFit(NamedTuple):
    """What :func:`fit_outlines` finds for each of C outlines."""

    distances: np.ndarray  # (C,) metres: the least mean distance of the view to the outline
    shifts: np.ndarray  # (C,3) whole cells: the shift of the view that reached it


def fit_outlines(outlines: Sequence[Outline], points: np.ndarray) -> OutlineFit:
    """For each outline, the least mean distance of ``points`` (a view's key points in the
    canonical frame, any anchor) to it over the shifts, and that shift; the truncation (and no
    shift) for no points."""
    points = np.asarray(points, dtype=np.float64)
    if len(outlines) == 0 or len(points) == 0:
        return OutlineFit(
            np.full(len(outlines), OUTLINE_TRUNCATION), np.zeros((len(outlines), 3), dtype=int)
        )
    chosen = _spread(points, FIT_POINTS)
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
    shifts = np.stack(np.meshgrid(*steps, indexing="ij"), axis=-1).reshape(-1, 3)
    levels = padded.ravel()[base[:, None, :] + (shifts @ strides)[None, :, None]]
    sums = levels.sum(axis=2, dtype=np.int32)  # (C, shifts)
    best = sums.argmin(axis=1)
    distances = sums[np.arange(len(outlines)), best] * (
        OUTLINE_TRUNCATION / OUTLINE_LEVELS / len(chosen)
    )
    return OutlineFit(distances, shifts[best])


def lying_shares(
    outlines: Sequence[Outline], points: np.ndarray, shifts: np.ndarray, distance: float
) -> np.ndarray:
    """(C,) for each outline, the largest share of ``points`` (up to :data:`SHARE_POINTS` of
    them) within ``distance`` of it, read trilinearly, over the half-cell offsets around its
    whole-cell shift in ``shifts`` (:func:`fit_outlines`'); 0 for no points."""
    points = np.asarray(points, dtype=np.float64)
    shares = np.zeros(len(outlines))
    if len(points) == 0:
        return shares
    chosen = _spread(points, SHARE_POINTS)
    step = OUTLINE_TRUNCATION / OUTLINE_LEVELS
    for row, (outline, shift) in enumerate(zip(outlines, shifts, strict=True)):
        at = (chosen - outline.origin) / outline.cell + shift
        at = (at[None] + SHARE_OFFSETS[:, None]).reshape(-1, 3).T
        levels = map_coordinates(
            outline.levels.astype(np.float32), at, order=1, mode="grid-constant",
            cval=OUTLINE_LEVELS,
        ).reshape(len(SHARE_OFFSETS), len(chosen))  # fmt: skip
        shares[row] = (levels * step < distance).mean(axis=1).max()
    return shares


def _spread(points: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` of ``points`` spread over their order, anchored as outlines are."""
    chosen = points[np.linspace(0, len(points) - 1, min(count, len(points))).astype(int)]
    return chosen - floor_anchor(points)
