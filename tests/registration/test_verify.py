"""The verify stage: poses ranked by the query they explain and the surface they cover."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.levelling import leveller
from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, make_pose, transform
from catalign.registration.results import Candidate
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.verify import Scored, Verifier, best_per_model, surface_sample

Z_UP = np.array([0.0, 0.0, 1.0])
POSE = make_pose(axis_angle(Z_UP, 0.8) @ leveller(Z_UP).T, np.array([0.4, 0.1, 0.0]))


@pytest.fixture(scope="module")
def chair_points(box_chair) -> np.ndarray:
    return box_chair.points[::3]


@pytest.fixture
def library(chair_points, make_entry, make_library):
    centre = (chair_points.min(axis=0) + chair_points.max(axis=0)) / 2
    bulky = (chair_points - centre) * np.array([1.4, 1.0, 1.4]) + centre  # an armchair-ish one
    return make_library(make_entry("chair", chair_points), make_entry("bulky", bulky))


@pytest.fixture
def keypoints(chair_points) -> np.ndarray:
    observed, _ = voxel_downsample(transform(chair_points, POSE), 0.03)
    return observed


def _verifier(library, **options) -> Verifier:
    defaults = {"distance": 0.06, "coverage_points": 1_500, "verify_top": 32, "cell": 0.015}
    return Verifier(library, **(defaults | options))


def _hypothesis(model_id: str, pose: np.ndarray, keypoints: np.ndarray) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis(model_id, pose, np.zeros((0, 2), dtype=np.int64), view)


def _turned(angle: float) -> np.ndarray:
    return make_pose(axis_angle(Z_UP, angle), np.zeros(3)) @ POSE


def test_the_right_pose_of_the_right_model_ranks_first(library, keypoints) -> None:
    verifier = _verifier(library)
    checks = verifier.query_checks(keypoints, np.arange(0, len(keypoints), 2), leveller(Z_UP))
    hypotheses = [
        _hypothesis("chair", _turned(np.pi), keypoints),  # the back for the front
        _hypothesis("bulky", POSE, keypoints),  # explains as much, covers less
        _hypothesis("chair", POSE, keypoints),
        _hypothesis("chair", _turned(np.pi / 2), keypoints),
    ]
    ranked = verifier.rank(hypotheses, checks)
    assert ranked[0].hypothesis is hypotheses[2]
    assert ranked[0].score > 0.8 and ranked[1].score < ranked[0].score - 0.1
    assert [item.score for item in ranked] == sorted((item.score for item in ranked), reverse=True)
    assert verifier.score(hypotheses[2], checks).score == ranked[0].score


def test_only_the_best_explained_poses_get_the_full_score(library, keypoints) -> None:
    verifier = _verifier(library, verify_top=2)
    checks = verifier.query_checks(keypoints, np.arange(len(keypoints)), None)
    assert checks.layout is None
    hypotheses = [_hypothesis("chair", _turned(a), keypoints) for a in (1.0, 0.0, 2.0, 3.0)]
    explained = verifier.explained(hypotheses, checks.probes)
    ranked = verifier.rank(hypotheses, checks)
    assert len(ranked) == 2
    assert {id(item.hypothesis) for item in ranked} == {
        id(hypotheses[i]) for i in np.argsort(explained)[-2:]
    }


def test_every_candidate_is_answered_once_with_its_best_score(keypoints) -> None:
    def scored(model_id: str, score: float) -> Scored:
        return Scored(_hypothesis(model_id, POSE, keypoints), score)

    tried = [scored("a", 0.3), scored("c", 0.2), scored("a", 0.5)]
    assert best_per_model(["a", "b", "c"], tried) == [
        Candidate("a", 0.5),
        Candidate("c", 0.2),
        Candidate("b", 0.0),
    ]


def test_surface_sample_takes_every_nth_point_as_float64(chair_points) -> None:
    stored = chair_points.astype(np.float32)  # as a library entry holds them
    sample = surface_sample(stored, 1_000)
    assert sample.dtype == np.float64
    assert 1_000 <= len(sample) < 2_000
    assert np.array_equal(sample[1], stored[len(stored) // 1_000])
