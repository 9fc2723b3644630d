"""The engine's per-orientation searches and its stage clock."""

from __future__ import annotations

import time

import numpy as np
import pytest

from catalign.deadline import Deadline
from catalign.errors import DeadlineExceededError
from catalign.registration.results import Orientation
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.search import StageClock, query_searches

UP = np.array([0.0, 0.0, 1.0])


def _views(count: int, points: int, rng: np.random.Generator) -> list[QueryView]:
    return [
        QueryView(rng.normal(size=(points, 3)), rng.normal(size=(points, 8))) for _ in range(count)
    ]


def test_views_are_split_by_orientation_in_the_order_of_their_headings():
    rng = np.random.default_rng(0)
    orientations = [
        Orientation(UP, given=True, headings=(0.0, 1.0)),
        Orientation(-UP, given=False, headings=(0.5, 1.5, 2.5)),
    ]
    views = _views(5, 40, rng)
    searches = query_searches(orientations, views, probe_points=16, seed=3, support_radius=0.5)
    assert [s.orientation for s in searches] == orientations
    assert searches[0].views == views[:2] and searches[1].views == views[2:]
    for search in searches:
        assert search.keypoints is search.views[0].keypoints
        assert len(search.probes) == 16 and search.probes.max() < 40
        assert search.candidates == () and search.checks is None
        assert search.turn is not None  # an up: the turn that stands the query upright
    # the probe rows depend on the seed alone (and the key point count)
    again = query_searches(orientations, views, probe_points=16, seed=3, support_radius=0.5)
    np.testing.assert_array_equal(again[1].probes, searches[1].probes)


def test_a_free_search_has_no_turn_and_solid_points_have_neighbours():
    lone = np.array([[5.0, 5.0, 5.0]])
    cluster = np.random.default_rng(1).normal(scale=0.01, size=(30, 3))
    view = QueryView(np.vstack([cluster, lone]), np.zeros((31, 4)))
    (search,) = query_searches(
        [Orientation(None, given=False, headings=(0.0,))],
        [view],
        probe_points=8,
        seed=0,
        support_radius=0.1,
    )
    assert search.turn is None
    np.testing.assert_array_equal(search.solid, cluster)  # the stray point is left out


def test_the_clock_adds_up_each_stage_and_checks_the_deadline():
    clock = StageClock(None)
    for _ in range(2):
        with clock("verify"):
            time.sleep(0.01)
    assert clock.timings["verify"] >= 20.0
    assert list(clock.each([1, 2])) == [1, 2]

    expired = StageClock(Deadline(0.0))
    with pytest.raises(DeadlineExceededError), expired("features"):
        pass
    with pytest.raises(DeadlineExceededError):
        list(expired.each([1]))
