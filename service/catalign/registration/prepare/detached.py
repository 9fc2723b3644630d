"""Find small clusters detached from the chair a robot's segmentation kept (a neighbour's part,
flying pixels), so that they can be set aside before the features are computed, after the floor
(:mod:`~catalign.registration.prepare.floor`: a floor joins everything standing on it).

**Detached clusters** (:func:`detached_mask`). Points are put in cells of ``link / 3``; the
occupied cells are grown by one cell and labelled with 26-connectivity (``scipy.ndimage``), so
two points closer than ``link`` are always in one cluster, and two clusters farther apart than
4/3 ``link`` along every axis (2.3 ``link`` at most) never are. The main body is the largest
cluster by points; a cluster with fewer than ``small_share`` of its points is set aside,
never more than half of the cloud (smallest clusters first). The default ``link`` of 0.2 m is
measured: a 320 x 240 camera at 1.2 to 3 m sees surfaces at grazing angles as rows of points
several centimetres apart, and occlusion splits an office chair's base from its seat by 15 to
30 cm, so a chair's own view falls apart at small links. Over 240 ray-cast views of the 60
procedural chairs (no clutter), a link of 5 cm sets aside something in 59 % of the views (1.9 %
of the points on average, 16 % at most); 0.2 m in 11 % (0.13 % on average: 30 clusters of
28 points in the median, the largest an office chair's base 0.26 m under a seat that hides its
column, 6.7 % of that view). A blob of 200 points put 0.5 m from a chair is set aside in 90 % of
those views (the others have fewer than 2,000 points, so the blob is over a tenth of them),
at 0.3 m in 47 %, at 0.2 m never.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field
from scipy import ndimage

from catalign.options import OptionGroup
from catalign.registration.prepare.floor import MIN_POINTS, as_cloud

# Cells per link: cells of link/3 grown by one cell join every pair closer than link.
CELLS_PER_LINK = 3
# A larger grid than this is coarsened (a cell twice as large, until it fits).
MAX_GRID_CELLS = 20_000_000


class CleanupOptions(OptionGroup):
    """The clean-up's tunables (``engine.cleanup``); the measurements behind them are in the
    module docstring."""

    link_m: float = Field(default=0.2, gt=0, allow_inf_nan=False)
    """Points closer than this are in one cluster (0.2 m: see the module docstring)."""
    small_share: float = Field(default=0.1, ge=0, le=1)
    """Clusters with fewer points than this share of the main body's are set aside."""
    max_set_aside: float = Field(default=0.5, ge=0, le=1)
    """Never more than this share of the cloud is set aside."""


DEFAULT_OPTIONS = CleanupOptions()


def detached_mask(points: np.ndarray, *, options: CleanupOptions = DEFAULT_OPTIONS) -> np.ndarray:
    """Boolean mask (N,) of points in small clusters detached from the main object (no point
    within ``options.link_m`` metres of the main body).

    Clusters join points closer than the link (and never points more than 2.3 links apart); the
    largest is the main body and is always kept; clusters under ``small_share`` of its size are
    set aside, at most ``max_set_aside`` of the cloud. See the module docstring for why the link
    is 0.2 m.
    """
    pts = as_cloud(points)
    if len(pts) < MIN_POINTS:
        return np.zeros(len(pts), dtype=bool)
    labels = _clusters(pts, options.link_m)
    sizes = np.bincount(labels)
    main = int(np.argmax(sizes))
    small = np.flatnonzero(sizes < options.small_share * sizes[main])
    small = small[small != main]
    # Smallest first, while the total stays within max_set_aside of the cloud.
    small = small[np.argsort(sizes[small], kind="stable")]
    fits = np.cumsum(sizes[small]) <= options.max_set_aside * len(pts)
    aside = np.zeros(len(sizes), dtype=bool)
    aside[small[fits]] = True
    return aside[labels]


def _clusters(points: np.ndarray, link: float) -> np.ndarray:
    """Cluster label (N,) of each point: 26-connected components of the occupied cells of
    ``link / 3`` grown by one cell, so any two points closer than ``link`` share a label."""
    cell = link / CELLS_PER_LINK
    low = points.min(axis=0)
    span = points.max(axis=0) - low
    # Guard: a cloud over some 18 m (at 0.2 m) gets coarser cells, which join more, never less.
    while float(np.prod(np.floor(span / cell) + 3)) > MAX_GRID_CELLS:
        cell *= 2.0
    keys = np.floor((points - low) / cell).astype(np.int64) + 1
    grid = np.zeros(tuple(keys.max(axis=0) + 2), dtype=bool)
    grid[tuple(keys.T)] = True
    cube = np.ones((3, 3, 3), dtype=bool)
    labelled, _ = ndimage.label(ndimage.binary_dilation(grid, cube), structure=cube)
    return labelled[tuple(keys.T)] - 1
