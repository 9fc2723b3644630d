"""The match stage: fixed key point subsets, mutual matches by library row, heading choice."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller
from catalign.geometry.se3 import axis_angle
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.match import Matcher, model_subset, probe_rows, query_subset


def _unit(count: int, seed: int) -> np.ndarray:
    features = np.random.default_rng(seed).normal(size=(count, 16))
    return features / np.linalg.norm(features, axis=1, keepdims=True)


@pytest.fixture
def library(make_entry, make_library):
    points = np.random.default_rng(0).uniform(-0.3, 0.3, (300, 3))
    return make_library(make_entry("m", points, features=_unit(300, 1)))


def _matcher(library, **options) -> Matcher:
    defaults = {
        "distance": 0.05,
        "keep_headings": 1,
        "heading_draws": 300,
        "match_points": None,
        "model_points": None,
    }
    return Matcher(library, **(defaults | options))


def test_query_subset_is_fixed_sorted_and_capped() -> None:
    assert np.array_equal(query_subset(40, 50, seed=1), np.arange(40))
    assert np.array_equal(query_subset(40, None, seed=1), np.arange(40))
    subset = query_subset(1000, 100, seed=3)
    assert len(subset) == 100 and np.all(np.diff(subset) > 0)
    assert np.array_equal(subset, query_subset(1000, 100, seed=3))
    assert not np.array_equal(subset, query_subset(1000, 100, seed=4))


def test_probe_rows_are_a_seeded_random_order() -> None:
    rows = probe_rows(500, 50, seed=2)
    assert len(set(rows.tolist())) == 50 and rows.max() < 500
    assert np.array_equal(rows, probe_rows(500, 50, seed=2))
    assert sorted(probe_rows(20, 50, seed=2).tolist()) == list(range(20))


def test_model_subset_keeps_rows_features_and_positions_together() -> None:
    keypoints = np.random.default_rng(0).normal(size=(100, 3))
    features = _unit(100, 1)
    whole = model_subset(keypoints, features, None)
    assert np.array_equal(whole.rows, np.arange(100)) and whole.features is features
    part = model_subset(keypoints, features, 30)
    assert len(part.rows) == 30 and np.all(np.diff(part.rows) > 0)
    assert np.array_equal(part.features, features[part.rows])
    assert np.array_equal(part.keypoints, keypoints[part.rows])
    assert np.array_equal(part.rows, model_subset(keypoints, features, 30).rows)


def test_matches_name_rows_of_the_query_and_of_the_library_entry(library) -> None:
    entry = library["m"]
    order = np.random.default_rng(5).permutation(entry.num_keypoints)
    view = QueryView(entry.keypoints[order] + 1.0, entry.features[order])
    found = _matcher(library, match_points=120).match("m", view, seed=0)
    # identical features: each query row is matched to the entry row it was copied from
    assert np.array_equal(found.pairs[:, 0], query_subset(len(order), 120, seed=0))
    assert np.array_equal(order[found.pairs[:, 0]], found.pairs[:, 1])
    assert np.array_equal(found.model_points, entry.keypoints[found.pairs[:, 1]])
    assert np.array_equal(found.observed, view.keypoints[found.pairs[:, 0]])


def test_only_the_models_matchable_rows_are_matched(library) -> None:
    entry = library["m"]
    view = QueryView(entry.keypoints, entry.features)
    matcher = _matcher(library, model_points=100)
    assert matcher.matchable("m") is matcher.matchable("m")  # cached
    rows = matcher.matchable("m").rows
    found = matcher.match("m", view, seed=0)
    assert set(found.pairs[:, 1].tolist()) <= set(rows.tolist())
    assert np.array_equal(found.pairs[:, 0], found.pairs[:, 1])  # each row's own copy


@pytest.mark.parametrize("with_up", [False, True])
def test_the_heading_whose_features_agree_is_kept(library, with_up: bool) -> None:
    entry = library["m"]
    up = np.array([0.0, 0.0, 1.0])
    turn = leveller(up) if with_up else None
    observed = entry.keypoints @ (leveller(up) if with_up else np.eye(3))  # model +Y -> +Z
    wrong = [QueryView(observed, _unit(entry.num_keypoints, seed)) for seed in (7, 8, 9)]
    right = QueryView(observed, entry.features)
    views = [*wrong[:2], right, wrong[2]]
    probes = probe_rows(entry.num_keypoints, 200, seed=0)
    chosen = _matcher(library, keep_headings=2).choose_headings(["m"], views, probes, turn, 0)
    assert len(chosen) == 2 and chosen[0] is right


def test_with_up_only_geometrically_consistent_matches_count(library) -> None:
    """Two headings with the same features: only the one whose key points an upright pose
    explains wins (the other's are turned over)."""
    entry = library["m"]
    up = np.array([0.0, 0.0, 1.0])
    upright = QueryView(entry.keypoints @ leveller(up), entry.features)
    tipped = axis_angle(np.array([1.0, 0.0, 0.0]), np.pi / 2) @ leveller(up).T
    over = QueryView(entry.keypoints @ tipped.T, entry.features)
    assert not np.allclose(tipped @ MODEL_UP, up)
    probes = probe_rows(entry.num_keypoints, 200, seed=0)
    matcher = _matcher(library, keep_headings=1)
    assert matcher.choose_headings(["m"], [over, upright], probes, leveller(up), 0) == [upright]


def test_no_choice_when_there_are_no_more_headings_than_kept(library) -> None:
    entry = library["m"]
    views = [QueryView(entry.keypoints, entry.features)] * 2
    matcher = _matcher(library, keep_headings=3)
    assert matcher.choose_headings(["m"], views, np.arange(5), None, 0) == views
