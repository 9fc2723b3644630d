"""Find the floor a robot's segmentation kept under a chair, so that it can be set aside before
the features are computed (small clusters detached from the chair are
:mod:`~catalign.registration.prepare.detached`'s).

Both return masks; the caller decides what to drop (the floor first: a floor joins everything
standing on it into one cluster).

**Floor** (:func:`floor_mask`). Heights ``h = points @ up``; the floor, if any, is the lowest
large flat part of the cloud. A plane is searched among the points near the bottom (within
``band_m`` plus the tilt ``max_tilt_deg`` allows over the cloud's horizontal reach,
above the 0.5th percentile of ``h``) by RANSAC, with the plane's own normal within
``max_tilt_deg`` of ``up`` (so ``up`` may be off by 10 degrees), scoring the points within
2 cm of the plane minus four times those below it (a floor has nothing under it). It is refitted
by least squares on its inliers three times; the tolerance is 2.5 sigma of the residuals (their
MAD within 6 cm of the plane), at least ``min_tol_m`` and at most ``max_tol_m``. The
plane is a floor only if all of these hold:

* its inliers cover a real 2D area: at least ``min_floor_area_m2`` of occupied ``voxel``
  cells, and ``min_interior`` coarse cells (three voxels) with all eight neighbours occupied
  too. With no floor in view, the lowest plane (leg tips, casters, a pedestal's base plate, the
  bottom edges of a sofa's or a bench's panels) covers 0.11 m2 at most in 297 of 300 ray-cast
  views of the 60 procedural chairs; a ring of floor 0.2 m wide around the chair covers 0.35 m2
  at least (180 views). The three others are the seat of a sofa or a bench at the bottom of a
  view the camera cropped (0.4 to 0.75 m2), which the third rule rejects;
* its residual sigma is at most ``max_sigma_m``: a floor is flat to the sensor's noise
  (1.3 cm at most in those views) while a cushion is not. With ``up`` off by 10 degrees, a
  sofa's cushions were once taken for a floor (sigma 3.9 cm) before this rule;
* at most ``max_below_share`` of its inliers (plus ``below_slack`` points) lie below
  it: the noise of a real floor puts 0.9 % there at most, a seat has its front under it
  (3.5 % and more).

Under an up that was guessed, not given, a chair's backrest or side can pass all three, so
:func:`floor_mask` takes ``min_spread``: the floor must also reach past the chair
(:func:`spread`; the orient stage's thresholds and their measurements are in
:mod:`~catalign.registration.prepare.orient`). And a floor has an object standing on it: with
``min_standing``, the points above it must occupy that many voxels (a flat backrest seen face
on, with a few points beyond it, is all plane and passes every other rule).

The mask then holds the inliers and every point below the plane. Measured on ray-cast views of
the 60 procedural chairs (3 per chair, camera at 1.2 to 3 m, elevation 5 to 50 degrees, depth
noise as :class:`~catalign.data.camera.DepthNoise`) with a disc of floor reaching 0.3 m beyond
the chair: the floor is found in 178 of 180 views (the two others see less than 0.1 m2 of
floor past a sofa filling the image), recall 99.1 % at the least; chair points masked: 0.8 %
on average, 1.9 % at the 95th percentile. Parts lying on the floor lose what is within the
tolerance of it: a pedestal stool's base plate (2.5 cm thick) 5 to 10 % of the view, sled
runners up to 4 %. With ``up`` off by 10 degrees the numbers are the same. With no floor in
view, nothing is masked in 300 views, nor in 300 with ``up`` off by 10 degrees.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from numbers import Real

import numpy as np
from pydantic import Field
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from catalign.errors import InvalidInputError
from catalign.geometry.sampling import occupied_voxels
from catalign.options import OptionGroup
from catalign.registration.prepare.validation import MAX_RANGE_M

# Fewer points than this: nothing to clean, the masks are all False.
MIN_POINTS = 10


class FloorOptions(OptionGroup):
    """The floor's tunables (``engine.floor``); the measurements behind them are in the
    module docstring."""

    max_tilt_deg: float = Field(default=12.0, gt=0, lt=90)
    """Largest angle between the floor's normal and the up it is sought under (a given up may
    be off by about 10 degrees)."""
    bottom_percentile: float = Field(default=0.5, ge=0, le=100)
    """The bottom of the cloud: this percentile of the heights (robust to a few stray
    points)."""
    band_m: float = Field(default=0.05, gt=0)
    """The band above the bottom searched for the plane: this, plus what the tilt allows over
    the cloud's horizontal reach (99th percentile of the distances to its median)."""
    ransac_draws: int = Field(default=256, ge=1)
    """Plane hypotheses of the RANSAC."""
    ransac_sample: int = Field(default=4000, ge=3)
    """Points each hypothesis is scored on, at most."""
    ransac_tol_m: float = Field(default=0.02, gt=0)
    """Inlier distance of the RANSAC."""
    below_weight: float = Field(default=4.0, ge=0)
    """Weight of a point below a hypothesis, subtracted from its inliers (a floor has nothing
    under it)."""
    refits: int = Field(default=3, ge=1)
    """Least-squares refits on the inliers."""
    sigma_window_m: float = Field(default=0.06, gt=0)
    """The window of residuals the noise (sigma, from their median) is measured in."""
    tol_sigmas: float = Field(default=2.5, gt=0)
    """Inlier tolerance: this many sigmas of the residuals, clipped to ``min_tol_m`` ..
    ``max_tol_m``. 1.5 cm (not 2) at the least keeps more of the parts lying on the floor (0.8 %
    of a chair's points masked on average instead of 1.0 %, sled runners 4 % instead of 6 %, a
    pedestal's base 5-10 % instead of 10-13 %) at no cost in recall (99.1 % at the least
    either way)."""
    min_tol_m: float = Field(default=0.015, gt=0)
    """Smallest inlier tolerance."""
    max_tol_m: float = Field(default=0.05, gt=0)
    """Largest inlier tolerance."""
    min_floor_area_m2: float = Field(default=0.2, ge=0)
    """A floor covers this much occupied area (cells of a voxel) at least."""
    coarse_voxels: int = Field(default=3, ge=1)
    """Edge, in voxels, of the coarse cells a floor's interior is counted in."""
    min_interior: int = Field(default=4, ge=0)
    """Coarse cells with all eight neighbours occupied a floor holds at least (not a line)."""
    max_sigma_m: float = Field(default=0.02, gt=0)
    """A floor is flat to the sensor's noise: its residuals' sigma at most this."""
    max_below_share: float = Field(default=0.02, ge=0, le=1)
    """Share of a floor's inliers that may lie below it (plus ``below_slack`` points)."""
    below_slack: int = Field(default=20, ge=0)
    """Points below a floor allowed beyond ``max_below_share``."""
    remnant_band_m: float = Field(default=0.05, ge=0)
    """Floor remnants: points this low above a found floor, outside the footprint of the
    points above them (:func:`_floor_remnants`) ..."""
    footprint_margin_m: float = Field(default=0.03, ge=0)
    """... widened by this margin."""


