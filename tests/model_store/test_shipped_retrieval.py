"""The shipped retrieval encoders: they serve with the shipped weights and library, and a library
chair's own partial view finds its model among the shipped library by descriptor alone, where
the pooled features it replaces do not."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.geometry.se3 import make_pose
from catalign.library.loaded import Library, load
from catalign.library.retrieval import global_descriptor

SEEDS = range(12)
# Measured with the shipped encoders on these 12 views (the shipped engine test's), each
# described at its true heading, among the 60 shipped chairs: the view's own model ranks first
# for 10 and second for the other 2 (MIN_FIRST and MAX_RANK leave one for other BLAS builds);
# the mean and max of the same features rank it 20th to 60th, never among the top 10.
MIN_FIRST = 9
MAX_RANK = 2  # 0-based: third


@pytest.fixture(scope="module")
def shipped() -> tuple[LearnedExtractor, Library]:
    extractor = LearnedExtractor()
    return extractor, load(DEFAULT_MODEL_DIR / "library", extractor.fingerprint)


def test_the_shipped_weights_have_encoders_the_library_was_built_with(shipped) -> None:
    extractor, library = shipped
    assert extractor.retrieval is not None
    assert library.fingerprint == extractor.fingerprint
    assert extractor.fingerprint.endswith(extractor.retrieval.fingerprint[:16])
    card = extractor.retrieval.card
    assert card["extractor"] == extractor.card["sha256"]
    assert card["held_out"]["recall@10"] >= 0.9


def _ranks(extractor: LearnedExtractor, library: Library, seed: int) -> tuple[int, int]:
    """The rank of the view's own model among the library, by the encoders and pooled."""
    shape = procedural_shape(seed)
    rotation = upright_rotation(0.7 + 1.3 * seed)
    pose = make_pose(rotation, np.array([0.3, -0.2, -shape.points[:, 1].min()]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(seed))
    canonical = points @ rotation  # the view turned into the model's frame (its true heading)
    found = extractor.describe(canonical)
    assert extractor.retrieval is not None
    learned = extractor.retrieval.view_descriptors([(found.keypoints, found.features)])[0]
    pooled = global_descriptor(found.features)
    own = library.ids.index(shape.shape_id)
    ranks = []
    for query, models in ((learned, library.descriptors), (pooled, None)):
        if models is None:
            models = np.stack([global_descriptor(e.features) for e in library])
        scores = models @ query / np.linalg.norm(models, axis=1)
        ranks.append(int((scores > scores[own]).sum()))
    return ranks[0], ranks[1]


def test_own_views_find_their_model_by_descriptor(shipped) -> None:
    ranks = np.array([_ranks(*shipped, seed) for seed in SEEDS])
    learned, pooled = ranks[:, 0], ranks[:, 1]
    assert (learned == 0).sum() >= MIN_FIRST, f"own model ranks {learned.tolist()}"
    assert learned.max() <= MAX_RANK, f"own model ranks {learned.tolist()}"
    assert learned.mean() < pooled.mean(), f"{learned.tolist()} against {pooled.tolist()}"
