"""Truncated distance grids: a point set's distance field, sampled once, read by lookups.

Verification asks, for every pose of every candidate, how far hundreds of posed points land
from a surface. A KD-tree answers each of those queries with a search; a grid of the distances,
computed once, answers it with one interpolated read, which is what makes scoring thousands of
poses cheap. Only distances up to the checks' inlier distance matter, so the field is
truncated there and quantized to one byte: the grid of a chair at 1.25 cm cells is a quarter of
a megabyte, and a step of ``truncation / 255`` (0.3 mm at 7.5 cm) is far below the cell's own
interpolation error.

The values are exact distances at the cell centres (a KD-tree query of every centre, bounded
at the truncation), not an Euclidean distance transform of an occupancy grid, which would move
every point to its cell's centre and err by up to half a cell diagonal before interpolating.
Between centres the read is trilinear, so near the surface a lookup errs by at most about one
cell: the distance field of a point set is a cone at each point, which interpolation blunts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

LEVELS = 255  # the uint8 value that means "at or beyond the truncation"
# Grid cell and truncation, in voxels of the extractor: half a voxel keeps a lookup within about
# 1 mm of the exact distance on average (at most a cell off, right on the surface); three
# voxels reach past the verification distance (two) and the coarse ICP distance (three).
CELL_VOXELS = 0.5
TRUNCATION_VOXELS = 3.0
# The most cells a grid holds (bytes, one per cell): a chair's grid holds about 0.6 million.
MAX_CELLS = 32_000_000


@dataclass(frozen=True, eq=False)
class DistanceGrid:
    """Distances (metres) to a point set, on a regular grid, clipped at ``truncation``.

    ``values`` (X,Y,Z) uint8 holds ``distance / step`` rounded, with ``LEVELS`` for "at or
    beyond the truncation"; cell ``(i, j, k)``'s centre is ``origin + cell * (i, j, k)``.
    Points outside the grid read as the truncation: the grid reaches that far past the points.

    Example::

        grid = DistanceGrid.around(surface, cell=0.0125, truncation=0.075)
        gaps = grid.distances(probes)  # (N,) metres, trilinear
    """

    values: np.ndarray
    origin: np.ndarray
    cell: float
    step: float

    @property
    def truncation(self) -> float:
        """The largest distance the grid tells apart from "far"."""
        return LEVELS * self.step

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The first and the last cell centre: the box the grid's distances are known in."""
        return self.origin, self.origin + self.cell * (np.array(self.values.shape) - 1)

    @classmethod
    def around(
        cls,
        points: np.ndarray,
        *,
        cell: float,
        truncation: float,
        low: np.ndarray | None = None,
        high: np.ndarray | None = None,
    ) -> DistanceGrid:
        """The grid of ``points``' distance field over the box ``low``..``high`` (their
        bounding box when not given) grown by ``truncation``."""
        points = np.asarray(points, dtype=np.float64)
        low = points.min(axis=0) if low is None else np.asarray(low, dtype=np.float64)
        high = points.max(axis=0) if high is None else np.asarray(high, dtype=np.float64)
        origin = low - truncation
        span = high + truncation - origin
        # A model far larger than furniture gets coarser cells, not a grid beyond memory.
        cell = max(cell, float(np.cbrt(np.prod(span + cell) / MAX_CELLS)))
        shape = np.ceil(span / cell).astype(int) + 1
        tree, step = cKDTree(points), truncation / LEVELS
        values = np.empty(shape, dtype=np.uint8)
        y, z = np.meshgrid(*(origin[a] + cell * np.arange(shape[a]) for a in (1, 2)), indexing="ij")
        for i in range(shape[0]):  # a slab at a time keeps the query's memory small
            centres = np.column_stack([np.full(y.size, origin[0] + cell * i), y.ravel(), z.ravel()])
            gaps, _ = tree.query(centres, distance_upper_bound=truncation)
            levels = np.minimum(np.round(np.minimum(gaps, truncation) / step), LEVELS)
            values[i] = levels.reshape(shape[1:])
        return cls(values, origin, float(cell), float(step))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Each of ``points`` (N,3)' distance to the point set (trilinear between centres),
        the truncation where it is that far or outside the grid."""
        coordinates = ((np.asarray(points, dtype=np.float64) - self.origin) / self.cell).T
        levels = map_coordinates(
            self.values, coordinates, output=np.float64, order=1, mode="nearest"
        )
        return levels * self.step
