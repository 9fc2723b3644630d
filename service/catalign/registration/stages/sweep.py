"""The upright sweep: poses of a model found from its surface alone, where its matches are few.

With an up the pose has four degrees of freedom, a yaw about the up and a shift. When the
observed chair's own CAD is in the library (a robot's known furniture), a view of it lies on
that model's surface at one pose, yet its features may give too few consistent matches for
the two-point search to find the pose: a near-twin then wins with a fraction of the fit. The
sweep does not need matches. Under each yaw of a grid (around the proposed headings) it tries
every shift of a grid that keeps the view inside the model's bounding box, grown by the inlier
distance (a view of a model lies within its box), and scores each pose by how much of a small
sample of the view lands near the model's surface, read from the model's distance grid
(:class:`~catalign.geometry.distance_grid.DistanceGrid`). The shifts are whole multiples of the
grid's cell, so every read of a yaw is one integer add and one gather, with no interpolation.

Each model's best distinct poses join the matched ones in verification. The grid poses are
within half a step of the truth (2.5 degrees and 1.25 cm at the defaults), inside the reach of
ICP, which the engine runs on the best of them when no matched pose fits exactly; it keeps
those that then fit exactly, and drops the rest. A swept pose of *another* instance fits its
surface without matching its parts (a seat on a seat, whichever way round), and measured a
worse category-level pose than the matched ones: the sweep is how the observed instance itself
is found, not another.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass

import numpy as np

from catalign.geometry.distance_grid import LEVELS, DistanceGrid
from catalign.geometry.levelling import yaw_rotations
from catalign.geometry.se3 import make_pose
from catalign.library.loaded import Library
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.gravity import DISTINCT_YAW_DEG, distinct_poses
from catalign.registration.stages.hypothesise import NO_MATCHES, Hypothesis


@dataclass(frozen=True)
class Sweep:
    """Each yaw's best shift of one model and its score: ``x = R(yaw) (m - shift)`` in the
    levelled frame, ``m`` a model point; yaws whose box holds no shift are left out."""

    yaws: np.ndarray
    shifts: np.ndarray
    scores: np.ndarray


def sweep_yaws(headings: tuple[float, ...], step_deg: float, span_deg: float | None) -> np.ndarray:
    """The yaws (radians) of the sweep: a grid of ``step_deg`` over the whole turn (``span_deg``
    None, or no ``headings``), or ``step_deg`` apart over ``span_deg`` either side of each of
    ``headings``, centred on it: the grid turns with the chair, as its proposed heading does,
    so a view moved by the sensor is swept at the same yaws relative to the chair. A yaw
    within half a step of an earlier one (of an earlier heading) is left out."""
    if span_deg is None or not headings:
        count = max(1, round(360.0 / step_deg))
        return np.arange(count) * (2 * np.pi / count)
    reach = int(np.floor(span_deg / step_deg + 1e-9))
    offsets = np.radians(step_deg) * np.arange(-reach, reach + 1)
    yaws: list[float] = []
    for yaw in (heading + offset for heading in headings for offset in offsets):
        turn = np.abs(np.angle(np.exp(1j * (np.array(yaws) - yaw))))
        if not np.any(turn < np.radians(step_deg) / 2):
            yaws.append(float(np.mod(yaw, 2 * np.pi)))
    return np.array(yaws)


def closeness_table(step: float, distance: float) -> np.ndarray:
    """For each level of a distance grid (``step`` metres apart), ``1 - (d / distance)**2``
    clipped at 0, as the surface check scores a point; the last level (at or beyond the
    truncation) scores 0."""
    gaps = np.arange(LEVELS + 1) * step
    table = np.clip(1.0 - (gaps / distance) ** 2, 0.0, None).astype(np.float32)
    table[LEVELS] = 0.0
    return table


def sweep_model(
    grid: DistanceGrid,
    bbox_min: np.ndarray,
    bbox_max: np.ndarray,
    levelled: np.ndarray,
    yaws: np.ndarray,
    *,
    distance: float,
    step_cells: int,
    max_shifts: int,
) -> Sweep:
    """The best shift of the view sample ``levelled`` (N,3, its up along +Y) onto one model at
    each of ``yaws``, by the mean closeness (:func:`closeness_table`) of the sample to the
    model's surface. The shifts keep the sample within the model's box grown by ``distance``.
    They are searched coarse to fine, every yaw at once: the shifts of a grid twice
    ``step_cells`` grid cells apart (at most about ``max_shifts`` a yaw: the step grows where
    the box leaves more room, as it does for a small view), scored with a looser distance,
    then the shifts ``step_cells`` apart around each yaw's best."""
    cell = grid.cell
    # Every read stays inside the grid: the fine pass reaches a step past the coarse grid.
    margin = min(distance, grid.truncation - step_cells * cell)
    turned = levelled @ yaw_rotations(yaws)  # R(yaw)^T x, per yaw
    low = bbox_min - margin - turned.min(axis=1)
    high = bbox_max + margin - turned.max(axis=1)
    feasible = np.flatnonzero(np.all(high >= low, axis=1))
    if len(feasible) == 0:
        return Sweep(np.zeros(0), np.zeros((0, 3)), np.zeros(0))
    turned, low, high = turned[feasible], low[feasible], high[feasible]
    room = (high - low) / cell  # in cells, per yaw and axis
    spread = np.prod(np.floor(room / (2 * step_cells)) + 1, axis=1).max()
    stride = 2 * step_cells * max(1, int(np.ceil((spread / max_shifts) ** (1 / 3))))
    counts = np.floor(room / stride).astype(np.int64) + 1
    start = (low + high) / 2 - (counts - 1) * stride * cell / 2
    reader = _GridReader(grid)
    base = reader.cells(turned + start[:, None, :])  # (Y,N,3)
    steps = np.indices(counts.max(axis=0)).reshape(3, -1).T  # (S,3), every yaw's grid within
    loose = closeness_table(grid.step, min(1.5 * distance, grid.truncation))
    every = np.broadcast_to(steps * stride, (len(base), *steps.shape))
    coarse = reader.closeness(base, every, loose)
    coarse[np.any(steps[None] >= counts[:, None], axis=2)] = -1.0  # beyond a yaw's own box
    best = steps[np.argmax(coarse, axis=1)] * stride  # (Y,3)
    fine = best[:, None, :] + (np.indices((3, 3, 3)).reshape(3, -1).T - 1) * step_cells
    closeness = reader.closeness(base, fine, closeness_table(grid.step, distance))
    chosen = np.argmax(closeness, axis=1)
    rows = np.arange(len(base))
    shifts = start + fine[rows, chosen] * cell
    return Sweep(yaws[feasible], shifts, closeness[rows, chosen].astype(np.float64))