DEFAULT_OPTIONS = FloorOptions()


@dataclass(frozen=True)
class FloorFit:
    """The lowest plane found and the measurements that decide whether it is a floor."""

    normal: np.ndarray
    offset: float
    tol: float
    sigma: float
    inliers: int
    below: int
    area: float
    interior: int
    is_floor: bool


def floor_mask(
    points: np.ndarray,
    up: np.ndarray,
    *,
    voxel: float,
    min_spread: float = 0.0,
    min_standing: int = 0,
    options: FloorOptions = DEFAULT_OPTIONS,
) -> np.ndarray:
    """Boolean mask (N,) of the points of a supporting floor: a plane perpendicular (within ~10
    deg) to the unit vector ``up`` at the bottom of the cloud along ``up``. All False when
    there is none.

    The floor's inliers (within max(1.5 cm, 2.5 sigma) of the plane) and everything below it
    are masked; ``voxel`` is the cell the floor's area is measured in. With ``min_spread``, the
    floor must also spread that many times wider than what stands on it (:func:`spread`); with
    ``min_standing``, what stands on it must occupy that many ``voxel`` cells. See the module
    docstring for the rules and their measured thresholds; ``options`` holds them.
    """
    pts = as_cloud(points)
    fit = fit_floor(pts, up, voxel=voxel, options=options)
    if fit is None or not fit.is_floor:
        return np.zeros(len(pts), dtype=bool)
    heights = pts @ fit.normal - fit.offset
    mask = (heights < fit.tol) | _floor_remnants(pts, heights, fit.normal, options)
    if occupied_voxels(pts[~mask], voxel) < min_standing:
        return np.zeros(len(pts), dtype=bool)
    if min_spread > 0 and spread(pts, mask, fit.normal) < min_spread:
        return np.zeros(len(pts), dtype=bool)
    return mask


