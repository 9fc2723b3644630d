"""Distinct answers and pose transfer: poses grouped by what they claim, and carried between
models that share the canonical frame."""

from __future__ import annotations

import numpy as np

from catalign.geometry.levelling import yaw_rotations
from catalign.geometry.se3 import make_pose
from catalign.geometry.symmetry import YawSymmetry
from catalign.registration.decision.answers import (
    best_other,
    category_share,
    distinct,
    promoted,
    same_answer,
)
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.verify import Scored


def _yaw(degrees: float) -> np.ndarray:
    angle = np.radians(degrees)
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _scored(model_id: str, yaw_deg: float, score: float, shift: float = 0.0) -> Scored:
    pose = make_pose(_yaw(yaw_deg), np.array([shift, 0.0, 0.0]))
    return Scored(Hypothesis(model_id, pose, np.zeros((0, 2), dtype=np.int64), None), score)


def test_the_same_model_at_nearly_the_same_turn_is_one_answer() -> None:
    assert same_answer(_scored("a", 0, 0.5), _scored("a", 25, 0.4, shift=0.05))
    assert not same_answer(_scored("a", 0, 0.5), _scored("a", 35, 0.4))
    assert not same_answer(_scored("a", 0, 0.5), _scored("b", 0, 0.4))


def test_distinct_keeps_the_best_of_each_answer_in_order() -> None:
    ranked = [
        _scored("a", 0, 0.9),
        _scored("a", 10, 0.8),  # the same answer as the first
        _scored("a", 180, 0.7),  # a half turn: another answer
        _scored("b", 0, 0.6),
        _scored("a", 175, 0.5),  # the half turn again
        _scored("c", 90, 0.4),
    ]
    kept = distinct(ranked, 10)
    assert [(k.hypothesis.model_id, k.score) for k in kept] == [
        ("a", 0.9),
        ("a", 0.7),
        ("b", 0.6),
        ("c", 0.4),
    ]
    assert distinct(ranked, 2) == kept[:2]
    pairs = [("x", item) for item in ranked]
    assert [p[1] for p in distinct(pairs, 10, lambda pair: pair[1])] == kept


def test_best_other_separates_other_headings_from_other_models() -> None:
    ranked = [_scored("a", 0, 0.9), _scored("a", 5, 0.85), _scored("a", 180, 0.6)]
    ranked += [_scored("b", 0, 0.7)]
    answer = ranked[0]
    assert best_other(ranked, answer, same_model=True) == 0.6  # the 5-degree pose is the same
    assert best_other(ranked, answer, same_model=False) == 0.7
    assert best_other(ranked[:2], answer, same_model=True) == 0.0


def test_a_clearly_more_confident_alternative_is_promoted() -> None:
    assert promoted([0.4, 0.3, 0.55, 0.52], margin=0.1) == 2  # the most confident one
    assert promoted([0.4, 0.3, 0.48, 0.2], margin=0.1) == 0  # only just ahead: a near tie
    assert promoted([0.9, 0.95], margin=0.0) == 1
    assert promoted([0.4, 0.9], margin=None) == 0  # the option is off
    assert promoted([0.4, None], margin=0.1) == 0  # no calibrator, no confidences
    assert promoted([0.7], margin=0.1) == 0


def _turned(model_id: str, turn_deg: float, score: float) -> Scored:
    """A pose of ``model_id`` turned by ``turn_deg`` about the model's up (+Y) before a fixed
    placement in the observation."""
    placement = _yaw(30.0)  # the observation's frame differs from the model's
    pose = make_pose(placement @ yaw_rotations(np.radians([turn_deg]))[0], np.zeros(3))
    return Scored(Hypothesis(model_id, pose, np.zeros((0, 2), dtype=np.int64), None), score)


def test_a_symmetric_turn_of_the_same_model_is_the_same_answer() -> None:
    symmetries = {"table": YawSymmetry(2), "square": YawSymmetry(4), "round": YawSymmetry(0)}
    symmetry_of = symmetries.get
    assert same_answer(_turned("table", 0, 0.9), _turned("table", 178, 0.8), symmetry_of)
    assert not same_answer(_turned("table", 0, 0.9), _turned("table", 90, 0.8), symmetry_of)
    assert same_answer(_turned("square", 0, 0.9), _turned("square", 92, 0.8), symmetry_of)
    assert same_answer(_turned("round", 0, 0.9), _turned("round", 133, 0.8), symmetry_of)
    assert not same_answer(_turned("table", 0, 0.9), _turned("table", 180, 0.8))  # no symmetry
    ranked = [_turned("table", 0, 0.9), _turned("table", 180, 0.85), _turned("round", 0, 0.5)]
    ranked += [_turned("round", 90, 0.4)]
    assert [k.score for k in distinct(ranked, 10, symmetry_of=symmetry_of)] == [0.9, 0.5]
    # The half turn of a rectangular table is no other heading: it leaves no heading margin.
    assert best_other(ranked, ranked[0], same_model=True, symmetry_of=symmetry_of) == 0.0
    assert best_other(ranked, ranked[0], same_model=True) == 0.85


def test_the_category_confidence_is_the_share_of_confidence_on_the_winners_category() -> None:
    assert category_share([("table", 0.6), ("table", 0.2), ("chair", 0.2)]) == 0.8
    assert category_share([("chair", 0.9)]) == 1.0  # nothing else came close
    assert category_share([("chair", 0.3), ("table", None)]) is None  # no calibrator
    assert category_share([("chair", 0.0), ("table", 0.0)]) is None
    assert category_share([]) is None
