"""The finish stage: an exact fit keeps its pose and gets its statistics and evidence; another
instance is stood upright and recentred by the category fit; the result carries the winner's
fit, the candidates' best scores and the alternatives."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from catalign.data.views import WORLD_UP, upright_rotation
from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.decision.confidence import Calibrator, Tree
from catalign.registration.decision.finish import Finisher
from catalign.registration.decision.rules import Finished, Found, Refined
from catalign.registration.prepare.validation import CheckedCloud
from catalign.registration.results import Orientation
from catalign.registration.stages.category_fit import CategoryFitter
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import Refiner
from catalign.registration.stages.request import RequestCache
from catalign.registration.stages.search import Search
from catalign.registration.stages.verify import Scored

VOXEL = 0.03
POSE = make_pose(upright_rotation(0.6), np.array([0.5, -0.3, 0.0]))


@pytest.fixture
def finisher(box_chair, make_entry, make_library) -> Finisher:
    library = make_library(make_entry("chair", box_chair.points))
    refiner = Refiner(library, distance=VOXEL, icp_iterations=30, icp_points=None)
    return Finisher(
        library,
        refiner,
        CategoryFitter(library, refiner, extent_points=1500),
        icp_distance=VOXEL,
        exact_fitness=0.9,
        calibrator=None,
    )


def _search(finisher: Finisher, keypoints: np.ndarray) -> Search:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    probes = np.arange(min(384, len(keypoints)))
    return Search(Orientation(WORLD_UP, True, (0.0,)), [view], probes, support_radius=2 * VOXEL)


def _posed(search: Search, pose: np.ndarray, score: float) -> Scored:
    return Scored(Hypothesis("chair", pose, np.zeros((0, 2), np.int64), search.views[0]), score)


def _refined(finisher: Finisher, search: Search, item: Scored) -> Refined:
    """``item`` taken as refined already: its fit measured, its score's factors made up."""
    fit = finisher.refiner.fit(item.hypothesis, search.keypoints)
    return Refined(Found(search, item), item, (item.score, 1.0, 1.0), fit)


def _finish(finisher: Finisher, search: Search, item: Scored, tried: list[Scored]) -> Finished:
    refined = _refined(finisher, search, item)
    return finisher.finish(refined, tried, True, estimate_scale=False, cache=RequestCache())


def test_an_exact_fit_keeps_its_pose_and_gets_its_evidence(finisher, box_chair) -> None:
    keypoints, _ = voxel_downsample(transform(box_chair.points, POSE), VOXEL)
    search = _search(finisher, keypoints)
    item = _posed(search, POSE, 0.8)
    turned = _posed(search, POSE @ make_pose(axis_angle(np.array([0, 1.0, 0]), np.pi), 0), 0.4)
    done = _finish(finisher, search, item, [item, turned])
    np.testing.assert_allclose(done.item.hypothesis.transform, POSE)
    assert done.fit.fitness > 0.95 and done.confidence is None
    assert done.evidence.fitness == pytest.approx(done.fit.fitness)
    assert done.evidence.heading_margin == pytest.approx(0.4 / 0.8)  # the half turn's score
    assert done.evidence.model_margin == 0.0  # no other model was tried

    cloud = CheckedCloud(keypoints, len(keypoints), 0, len(keypoints))
    result = finisher.result([done], cloud, ["chair"], [item, turned], {"verify": 1.0})
    assert result.model_id == "chair" and result.alternatives == ()
    assert result.inlier_ratio == pytest.approx(done.fit.num_inliers / len(keypoints))
    assert [(c.model_id, c.score) for c in result.candidates] == [("chair", 0.8)]


def test_another_instance_is_stood_upright_by_the_category_fit(finisher, box_chair) -> None:
    points = box_chair.points * np.array([1.15, 1.0, 1.15])  # a wider chair of the same height
    keypoints, _ = voxel_downsample(transform(points, POSE), VOXEL)
    search = _search(finisher, keypoints)
    tilted = POSE @ make_pose(axis_angle(np.array([1.0, 0, 0]), np.radians(4.0)), 0)
    done = _finish(finisher, search, _posed(search, tilted, 0.5), [])
    pose = done.item.hypothesis.transform
    assert rotation_error_deg(pose[:3, :3], POSE[:3, :3]) < 1.0  # upright again


@pytest.mark.parametrize(("own", "expected"), [("chair", 0.12), ("table", 0.88)])
def test_a_category_with_its_own_calibrator_reads_its_models_answers_with_it(
    finisher, box_chair, own: str, expected: float
) -> None:
    """The answer for a chair reads the chairs' own calibrator where one is given, and the
    general one where only another category has its own."""
    leaf = Tree(
        feature=np.array([0]),
        threshold=np.array([0.0]),
        left=np.array([-1]),
        right=np.array([-1]),
        value=np.array([0.0]),
    )
    general = Calibrator(2.0, 0.1, (leaf,), card={})
    of_category = Calibrator(-2.0, 0.1, (leaf,), card={})
    finisher = replace(finisher, calibrator=general, calibrators={own: of_category})
    keypoints, _ = voxel_downsample(transform(box_chair.points, POSE), VOXEL)
    search = _search(finisher, keypoints)
    item = _posed(search, POSE, 0.8)

    done = _finish(finisher, search, item, [item])
    assert done.confidence == pytest.approx(expected, abs=0.01)
