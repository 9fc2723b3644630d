"""Outlines: a coarse distance field per entry, the fit of a view to it over shifts, and the
share of a view lying on it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial import cKDTree

from catalign.geometry.levelling import floor_anchor
from catalign.library.outline import (
    FIT_POINTS,
    LIFT_CELLS,
    OUTLINE_LEVELS,
    OUTLINE_TRUNCATION,
    SHARE_POINTS,
    SHIFT_CELLS,
    Outline,
    fit_outlines,
    lying_shares,
    outline_of,
)


def _chair_like(
    seed: int, width: float = 0.5, height: float = 0.9, seat: float = 0.4
) -> np.ndarray:
    """Points on a seat slab, a back slab and a leg, +Y up."""
    rng = np.random.default_rng(seed)
    top = rng.uniform([0, seat, 0], [width, seat + 0.05, width], (3000, 3))
    back = rng.uniform([0, seat + 0.05, width - 0.05], [width, height, width], (3000, 3))
    legs = rng.uniform([0, 0, 0], [0.04, seat, 0.04], (400, 3))
    return np.vstack([top, back, legs])


def test_an_outline_reads_back_from_its_bytes() -> None:
    outline = outline_of(_chair_like(0))
    again = Outline.from_bytes(outline.to_bytes())
    np.testing.assert_array_equal(again.levels, outline.levels)
    np.testing.assert_allclose(again.origin, outline.origin, atol=1e-6)
    assert again.cell == pytest.approx(outline.cell)
    assert len(outline.to_bytes()) < 5_000  # a chair-sized model in a few kilobytes


@pytest.mark.parametrize(
    "data", [b"", b"\x00" * 10, Outline(np.zeros(3), 0.05, np.zeros((3, 3, 3))).to_bytes()[:-2]]
)
def test_bytes_that_are_no_outline_are_refused(data: bytes) -> None:
    with pytest.raises(ValueError, match="outline"):
        Outline.from_bytes(data)


def test_the_levels_are_the_truncated_distances_in_steps() -> None:
    points = _chair_like(1)
    outline = outline_of(points)
    anchored = points - floor_anchor(points)
    x, y, z = outline.levels.shape
    cells = np.stack(np.meshgrid(np.arange(x), np.arange(y), np.arange(z), indexing="ij"), -1)
    centres = outline.origin + outline.cell * cells.reshape(-1, 3)
    exact = np.minimum(cKDTree(anchored).query(centres)[0], OUTLINE_TRUNCATION)
    step = OUTLINE_TRUNCATION / OUTLINE_LEVELS
    # 255 levels narrowed to 15: within one 4-bit step (and the 8-bit grid's half step)
    assert np.abs(outline.levels.ravel() * step - exact).max() <= step
    assert outline.levels.max() == OUTLINE_LEVELS and outline.levels.min() == 0


def _chosen(points: np.ndarray, count: int) -> np.ndarray:
    chosen = points[np.linspace(0, len(points) - 1, min(count, len(points))).astype(int)]
    return chosen - floor_anchor(points)


def _mean_level_at(outline: Outline, points: np.ndarray, shift) -> float:
    """The mean nearest-cell distance of the fit's points at one whole-cell shift."""
    cells = np.rint((_chosen(points, FIT_POINTS) - outline.origin) / outline.cell).astype(int)
    cells = np.clip(cells, 0, np.array(outline.levels.shape) - 1) + np.asarray(shift)
    inside = np.all((cells >= 0) & (cells < outline.levels.shape), axis=1)
    levels = np.full(len(cells), OUTLINE_LEVELS)
    levels[inside] = outline.levels[tuple(cells[inside].T)]
    return levels.mean() * OUTLINE_TRUNCATION / OUTLINE_LEVELS


def _reference_fit(outline: Outline, points: np.ndarray) -> float:
    """The least mean nearest-cell distance over the shifts, one shift at a time."""
    reach = [SHIFT_CELLS, LIFT_CELLS, SHIFT_CELLS]
    shifts = itertools.product(*(range(-r, r + 1) for r in reach))
    return min(_mean_level_at(outline, points, shift) for shift in shifts)


