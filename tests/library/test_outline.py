"""Outlines: a coarse distance field per entry, and the fit of a view to it over shifts."""

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
    SHIFT_CELLS,
    Outline,
    fit_distances,
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


def _reference_fit(outline: Outline, points: np.ndarray) -> float:
    """The least mean nearest-cell level over the shifts, one shift at a time."""
    chosen = points[np.linspace(0, len(points) - 1, min(FIT_POINTS, len(points))).astype(int)]
    chosen = chosen - floor_anchor(points)
    best = np.inf
    reach = [SHIFT_CELLS, LIFT_CELLS, SHIFT_CELLS]
    for shift in itertools.product(*(range(-r, r + 1) for r in reach)):
        cells = np.rint((chosen - outline.origin) / outline.cell).astype(int)
        cells = np.clip(cells, 0, np.array(outline.levels.shape) - 1) + shift
        inside = np.all((cells >= 0) & (cells < outline.levels.shape), axis=1)
        levels = np.full(len(cells), OUTLINE_LEVELS)
        levels[inside] = outline.levels[tuple(cells[inside].T)]
        best = min(best, levels.mean())
    return best * OUTLINE_TRUNCATION / OUTLINE_LEVELS


def test_fit_distances_match_a_shift_by_shift_reference() -> None:
    outlines = [outline_of(_chair_like(seed, width=w)) for seed, w in ((2, 0.5), (3, 0.7))]
    rng = np.random.default_rng(4)
    view = _chair_like(5)[rng.choice(6400, 700, replace=False)] + [0.3, -0.2, 0.1]
    fitted = fit_distances(outlines, view)
    np.testing.assert_allclose(fitted, [_reference_fit(o, view) for o in outlines], atol=1e-12)


def test_a_partial_view_fits_its_own_model_better_than_another() -> None:
    own, other = _chair_like(6), _chair_like(7, width=0.6, seat=0.55)
    # the front half only: its anchor is not the model's, the shifts find it
    front = own[own[:, 2] < 0.3]
    view = front + np.random.default_rng(8).normal(0, 0.005, front.shape) + [2.0, 0.0, -1.0]
    near, far = fit_distances([outline_of(own), outline_of(other)], view)
    assert near < 0.02 and far > 2 * near  # within nearest-cell reads of 5 cm cells


def test_no_points_fit_nothing() -> None:
    assert fit_distances([outline_of(_chair_like(9))], np.zeros((0, 3))).tolist() == [
        OUTLINE_TRUNCATION
    ]
    assert fit_distances([], _chair_like(9)).shape == (0,)
