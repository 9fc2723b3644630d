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