class _GridReader:
    """Reads a distance grid at whole cells: a sample's cells once, then each shift (in cells)
    as one integer add and one gather of the flattened grid."""

    def __init__(self, grid: DistanceGrid) -> None:
        self.grid = grid
        self.values = grid.values.reshape(-1)
        shape = grid.values.shape
        self.strides = np.array([shape[1] * shape[2], shape[2], 1])

    def cells(self, points: np.ndarray) -> np.ndarray:
        """The cells of ``points`` (..., 3), as integers."""
        return np.rint((points - self.grid.origin) / self.grid.cell).astype(np.int64)

    def closeness(self, base: np.ndarray, steps: np.ndarray, table: np.ndarray) -> np.ndarray:
        """The mean ``table`` value of each yaw's sample at cells ``base`` (Y,N,3) shifted by
        each of that yaw's ``steps`` (Y,S,3 cells): (Y,S). The callers keep their reads inside
        the grid; a flat index past either end of it is clamped there, never read out of
        bounds."""
        flat = (base @ self.strides)[:, None, :] + (steps @ self.strides)[:, :, None]
        flat = np.clip(flat, 0, len(self.values) - 1)
        return table[self.values[flat]].mean(axis=2)


@dataclass(frozen=True)
class Sweeper:
    """Poses of the leading candidates from their surfaces (module docstring).

    ``distance`` is the inlier distance (metres); ``sweep_models`` how many of the best
    shortlisted models are swept (0: none), ``sweep_yaw_deg`` and ``sweep_step`` the yaw and
    shift steps (degrees, and cells of the library's distance grids), ``sweep_span_deg`` how
    far either side of each proposed heading the yaws reach (None: the whole turn),
    ``sweep_probes`` the view's points that are read, ``sweep_shifts`` the most shifts tried
    at a yaw, and ``sweep_poses`` the distinct poses kept of each model.
    """

    library: Library
    _: KW_ONLY
    distance: float
    sweep_models: int
    sweep_yaw_deg: float
    sweep_span_deg: float | None
    sweep_step: int
    sweep_probes: int
    sweep_shifts: int
    sweep_poses: int

    def poses(
        self,
        model_ids: list[str],
        probes: np.ndarray,
        turn: np.ndarray,
        headings: tuple[float, ...],
        view: QueryView,
    ) -> list[Hypothesis]:
        """The best distinct sweep poses of the first ``sweep_models`` of ``model_ids``, from
        the first ``sweep_probes`` of the query's ``probes`` (observation frame, in random
        order) levelled by ``turn``, at yaws around the proposed ``headings`` (every yaw when
        there are none). A pose records ``view``, the query's first, and no matches."""
        if self.sweep_models == 0:
            return []
        levelled = probes[: self.sweep_probes] @ turn.T
        yaws = sweep_yaws(headings, self.sweep_yaw_deg, self.sweep_span_deg)
        unlevel = make_pose(turn.T, np.zeros(3))
        found = []
        for model_id in model_ids[: self.sweep_models]:
            entry = self.library[model_id]
            sweep = sweep_model(
                entry.grid,
                entry.bbox_min,
                entry.bbox_max,
                levelled,
                yaws,
                distance=self.distance,
                step_cells=self.sweep_step,
                max_shifts=self.sweep_shifts,
            )
            order = np.argsort(-sweep.scores, kind="stable")
            rotations = yaw_rotations(sweep.yaws[order])
            translations = -np.einsum("hij,hj->hi", rotations, sweep.shifts[order])
            chosen = distinct_poses(
                sweep.yaws[order], translations, self.sweep_poses, DISTINCT_YAW_DEG, self.distance
            )
            found += [
                Hypothesis(
                    model_id,
                    unlevel @ make_pose(rotations[i], translations[i]),
                    NO_MATCHES,
                    view,
                    swept=True,
                )
                for i in chosen
            ]
        return found
