"""Each pose is refined once and fitted once per request, however many search rounds the
request takes (the later rounds meet the earlier rounds' poses again)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.geometry.se3 import make_pose, random_rotation
from catalign.library.loaded import load
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine

UP = np.array([0.0, 0.0, 1.0])


def _view(seed: int) -> np.ndarray:
    shape = procedural_shape(seed)
    pose = make_pose(upright_rotation(0.7 + 1.3 * seed), np.array([0.3, -0.2, 0.5]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    return render_view(shape, pose, camera, np.random.default_rng(seed))


@pytest.mark.parametrize("with_up", [True, False])
def test_every_pose_is_refined_and_fitted_once_over_two_rounds(
    monkeypatch: pytest.MonkeyPatch, with_up: bool
) -> None:
    extractor = LearnedExtractor()
    library = load(DEFAULT_MODEL_DIR / "library", extractor.fingerprint)
    # one heading described first, and every answer weak: a second round always runs
    config = EngineConfig(
        orient={"heading_mass": 0.01, "up_mass": 0.01}, decision={"heading_fallback": 1.0}
    )
    engine = Engine(extractor, library, config=config)
    refined: Counter[int] = Counter()
    fitted: Counter[int] = Counter()
    rounds, seen = [], []  # seen: the poses kept alive, so that no id is reused
    refine, fit, round_ = engine.refiner.refine, engine.refiner.fit, engine._round

    def counted_refine(pose, query):
        refined[id(pose)] += 1
        seen.append(pose)
        return refine(pose, query)

    def counted_fit(pose, query):
        fitted[id(pose)] += 1
        seen.append(pose)
        return fit(pose, query)

    def counted_round(searches, request):
        rounds.append(len(searches))
        return round_(searches, request)

    monkeypatch.setattr(engine.refiner, "refine", counted_refine)
    monkeypatch.setattr(engine.refiner, "fit", counted_fit)
    monkeypatch.setattr(engine, "_round", counted_round)
    points = _view(3)
    if not with_up:
        points = points @ random_rotation(np.random.default_rng(5)).T
    result = engine.register(points, up=UP if with_up else None, seed=0)
    assert result.model_id and len(rounds) >= 2
    assert refined and max(refined.values()) == 1, "a pose was refined twice"
    assert fitted and max(fitted.values()) == 1, "a pose was fitted twice"
