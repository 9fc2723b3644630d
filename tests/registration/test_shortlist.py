"""The shortlist stage: models ranked by descriptor, size and height, best over headings."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.levelling import leveller
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.shortlist import shortlist


def _box(size: tuple[float, float, float], seed: int, count: int = 400) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, (count, 3)) * np.asarray(size)


def _features(seed: int, count: int) -> np.ndarray:
    features = np.random.default_rng(seed).normal(size=(count, 8)) + 3.0 * (seed % 3 == 0)
    return features / np.linalg.norm(features, axis=1, keepdims=True)


@pytest.fixture
def library(make_entry, make_library):
    shapes = {"a": (1, 0), "b": (2, 1), "c": (3, 3)}
    return make_library(
        *(
            make_entry(name, _box((0.5, 0.9, 0.5), seed), features=_features(feature_seed, 400))
            for name, (seed, feature_seed) in shapes.items()
        )
    )


def test_the_model_whose_features_the_query_shares_comes_first(library) -> None:
    view = QueryView(library["c"].keypoints, library["c"].features)
    assert shortlist(library, [view], None, None)[0] == "c"
    assert shortlist(library, [view], 2, None) == shortlist(library, [view], None, None)[:2]


def test_each_model_keeps_its_best_heading(library) -> None:
    wrong = QueryView(library["a"].keypoints, _features(7, 400))
    right = QueryView(library["a"].keypoints, library["a"].features)
    assert shortlist(library, [wrong, right], 1, None) == ["a"]


def test_with_up_a_model_of_another_height_drops_back(make_entry, make_library) -> None:
    tall = make_entry("tall", _box((0.5, 1.8, 0.5), 4), features=_features(5, 400))
    short = make_entry("short", _box((0.5, 0.9, 0.5), 4), features=_features(5, 400))
    library = make_library(tall, short)
    # the short model's own view, in a Z-up world: same features for both, heights differ
    z_up = np.array([0.0, 0.0, 1.0])
    observed = short.keypoints @ leveller(z_up)  # model +Y -> world +Z
    view = QueryView(observed, short.features)
    assert shortlist(library, [view], None, leveller(z_up)) == ["short", "tall"]


def _slabs(seat: float, seed: int) -> np.ndarray:
    """A seat and a back, +Y up: a chair's outline."""
    rng = np.random.default_rng(seed)
    top = rng.uniform([0, seat, 0], [0.5, seat + 0.05, 0.5], (1500, 3))
    back = rng.uniform([0, seat + 0.05, 0.45], [0.5, 0.9, 0.5], (1500, 3))
    return np.vstack([top, back, rng.uniform([0, 0, 0], [0.04, seat, 0.04], (200, 3))])


def test_the_model_a_view_lies_on_passes_one_its_descriptor_prefers(
    make_entry, make_library
) -> None:
    own, other = _slabs(0.40, 1), _slabs(0.55, 2)
    view_points = own[own[:, 2] < 0.3] + [1.0, 0.0, -2.0]  # its front, anywhere
    features = _features(5, len(view_points))
    library = make_library(
        make_entry("own", own, features=_features(5, len(own))),  # pooled, nearly the same
        make_entry("other", other, keypoints=view_points, features=features),
    )
    view = QueryView(view_points, features)  # the features the other model holds
    assert shortlist(library, [view], None, None) == ["other", "own"]
    fit = {"fit_from": 2, "fit_weight": 20.0}
    assert shortlist(library, [view], 1, None, fit_candidates=2, **fit) == ["own"]
    # only the best by descriptor are fitted: one candidate fitted keeps the order
    assert shortlist(library, [view], None, None, fit_candidates=1, **fit) == ["other", "own"]
    # and only in a library of at least ``fit_from`` models
    unfitted = {"fit_from": 3, "fit_candidates": 2, "fit_weight": 20.0}
    assert shortlist(library, [view], 1, None, **unfitted) == ["other"]
