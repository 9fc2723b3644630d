"""The early stops with the shipped weights and calibrator: a confident heading proposal
(``heading_mass``, with ``up``) or up proposal (``up_mass``, without) is searched alone, and an
answer found there that the calibrator doubts sends the query to the other proposals, where
the right pose is. The view is a library chair's own; proposed a quarter turn from the truth
alone, its answer is wrong and doubted (confidence 0.35 with ``up``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.features.orientation import OrientationProposer, Proposal
from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller, yaw_of
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg
from catalign.library.loaded import load
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine
from catalign.registration.prepare.frame import query_frame
from catalign.registration.results import RegistrationResult
from catalign.registration.stages.request import Request
from catalign.registration.stages.search import Search
from catalign.registration.stages.verify import Scored

UP = np.array([0.0, 0.0, 1.0])
# The chair of the default library seen (test_shipped_engine's views).
SEED = 1
# Without up, the scene is turned so that the chair's up is nowhere near +Z.
TURN = axis_angle(np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74]), 2.1)


class Proposing:
    """The shipped proposer, with the given ups or headings (and probability masses) instead
    of its own."""

    def __init__(
        self,
        proposer: OrientationProposer,
        ups: list[Proposal] | None = None,
        headings: list[Proposal] | None = None,
    ) -> None:
        self._proposer, self._ups, self._headings = proposer, ups, headings

    def ups(self, points: np.ndarray, count: int) -> list[Proposal]:
        return self._proposer.ups(points, count) if self._ups is None else self._ups[:count]

    def headings(self, levelled: list[np.ndarray], count: int) -> list[list[Proposal]]:
        if self._headings is None:
            return self._proposer.headings(levelled, count)
        return [self._headings[:count] for _ in levelled]


@dataclass(frozen=True)
class Stop:
    """One early stop: its option, whether the query has ``up``, how the proposals put a
    wrong one first (the proposer, given the shipped one, the chair's pose and how far off the
    first proposal is), and what a search counts as searched (a heading, or an up)."""

    option: str
    with_up: bool
    proposer: Callable[[OrientationProposer, np.ndarray, float], Proposing]
    searched: Callable[[Search], set[tuple[float, ...]]]


def _headings_first_off(shipped: OrientationProposer, pose: np.ndarray, off: float) -> Proposing:
    truth = yaw_of(leveller(pose[:3, :3] @ MODEL_UP) @ pose[:3, :3])
    first = Proposal(truth + np.radians(off), 0.97)
    return Proposing(shipped, headings=[first, Proposal(truth, 0.02)])


def _ups_first_off(shipped: OrientationProposer, pose: np.ndarray, off: float) -> Proposing:
    truth = pose[:3, :3] @ MODEL_UP
    side = np.cross(truth, [1.0, 0.0, 0.0])
    first = axis_angle(side / np.linalg.norm(side), np.radians(off)) @ truth
    return Proposing(shipped, ups=[Proposal(first, 0.9), Proposal(truth, 0.05)])


STOPS = {
    "heading": Stop(
        "heading_mass",
        True,
        _headings_first_off,
        lambda search: {(h,) for h in search.orientation.headings[: len(search.views)]},
    ),
    "up": Stop(
        "up_mass",
        False,
        _ups_first_off,
        lambda search: {tuple(np.round(search.orientation.up, 6))},
    ),
}


@pytest.fixture(scope="module")
def extractor() -> LearnedExtractor:
    return LearnedExtractor()


def own_view(with_up: bool) -> tuple[np.ndarray, np.ndarray]:
    """The chair's own view standing on a Z-up floor (none in view), turned by :data:`TURN`
    without ``up``, and its pose."""
    shape = procedural_shape(SEED)
    pose = make_pose(
        upright_rotation(0.7 + 1.3 * SEED), np.array([0.3, -0.2, -shape.points[:, 1].min()])
    )
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(SEED))
    if with_up:
        return points, pose
    return points @ TURN.T, make_pose(TURN, np.zeros(3)) @ pose


def registered(
    extractor: LearnedExtractor,
    monkeypatch: pytest.MonkeyPatch,
    stop: Stop,
    first_off_deg: float,
    **options: float | None,
) -> tuple[RegistrationResult, bool, int]:
    """The answer, whether it recovers the view (own model, 2 degrees, 1 cm) and how many
    headings or ups were searched, when the proposer puts one ``first_off_deg`` from the
    truth first, sure of it, and the true one second."""
    points, pose = own_view(stop.with_up)
    # The proposer works in the query's own frame: its proposals are put there.
    frame = query_frame(points, UP if stop.with_up else None)
    pose_there = make_pose(frame.rotation, -frame.rotation @ frame.centre) @ pose
    proposer = stop.proposer(extractor.orientation, pose_there, first_off_deg)
    monkeypatch.setattr(extractor, "orientation", proposer)
    library = load(DEFAULT_MODEL_DIR / "library", extractor.fingerprint)
    config = EngineConfig(**({"heading_mass": 0.95, stop.option: 0.5} | options))
    engine = Engine(extractor, library, config=config)
    searched: set[tuple[float, ...]] = set()
    search = engine.searcher.search

    def recorded(query: Search, request: Request) -> tuple[Search, list[Scored]]:
        searched.update(stop.searched(query))
        return search(query, request)

    monkeypatch.setattr(engine.searcher, "search", recorded)
    result = engine.register(points, up=UP if stop.with_up else None, seed=0)
    recovered = (
        result.model_id == procedural_shape(SEED).shape_id
        and rotation_error_deg(result.pose[:3, :3], pose[:3, :3]) < 2.0
        and float(np.linalg.norm(result.pose[:3, 3] - pose[:3, 3])) < 0.01
    )
    return result, recovered, len(searched)


@pytest.fixture(params=list(STOPS))
def stop(request: pytest.FixtureRequest) -> Stop:
    return STOPS[request.param]


def test_a_confident_right_proposal_is_searched_alone(extractor, monkeypatch, stop) -> None:
    result, recovered, searched = registered(extractor, monkeypatch, stop, 0.0)
    assert recovered and result.confidence >= EngineConfig().decision.heading_fallback
    assert searched == 1


# Doubt above the first answer's confidence: a network sure of a wrong heading also weighs the
# poses at that heading up (``heading_belief_power``), which makes their answer look surer.
DOUBT = {"heading_fallback": 0.95}


def test_a_doubted_answer_is_the_answer_of_every_proposal(extractor, monkeypatch, stop) -> None:
    result, recovered, searched = registered(extractor, monkeypatch, stop, 90.0, **DOUBT)
    assert recovered, f"not recovered after the fallback (confidence {result.confidence:.2f})"
    assert searched == 2  # the first proposal's work is kept, not done again
    every, _, _ = registered(extractor, monkeypatch, stop, 90.0, **DOUBT, **{stop.option: None})
    assert result.model_id == every.model_id
    np.testing.assert_allclose(result.pose, every.pose, atol=1e-9)
    assert result.confidence == pytest.approx(every.confidence)


def test_without_the_fallback_a_wrong_first_proposal_is_all_there_is(
    extractor, monkeypatch, stop
) -> None:
    result, recovered, searched = registered(
        extractor, monkeypatch, stop, 90.0, heading_fallback=0.0
    )
    assert searched == 1
    assert not recovered and result.confidence < DOUBT["heading_fallback"]
