"""The decision alone, on hand-made round results: which poses are refined, which answer wins,
how the alternatives are ordered and when a more confident one is promoted."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from catalign.geometry.se3 import axis_angle, make_pose
from catalign.registration.decision.confidence import Evidence
from catalign.registration.decision.rules import Finished, Found, Refined, Rules, decide
from catalign.registration.results import Orientation
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import NO_MATCHES, Hypothesis
from catalign.registration.stages.refine import Fit
from catalign.registration.stages.search import Search
from catalign.registration.stages.verify import Scored

UP = np.array([0.0, 0.0, 1.0])
RULES = Rules(
    refine=2,
    alternatives=2,
    sweep_refine=1,
    exact_fitness=0.9,
    sure_fitness=0.95,
    confidence_margin=0.2,
)
VIEW = QueryView(np.zeros((10, 3)), np.zeros((10, 4), dtype=np.float32))
SEARCH = Search(Orientation(UP, True, (0.0,)), [VIEW], np.arange(10), support_radius=0.05)
UPSIDE_DOWN = Search(Orientation(-UP, False, (0.0,)), [VIEW], np.arange(10), support_radius=0.05)


def _found(
    model_id: str,
    score: float,
    yaw_deg: float = 0.0,
    *,
    swept: bool = False,
    search: Search = SEARCH,
) -> Found:
    pose = make_pose(axis_angle(UP, np.radians(yaw_deg)), np.zeros(3))
    return Found(search, Scored(Hypothesis(model_id, pose, NO_MATCHES, VIEW, swept), score))


class Round:
    """A round's refinements and confidences made up by hand: each found pose refines to
    itself with the given fitness (and score, when given), and each finished answer gets the
    given confidence (by model id). Counts every refinement and finish."""

    def __init__(
        self,
        fitness: dict[str, float],
        confidence: dict[str, float] | None = None,
        refined_score: dict[str, float] | None = None,
    ) -> None:
        self.fitness, self.confidence = fitness, confidence or {}
        self.refined_score = refined_score or {}
        self.refined: list[Found] = []
        self.finished: list[tuple[str, bool]] = []

    def refine(self, item: Found) -> Refined:
        self.refined.append(item)
        model_id = item.scored.hypothesis.model_id
        score = self.refined_score.get(model_id, item.scored.score)
        fit = Fit(self.fitness.get(model_id, 0.3), 0.01, 100)
        return Refined(item, Scored(item.scored.hypothesis, score), (score, 1.0, 1.0), fit)

    def finish(self, refined: Refined, tried: Sequence[Scored], refit: bool) -> Finished:
        model_id = refined.scored.hypothesis.model_id
        self.finished.append((model_id, refit))
        evidence = Evidence(*([0.0] * 9), up_given=True, up_belief=1.0, keypoints=100)
        confidence = self.confidence.get(model_id)
        return Finished(refined.search, refined.scored, refined.fit, evidence, confidence)

    def decide(self, found: list[Found], rules: Rules = RULES):
        return decide(found, rules, refine=self.refine, finish=self.finish)


def _models(decision) -> list[str]:
    return [answer.item.hypothesis.model_id for answer in decision.answers]


def test_nothing_found_decides_nothing() -> None:
    assert Round({}).decide([]) is None


def test_the_best_matched_poses_and_one_per_further_answer_are_refined() -> None:
    found = [_found("a", 0.9), _found("a", 0.8, 2.0), _found("a", 0.7, 4.0), _found("b", 0.6)]
    found += [_found("c", 0.5), _found("d", 0.4)]
    round_ = Round({})
    decision = round_.decide(found)
    refined = [item.scored.score for item in round_.refined]
    assert refined == [0.9, 0.8, 0.6, 0.5]  # the 2 best, then b and c (3 answers in all)
    assert _models(decision) == ["a", "b", "c"]
    # the tried poses: every refined one and the matched ones that were not refined
    assert sorted(s.score for s in decision.tried) == [0.4, 0.5, 0.6, 0.7, 0.8, 0.9]


def test_a_sure_exact_fit_wins_over_a_better_scored_loose_one() -> None:
    found = [_found("twin", 0.9), _found("own", 0.5), _found("other", 0.4)]
    decision = Round({"twin": 0.5, "own": 0.97}).decide(found)
    assert _models(decision)[0] == "own"
    assert _models(decision)[1:] == ["twin", "other"]


def test_a_sure_fit_beats_one_that_fits_only_exactly() -> None:
    found = [_found("turned", 0.9), _found("right", 0.5)]
    decision = Round({"turned": 0.92, "right": 0.97}).decide(found)
    assert _models(decision)[0] == "right"


def test_with_a_fit_margin_the_closest_sure_fit_beats_a_better_scored_twin() -> None:
    found = [_found("twin", 0.9), _found("own", 0.5), _found("other", 0.4)]
    fitness = {"twin": 0.96, "own": 0.995, "other": 0.985}
    assert _models(Round(fitness).decide(found))[0] == "twin"  # no margin: the score decides
    margin = Rules(**{**vars(RULES), "fit_margin": 0.02})
    assert _models(Round(fitness).decide(found, margin))[0] == "own"
    # within the margin of the closest fit the score decides again
    assert _models(Round({**fitness, "twin": 0.98}).decide(found, margin))[0] == "twin"


def test_swept_poses_are_refined_only_when_no_fit_is_sure_and_kept_only_if_exact() -> None:
    """The best distinct swept answer (one: ``sweep_refine``) and the best swept pose under
    each further orientation are refined when no refined pose fits surely."""
    found = [_found("a", 0.9), _found("own", 0.95, swept=True), _found("c", 0.5, swept=True)]
    found += [_found("b", 0.3, swept=True, search=UPSIDE_DOWN)]
    round_ = Round({"a": 0.6, "own": 0.93, "b": 0.4})
    decision = round_.decide(found)
    assert [item.scored.hypothesis.model_id for item in round_.refined] == ["a", "own", "b"]
    assert _models(decision) == ["own", "a"]  # b fits loosely once refined: dropped

    sure = Round({"a": 0.97, "own": 0.93})
    assert _models(sure.decide(found[:2])) == ["a"]
    assert all(not item.swept for item in sure.refined)


def test_a_clearly_more_confident_alternative_is_promoted_after_its_own_refit() -> None:
    found = [_found("a", 0.9), _found("b", 0.8)]
    round_ = Round({}, confidence={"a": 0.4, "b": 0.7})
    decision = round_.decide(found)
    assert _models(decision) == ["b", "a"]
    # the winner and the alternative finished once each, then the challenger as a winner
    assert round_.finished == [("a", True), ("b", False), ("b", True)]
    assert decision.winner.confidence == 0.7


@pytest.mark.parametrize(
    ("confidence", "fitness", "winner"),
    [
        ({"a": 0.4, "b": 0.55}, {}, "a"),  # ahead by less than the margin: a near tie
        ({"a": 0.4, "b": 0.9}, {"a": 0.92}, "a"),  # the winner fits exactly: it stays
    ],
)
def test_the_winner_keeps_its_place(
    confidence: dict[str, float], fitness: dict[str, float], winner: str
) -> None:
    decision = Round(fitness, confidence=confidence).decide([_found("a", 0.9), _found("b", 0.8)])
    assert _models(decision)[0] == winner


def test_near_ties_and_a_symmetric_turn_are_ordered_stably() -> None:
    """Equal scores keep the order they were found in, and a model turned a half way round is
    a distinct answer of its own, after its better-scored twin pose."""
    found = [_found("a", 0.5), _found("b", 0.5), _found("a", 0.5, 180.0), _found("c", 0.5)]
    for _ in range(3):
        decision = Round({}).decide(found)
        assert [(a.item.hypothesis.model_id, _yaw_deg(a)) for a in decision.answers] == [
            ("a", 0),
            ("b", 0),
            ("a", 180),
        ]


def _yaw_deg(answer: Finished) -> int:
    return round(float(np.degrees(np.arccos(answer.item.hypothesis.transform[0, 0]))))