def _trilinear(levels: np.ndarray, at: np.ndarray) -> float:
    """One read between cell centres, cells outside the grid at the truncation's level."""
    low = np.floor(at).astype(int)
    total = 0.0
    for corner in itertools.product((0, 1), repeat=3):
        cell = low + corner
        weight = np.prod(np.where(corner, at - low, 1 - (at - low)))
        inside = np.all((cell >= 0) & (cell < levels.shape))
        total += weight * (levels[tuple(cell)] if inside else OUTLINE_LEVELS)
    return total


def _reference_share(outline: Outline, points: np.ndarray, shift, distance: float) -> float:
    """The best share over the half-cell offsets, one point and one offset at a time."""
    step = OUTLINE_TRUNCATION / OUTLINE_LEVELS
    chosen = (_chosen(points, SHARE_POINTS) - outline.origin) / outline.cell + shift
    best = 0.0
    for offset in itertools.product((-0.5, 0.0, 0.5), repeat=3):
        reads = [_trilinear(outline.levels, at + offset) for at in chosen]
        best = max(best, float(np.mean(np.array(reads) * step < distance)))
    return best


def test_fit_distances_match_a_shift_by_shift_reference() -> None:
    outlines = [outline_of(_chair_like(seed, width=w)) for seed, w in ((2, 0.5), (3, 0.7))]
    rng = np.random.default_rng(4)
    view = _chair_like(5)[rng.choice(6400, 700, replace=False)] + [0.3, -0.2, 0.1]
    fitted = fit_outlines(outlines, view)
    reference = [_reference_fit(o, view) for o in outlines]
    np.testing.assert_allclose(fitted.distances, reference, atol=1e-12)
    # the shift found reaches that distance (ties may pick another shift of the same sum)
    for outline, shift, distance in zip(outlines, fitted.shifts, fitted.distances, strict=True):
        assert _mean_level_at(outline, view, shift) == pytest.approx(distance, abs=1e-12)


def test_a_partial_view_fits_its_own_model_better_than_another() -> None:
    own, other = _chair_like(6), _chair_like(7, width=0.6, seat=0.55)
    # the front half only: its anchor is not the model's, the shifts find it
    front = own[own[:, 2] < 0.3]
    view = front + np.random.default_rng(8).normal(0, 0.005, front.shape) + [2.0, 0.0, -1.0]
    near, far = fit_outlines([outline_of(own), outline_of(other)], view).distances
    assert near < 0.02 and far > 2 * near  # within nearest-cell reads of 5 cm cells


def test_lying_shares_match_a_point_by_point_reference() -> None:
    outlines = [outline_of(_chair_like(2)), outline_of(_chair_like(3, width=0.6, seat=0.55))]
    rng = np.random.default_rng(4)
    view = _chair_like(2)[rng.choice(6400, 700, replace=False)] + [0.3, -0.2, 0.1]
    view = view + rng.normal(0, 0.005, view.shape)
    shifts = fit_outlines(outlines, view).shifts
    for distance in (0.02, 0.03, 0.05):
        shares = lying_shares(outlines, view, shifts, distance)
        reference = [
            _reference_share(o, view, s, distance) for o, s in zip(outlines, shifts, strict=True)
        ]
        np.testing.assert_allclose(shares, reference, atol=1e-12)
    near, far = lying_shares(outlines, view, shifts, 0.03)
    assert near > 0.9 and far < near - 0.2  # the view is of the first model


def test_no_points_fit_nothing() -> None:
    outline = outline_of(_chair_like(9))
    fit = fit_outlines([outline], np.zeros((0, 3)))
    assert fit.distances.tolist() == [OUTLINE_TRUNCATION] and fit.shifts.tolist() == [[0, 0, 0]]
    assert fit_outlines([], _chair_like(9)).distances.shape == (0,)
    assert lying_shares([outline], np.zeros((0, 3)), fit.shifts, 0.03).tolist() == [0.0]
