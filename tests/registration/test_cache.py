"""Per-model caches: bounded, least recently used dropped first, shared safely by threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from catalign.registration.assembly import build_matcher, build_refiner
from catalign.registration.config import EngineConfig
from catalign.registration.stages.model_cache import ModelCache


def test_the_least_recently_used_model_is_dropped_first():
    made: list[str] = []

    def maker(model_id: str):
        return lambda: made.append(model_id) or f"pieces of {model_id}"

    cache: ModelCache[str] = ModelCache(2)
    assert cache.get("a", maker("a")) == "pieces of a"
    cache.get("b", maker("b"))
    cache.get("a", maker("a"))  # used again: b is now the least recent
    cache.get("c", maker("c"))
    assert "a" in cache and "c" in cache and "b" not in cache and len(cache) == 2
    cache.get("b", maker("b"))  # made again when asked for
    assert made == ["a", "b", "c", "b"]


def test_without_a_capacity_every_model_is_kept_and_a_bad_one_is_refused():
    cache: ModelCache[int] = ModelCache(None)
    for i in range(500):
        cache.get(str(i), lambda i=i: i)
    assert len(cache) == 500
    with pytest.raises(ValueError, match="at least one"):
        ModelCache(0)


def test_threads_sharing_a_cache_get_their_values_and_the_bound_holds():
    cache: ModelCache[str] = ModelCache(8)
    ids = [str(i % 20) for i in range(2000)]
    with ThreadPoolExecutor(4) as pool:
        values = list(pool.map(lambda m: cache.get(m, lambda: m * 2), ids))
    assert values == [m * 2 for m in ids]
    assert len(cache) <= 8


def test_the_stages_keep_at_most_model_cache_models(make_entry, make_library):
    rng = np.random.default_rng(0)
    library = make_library(
        *(make_entry(f"m{i}", rng.normal(scale=0.2, size=(200, 3))) for i in range(3))
    )
    config = EngineConfig(model_cache=1)
    matcher = build_matcher(config, library, distance=0.05)
    refiner = build_refiner(config, library, distance=0.05)
    for model_id in library.ids:
        matcher.matchable(model_id)
        refiner.surface(model_id)
    assert len(matcher._matchable) == 1 and len(refiner._surfaces) == 1
    # what was dropped is computed again, the same
    first = matcher.matchable("m0")
    matcher.matchable("m1")
    np.testing.assert_array_equal(matcher.matchable("m0").rows, first.rows)
