"""Distinct answers: verified poses grouped into the different things they claim.

Many verified poses say the same thing (one model, one heading, a few millimetres apart); the
refinement budget and the answer's ``alternatives`` are spent on poses that say something
different: another model, or the same model turned by more than :data:`DISTINCT_TURN_DEG`
(a quarter or half turn of a nearly symmetric chair), unless the model maps onto itself under
that turn (a rectangular table turned half way round is the same answer: ``symmetry_of``).
Among the finished answers, the one returned is the winner of the scores unless another is
clearly more likely right (:func:`promoted`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np

from catalign.geometry.se3 import split_scale
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry
from catalign.registration.stages.verify import Scored

# Two poses of one model turned further apart than this are different answers.
DISTINCT_TURN_DEG = 30.0

Item = TypeVar("Item")
SymmetryOf = Callable[[str], YawSymmetry]


def no_symmetry(model_id: str) -> YawSymmetry:
    """The symmetry of a model when none is known: none."""
    return NO_SYMMETRY


def same_answer(a: Scored, b: Scored, symmetry_of: SymmetryOf = no_symmetry) -> bool:
    """Whether two poses claim the same model at nearly the same orientation, up to a turn
    under which the model (``symmetry_of`` its id) looks the same."""
    model_id = a.hypothesis.model_id
    if model_id != b.hypothesis.model_id:
        return False
    rotation_a = split_scale(a.hypothesis.transform)[0][:3, :3]
    rotation_b = split_scale(b.hypothesis.transform)[0][:3, :3]
    return symmetry_of(model_id).rotation_error_deg(rotation_a, rotation_b) <= DISTINCT_TURN_DEG


def distinct(
    ranked: Sequence[Item],
    limit: int,
    scored: Callable[[Item], Scored] = lambda item: item,
    symmetry_of: SymmetryOf = no_symmetry,
) -> list[Item]:
    """The first ``limit`` items of ``ranked`` (best first) whose poses are distinct answers:
    each item is kept unless an earlier kept one claims the same answer. ``scored`` gives an
    item's :class:`Scored`."""
    kept: list[Item] = []
    for item in ranked:
        if len(kept) == limit:
            break
        if not any(same_answer(scored(item), scored(other), symmetry_of) for other in kept):
            kept.append(item)
    return kept


def best_other(
    ranked: Sequence[Scored],
    answer: Scored,
    *,
    same_model: bool,
    symmetry_of: SymmetryOf = no_symmetry,
) -> float:
    """The best score in ``ranked`` of a pose that is a different answer from ``answer``:
    of the same model turned another way (``same_model``; a symmetric turn is no other way),
    or of another model; 0 when there is none."""
    scores = [
        item.score
        for item in ranked
        if (item.hypothesis.model_id == answer.hypothesis.model_id) == same_model
        and not same_answer(item, answer, symmetry_of)
    ]
    return float(np.max(scores)) if scores else 0.0


def category_share(answers: Sequence[tuple[str, float | None]]) -> float | None:
    """The share of the finished answers' confidence that falls on the winner's category
    (``answers``: each one's category and confidence, the winner first): near 1 when every
    answer that is believed at all is of that category, lower when another category's model
    came close. None without a confidence for each (no calibrator) or with none above 0."""
    if not answers or any(confidence is None for _, confidence in answers):
        return None
    total = sum(float(confidence or 0.0) for _, confidence in answers)
    if total <= 0.0:
        return None
    chosen = answers[0][0]
    return sum(float(c or 0.0) for category, c in answers if category == chosen) / total


def promoted(confidences: Sequence[float | None], margin: float | None) -> int:
    """Which of the finished answers (the winner of the scores first) to return: the most
    confident one when its confidence beats the winner's by more than ``margin``, else the
    winner (0), as without ``margin`` or without a confidence for each. The confidence is
    calibrated on evidence the score does not weigh (margins, fit, span, the belief in the
    up), so it judges better between distinct answers; the margin keeps the winner when they
    are nearly tied."""
    if margin is None or not confidences or any(c is None for c in confidences):
        return 0
    best = int(np.argmax(confidences))
    return best if confidences[best] > confidences[0] + margin else 0
