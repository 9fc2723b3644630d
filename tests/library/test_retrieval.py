from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.geometry.distance_grid import DistanceGrid
from catalign.library import Library, LibraryEntry, build, global_descriptor, load, shortlist
from catalign.library.retrieval import retrieval_scores
from catalign.library.store import Manifest


def synthetic_library(descriptors: np.ndarray, sizes: np.ndarray) -> Library:
    entries = []
    for i, (descriptor, size) in enumerate(zip(descriptors, sizes, strict=True)):
        size = np.asarray(size, dtype=np.float64)
        entries.append(
            LibraryEntry(
                model_id=f"m{i}",
                points=np.zeros((1, 3), np.float32),
                keypoints=np.zeros((1, 3)),
                features=np.zeros((1, 2), np.float32),
                descriptor=np.asarray(descriptor, np.float32),
                bbox_min=-size / 2,
                bbox_max=size / 2,
                size=size,
                grid=DistanceGrid.around(np.zeros((1, 3)), cell=0.025, truncation=0.15),
                source="test",
                source_sha256="0" * 64,
                units="m",
            )
        )
    manifest = Manifest(fingerprint="x", voxel_size=0.05, created="", updated="")
    return Library(Path("mem"), manifest, entries)


def test_global_descriptor():
    features = np.random.default_rng(0).normal(size=(50, 5)).astype(np.float32)
    descriptor = global_descriptor(features)
    assert descriptor.shape == (10,) and descriptor.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(descriptor[:5]), 1, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(descriptor[5:]), 1, rtol=1e-6)
    np.testing.assert_allclose(descriptor, global_descriptor(features[::-1]))  # order-free
    with pytest.raises(DegenerateInputError):
        global_descriptor(np.zeros((0, 5)))


def test_shortlist_finds_an_entry_from_its_own_descriptor(files, tmp_path, extractor):
    sources = [files.cloud(f"c{i}.npy", i, scale=0.2 + 0.1 * i) for i in range(4)]
    sources.append(files.box("box.obj"))
    build(sources, tmp_path / "lib", extractor, progress=False)
    lib = load(tmp_path / "lib", extractor.fingerprint)
    for entry in lib:
        ranked = shortlist(lib, entry.descriptor, entry.size, k=2)
        assert ranked[0] == entry.model_id and len(ranked) == 2
    query = lib["c2"]
    assert shortlist(lib, query.descriptor, query.size, k=None) == shortlist(
        lib, query.descriptor, query.size, k=99
    )
    assert sorted(shortlist(lib, query.descriptor, None, None)) == lib.ids


def test_a_query_larger_than_a_model_is_demoted():
    lib = synthetic_library(
        descriptors=np.array([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0]]),
        sizes=np.array([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]),
    )
    query = np.array([1.0, 0.0])
    assert shortlist(lib, query, None, k=None) == ["m0", "m1", "m2"]
    # a 0.8 m wide view cannot come from a model 0.17 m across
    assert shortlist(lib, query, np.array([0.8, 0.3, 0.2]), k=None) == ["m1", "m2", "m0"]
    # a small view fits anywhere: no penalty
    np.testing.assert_allclose(
        retrieval_scores(lib, query, np.array([0.05, 0.05, 0.05])),
        retrieval_scores(lib, query, None),
    )


def test_with_gravity_a_model_of_another_height_is_demoted():
    lib = synthetic_library(
        descriptors=np.array([[1.0, 0.0], [0.95, 0.05], [0.9, 0.1]]),
        sizes=np.array([[0.5, 1.2, 0.5], [0.5, 0.9, 0.5], [0.5, 0.7, 0.5]]),  # heights along +Y
    )
    query = np.array([1.0, 0.0])
    without = retrieval_scores(lib, query, None)
    with_height = retrieval_scores(lib, query, None, query_height=0.9)
    assert np.argmax(without) == 0 and np.argmax(with_height) == 1
    # a view taller than the model costs twice what a shorter one (feet hidden) does
    penalty = without - with_height
    assert penalty[1] == pytest.approx(0.0)
    assert penalty[2] / (0.2 / 0.7) == pytest.approx(2 * penalty[0] / (0.3 / 1.2))


def test_shortlist_arguments():
    lib = synthetic_library(np.eye(3), np.ones((3, 3)))
    with pytest.raises(InvalidInputError, match="at least 1"):
        shortlist(lib, np.ones(3), None, k=0)
    with pytest.raises(InvalidInputError, match="4 values but the library's have 3"):
        shortlist(lib, np.ones(4), None, k=1)
    assert shortlist(lib, np.ones(3), None, k=None) == ["m0", "m1", "m2"]  # ties by id
    empty = synthetic_library(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0 and shortlist(empty, np.ones(3), None, k=3) == []


def test_the_shortlist_stage_ranks_as_a_full_sort_does() -> None:
    """The stage keeps the best k by a partial sort; a full stable sort of every score is the
    reference, ties (repeated descriptors) in library order, with and without a category."""
    from catalign.registration.stages.describe import QueryView
    from catalign.registration.stages.shortlist import shortlist as stage_shortlist

    rng = np.random.default_rng(3)
    descriptors = rng.normal(size=(300, 64)).astype(np.float32)
    descriptors[150:] = descriptors[:150]  # every score twice: ties everywhere
    lib = synthetic_library(descriptors, np.full((300, 3), 0.6))
    views = [QueryView(np.zeros((2, 3)), rng.normal(size=(5, 32))) for _ in range(3)]
    query = np.stack([global_descriptor(v.features) for v in views])
    scores = retrieval_scores(lib, query, np.zeros(3)).max(axis=0)
    rows = rng.random(300) < 0.3
    for k, mask in [(1, None), (10, None), (None, None), (7, rows), (None, rows), (500, rows)]:
        order = np.argsort(-scores, kind="stable")
        if mask is not None:
            order = order[mask[order]]
        expected = [lib.ids[i] for i in order[:k]]
        assert stage_shortlist(lib, views, k, None, mask) == expected
