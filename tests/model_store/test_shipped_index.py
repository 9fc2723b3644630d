"""The engine's shortlist through the library's index, against the exact scan it stands in for:
the shipped weights and a copy of the shipped library, indexed, queried with the index from
its first entry on."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import WORLD_UP, render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.geometry.se3 import make_pose
from catalign.library.loaded import load
from catalign.library.shortlist_index import INDEX_DIR
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine

SEEDS = range(4)


def view(seed: int) -> tuple[str, np.ndarray]:
    """A shipped chair seen by a camera, upright, at some heading."""
    shape = procedural_shape(seed)
    pose = make_pose(upright_rotation(0.7 + 1.3 * seed), np.array([0.3, -0.2, 0.0]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    return shape.shape_id, render_view(shape, pose, camera, np.random.default_rng(seed))


@pytest.fixture(scope="module")
def indexed_library(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("shipped") / "library"
    shutil.copytree(DEFAULT_MODEL_DIR / "library", folder, ignore=shutil.ignore_patterns(".lock"))
    assert (folder / INDEX_DIR).is_dir(), "the shipped library carries its index"
    return folder


def engines(library_dir: Path, candidates: int) -> tuple[Engine, Engine]:
    extractor = LearnedExtractor()
    library = load(library_dir, extractor.fingerprint)
    assert library.index is not None and library.index.indexed == len(library)
    exact = EngineConfig().replaced(shortlist={"index_from": None})
    through = EngineConfig().replaced(
        shortlist={"index_from": 1, "index_candidates": candidates}, top_k=5
    )
    return (
        Engine(extractor, library, config=exact.replaced(top_k=5)),
        Engine(extractor, library, config=through),
    )


def test_an_index_that_gives_every_entry_shortlists_as_the_exact_scan(indexed_library) -> None:
    exact, through = engines(indexed_library, candidates=100)  # more than the 60 entries
    for seed in SEEDS[:2]:
        _, points = view(seed)
        a = exact.register(points, up=WORLD_UP, seed=seed)
        b = through.register(points, up=WORLD_UP, seed=seed)
        assert [c.model_id for c in a.candidates] == [c.model_id for c in b.candidates]
        assert a.model_id == b.model_id
        np.testing.assert_allclose(a.pose, b.pose)


def test_a_few_neighbours_still_find_the_observed_chair(indexed_library) -> None:
    exact, through = engines(indexed_library, candidates=8)
    found = 0
    for seed in SEEDS:
        own, points = view(seed)
        a = exact.register(points, up=WORLD_UP, seed=seed)
        b = through.register(points, up=WORLD_UP, seed=seed)
        if a.model_id == own:  # where the exact scan finds it, 8 neighbours a heading do too
            assert b.model_id == own, seed
            found += 1
    assert found >= 2  # the exact scan's own answers, so that the check above means something
