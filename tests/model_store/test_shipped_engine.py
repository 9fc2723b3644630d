"""The shipped checkpoint and default library through the engine: library chairs' own partial
views, under known rigid transforms, are recovered to within 2 degrees and 1 cm with ``up``,
and in any rotation without it (3 degrees and 3 cm)."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.geometry.se3 import make_pose, random_rotation, rotation_error_deg
from catalign.library.loaded import load
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine

UP = np.array([0.0, 0.0, 1.0])
SEEDS = range(12)
# Measured with the shipped checkpoint, orientation proposals, retrieval encoders and engine
# defaults: 8 of these 12 views are recovered within 2 degrees and 1 cm (0, 1, 2, 3, 5, 6, 7,
# 8; 5 of them when the shortlist pooled the features). The features were trained on ShapeNet
# chairs only. The floor leaves one case for other BLAS builds.
MIN_RECOVERED = 7
# The same views, the whole scene turned arbitrarily, without up: 11 of 12 recovered within 3
# degrees and 3 cm (all but 10; 7 with pooled features). A turned scene is voxelised
# differently, hence the looser bounds.
MIN_RECOVERED_WITHOUT_UP = 10


@pytest.fixture(scope="module")
def engine() -> Engine:
    extractor = LearnedExtractor()
    library = load(DEFAULT_MODEL_DIR / "library", extractor.fingerprint)
    config = EngineConfig(orient={"headings": extractor.headings}, top_k=10)
    return Engine(extractor, library, config=config)


def _recovered(engine: Engine, seed: int) -> bool:
    shape = procedural_shape(seed)
    # standing on the floor of a Z-up world, turned, seen from 2 m and 25 degrees up
    rotation = upright_rotation(0.7 + 1.3 * seed)
    pose = make_pose(rotation, np.array([0.3, -0.2, -shape.points[:, 1].min()]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(seed))
    result = engine.register(points, up=UP, seed=0)
    return (
        result.model_id == shape.shape_id
        and rotation_error_deg(result.pose[:3, :3], pose[:3, :3]) < 2.0
        and float(np.linalg.norm(result.pose[:3, 3] - pose[:3, 3])) < 0.01
    )


def test_own_partial_views_are_recovered(engine: Engine) -> None:
    recovered = [seed for seed in SEEDS if _recovered(engine, seed)]
    assert len(recovered) >= MIN_RECOVERED, f"recovered only the views of chairs {recovered}"


def _recovered_without_up(engine: Engine, seed: int) -> bool:
    """The same scene as above, the whole of it turned by an arbitrary rotation (a tilted
    hand-held sensor), registered without ``up``."""
    shape = procedural_shape(seed)
    rotation = upright_rotation(0.7 + 1.3 * seed)
    pose = make_pose(rotation, np.array([0.3, -0.2, -shape.points[:, 1].min()]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(seed))
    turn = make_pose(random_rotation(np.random.default_rng(100 + seed)), np.array([0.5, 1.0, -0.2]))
    expected = turn @ pose
    result = engine.register(points @ turn[:3, :3].T + turn[:3, 3], seed=0)
    return (
        result.model_id == shape.shape_id
        and result.up_estimated
        and rotation_error_deg(result.pose[:3, :3], expected[:3, :3]) < 3.0
        and float(np.linalg.norm(result.pose[:3, 3] - expected[:3, 3])) < 0.03
    )


def test_own_partial_views_in_any_rotation_are_recovered_without_up(engine: Engine) -> None:
    recovered = [seed for seed in SEEDS if _recovered_without_up(engine, seed)]
    assert len(recovered) >= MIN_RECOVERED_WITHOUT_UP, f"recovered only {recovered}"