def spread(points: np.ndarray, floor: np.ndarray, normal: np.ndarray) -> float:
    """The area of the ``floor`` points' convex hull in their plane over that of the other
    points' shadow on it (infinite when those cast none with an area).

    The floor a chair stands on reaches past the chair on the sides the camera sees; a chair's
    back or side, which a wrong guess of up puts at the bottom of the cloud, is no wider than
    the rest of the chair seen along it.
    """
    plane = _plane_basis(normal)
    areas = []
    for part in (points[floor], points[~floor]):
        try:
            areas.append(ConvexHull(part @ plane.T).volume)  # a 2D hull's volume is its area
        except (QhullError, ValueError):  # too few or collinear points: no area
            areas.append(0.0)
    return math.inf if areas[1] == 0 else areas[0] / areas[1]


def _floor_remnants(
    points: np.ndarray, heights: np.ndarray, normal: np.ndarray, options: FloorOptions
) -> np.ndarray:
    """Low points (under ``remnant_band_m`` above the floor) outside the chair's footprint:
    the floor's noisiest returns, beyond the plane's tolerance. Left in, a sparse ring of them
    around the chair stretches its observed extent, which the category fit centres on (in the
    evaluation's floor setting, RTE<5cm of another instance fell from 85 to 56 % before they
    were set aside). The footprint is where the points above the band stand, widened by
    ``footprint_margin_m``; parts of the chair that lie low inside it (a base plate,
    runners) stay."""
    low = heights < options.remnant_band_m
    standing = ~low
    if not low.any() or standing.sum() < 3:
        return np.zeros(len(points), dtype=bool)
    plane = _plane_basis(normal)
    footprint = points[standing] @ plane.T
    candidates = points[low] @ plane.T
    inside = np.zeros(len(candidates), dtype=bool)
    with contextlib.suppress(QhullError):  # collinear standing points: no area to stand in
        hull = footprint[ConvexHull(footprint).vertices]
        inside = Delaunay(hull).find_simplex(candidates) >= 0
    near, _ = cKDTree(footprint).query(candidates, distance_upper_bound=options.footprint_margin_m)
    remnants = np.zeros(len(points), dtype=bool)
    remnants[np.flatnonzero(low)] = ~inside & ~np.isfinite(near)
    return remnants


def fit_floor(
    points: np.ndarray, up: np.ndarray, *, voxel: float, options: FloorOptions = DEFAULT_OPTIONS
) -> FloorFit | None:
    """The lowest near-horizontal plane of the cloud and whether it is a floor (None when the
    cloud is too small to hold one); :func:`floor_mask` is what most callers want."""
    o = options
    pts = as_cloud(points)
    up = _as_up(up)
    check_length(voxel, "voxel")
    if len(pts) < MIN_POINTS:
        return None
    heights = pts @ up
    low = float(np.percentile(heights, o.bottom_percentile))
    flat = pts - np.outer(heights, up)
    reach = float(np.percentile(np.linalg.norm(flat - np.median(flat, axis=0), axis=1), 99.0))
    bottom = pts[heights <= low + o.band_m + reach * math.tan(math.radians(o.max_tilt_deg))]
    if len(bottom) < 3:
        return None
    normal, offset = _ransac_plane(bottom, up, np.random.default_rng(0), o)
    tol, sigma = o.ransac_tol_m, 0.0
    for _ in range(o.refits):
        near = np.abs(pts @ normal - offset) < tol
        if near.sum() < 3:
            return None
        normal, offset = _refit(pts[near], normal, offset, up, o.max_tilt_deg)
        residuals = np.abs(pts @ normal - offset)
        window = residuals[residuals < o.sigma_window_m]
        sigma = 1.4826 * float(np.median(window)) if len(window) else 0.0
        tol = float(np.clip(o.tol_sigmas * sigma, o.min_tol_m, o.max_tol_m))
    residuals = pts @ normal - offset
    inliers = np.abs(residuals) < tol
    below = int((residuals < -tol).sum())
    area, interior = _coverage(pts[inliers] @ _plane_basis(normal).T, voxel, o.coarse_voxels)
    is_floor = (
        area >= o.min_floor_area_m2
        and interior >= o.min_interior
        and sigma <= o.max_sigma_m
        and below <= o.max_below_share * inliers.sum() + o.below_slack
    )
    return FloorFit(
        normal=normal,
        offset=offset,
        tol=tol,
        sigma=sigma,
        inliers=int(inliers.sum()),
        below=below,
        area=area,
        interior=interior,
        is_floor=bool(is_floor),
    )


def as_cloud(points: np.ndarray) -> np.ndarray:
    """Finite float64 (N, 3) points, or InvalidInputError (far coordinates would blow up grids)."""
    try:
        cloud = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"points must be an (N, 3) array of numbers: {exc}") from None
    if cloud.ndim != 2 or cloud.shape[1] != 3:
        raise InvalidInputError(f"points must be an (N, 3) array, got shape {cloud.shape}")
    if not np.isfinite(cloud).all():
        raise InvalidInputError("points hold NaN or infinite values")
    if len(cloud) and float(np.abs(cloud).max()) > MAX_RANGE_M:
        raise InvalidInputError(
            f"points lie more than {MAX_RANGE_M:g} m from the origin; send them in metres"
        )
    return cloud


def _as_up(up: np.ndarray) -> np.ndarray:
    """``up`` as a unit 3-vector, or InvalidInputError."""
    try:
        vector = np.asarray(up, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"up must be a 3-vector of numbers: {exc}") from None
    if vector.shape != (3,) or not np.isfinite(vector).all() or not np.linalg.norm(vector) > 0:
        raise InvalidInputError(f"up must be a finite non-zero 3-vector, got {vector.tolist()}")
    return vector / np.linalg.norm(vector)


def check_length(value: float, name: str) -> None:
    """InvalidInputError unless ``value`` is a positive finite number (metres)."""
    number = isinstance(value, Real) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or value <= 0:
        raise InvalidInputError(f"{name} must be a positive number of metres, got {value!r}")


def cone_planes(
    points: np.ndarray, up: np.ndarray, *, max_tilt_deg: float, draws: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Planes through ``draws`` random triples of ``points`` whose normal, turned towards
    ``up``, is within ``max_tilt_deg`` of it: unit normals (K,3) and offsets (K,) with
    ``normal @ x = offset`` on the plane. Empty when no triple qualifies."""
    picks = rng.integers(0, len(points), size=(draws, 3))
    a, b, c = points[picks[:, 0]], points[picks[:, 1]], points[picks[:, 2]]
    normals = np.cross(b - a, c - a)
    lengths = np.linalg.norm(normals, axis=1)
    valid = lengths > 1e-12
    normals[valid] /= lengths[valid, None]
    normals *= np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    valid &= normals @ up >= math.cos(math.radians(max_tilt_deg))
    return normals[valid], np.einsum("ij,ij->i", normals[valid], a[valid])


def _ransac_plane(
    points: np.ndarray, up: np.ndarray, rng: np.random.Generator, options: FloorOptions
) -> tuple[np.ndarray, float]:
    """The plane (unit normal towards ``up``, offset) through three of ``points`` with the best
    score: points within ``ransac_tol_m`` minus ``below_weight`` times the points below it, so
    that the lowest large plane wins over the tips of the legs and over a seat."""
    o, scored = options, points
    if len(scored) > o.ransac_sample:
        scored = scored[rng.choice(len(scored), o.ransac_sample, replace=False)]
    normals, offsets = cone_planes(
        points, up, max_tilt_deg=o.max_tilt_deg, draws=o.ransac_draws, rng=rng
    )
    if len(normals) == 0:
        return up, float(np.percentile(points @ up, 50.0))
    residuals = scored @ normals.T - offsets
    score = (np.abs(residuals) < o.ransac_tol_m).sum(axis=0) - o.below_weight * (
        residuals < -o.ransac_tol_m
    ).sum(axis=0)
    best = int(np.argmax(score))
    return normals[best], float(offsets[best])


def _refit(
    points: np.ndarray, normal: np.ndarray, offset: float, up: np.ndarray, max_tilt_deg: float
) -> tuple[np.ndarray, float]:
    """Least-squares plane of ``points``; the previous one when its normal leaves the cone."""
    centre = points.mean(axis=0)
    fitted = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    if fitted @ up < 0:
        fitted = -fitted
    if fitted @ up < math.cos(math.radians(max_tilt_deg)):
        return normal, offset
    return fitted, float(fitted @ centre)


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal in-plane axes."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(normal, first)])


def _coverage(uv: np.ndarray, voxel: float, coarse_voxels: int) -> tuple[float, int]:
    """Occupied area (m2, cells of ``voxel``) of in-plane points, and the count of their coarse
    cells (``coarse_voxels`` voxels) whose eight neighbours are occupied too: zero for lines and
    small blobs whatever their extent. Sparse, so a stray far inlier costs nothing."""
    if len(uv) == 0:
        return 0.0, 0
    area = len(np.unique(np.floor(uv / voxel).astype(np.int64), axis=0)) * voxel**2
    cells = np.floor(uv / (coarse_voxels * voxel)).astype(np.int64)
    cells -= cells.min(axis=0) - 1
    width = int(cells[:, 1].max()) + 2
    keys = np.unique(cells[:, 0] * width + cells[:, 1])
    full = np.ones(len(keys), dtype=bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                full &= np.isin(keys + di * width + dj, keys, assume_unique=False)
    return float(area), int(full.sum())
