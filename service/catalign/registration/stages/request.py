"""One call of the engine: its options, its clock, and the :class:`RequestCache` its search
rounds share.

A query may be searched in more than one round (more headings, more ups, a floor kept): the
later rounds keep the earlier ones' views, so they meet the same model at the same view, the
same poses and the same answers again. The cache makes each of those computed once per call:
a model's poses at a view, a pose's refinement with its score and fit, an answer's category
fit. Its keys are the objects themselves (views and poses compare by identity), which the
cache holds for the whole call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import Fit
from catalign.registration.stages.search import StageClock
from catalign.registration.stages.verify import Scored

K = TypeVar("K")
V = TypeVar("V")


@dataclass(frozen=True, eq=False)
class RefinedPose:
    """A pose after ICP: scored again (weighed), the factors of its score, and its fit."""

    scored: Scored
    parts: tuple[float, float, float]
    fit: Fit


@dataclass(eq=False)
class RequestCache:
    """What one call computes once: each model's poses at each view, each pose's refinement,
    and each answer's category fit (with or without the refit at the observed size)."""

    poses: dict[tuple[str, QueryView], list[Hypothesis]] = field(default_factory=dict)
    refined: dict[Hypothesis, RefinedPose] = field(default_factory=dict)
    fitted: dict[tuple[Hypothesis, bool], tuple[Hypothesis, Fit]] = field(default_factory=dict)

    def poses_of(
        self, model_id: str, view: QueryView, make: Callable[[], list[Hypothesis]]
    ) -> list[Hypothesis]:
        return _once(self.poses, (model_id, view), make)

    def refined_pose(self, pose: Hypothesis, make: Callable[[], RefinedPose]) -> RefinedPose:
        return _once(self.refined, pose, make)

    def category_fit(
        self, pose: Hypothesis, refit: bool, make: Callable[[], tuple[Hypothesis, Fit]]
    ) -> tuple[Hypothesis, Fit]:
        return _once(self.fitted, (pose, refit), make)


@dataclass(frozen=True, eq=False)
class Request:
    """One call's shortlist size ``k`` (None: every model), whether it estimates scale, its
    seed, its clock, the library rows it may answer with and their ``category`` (None: every
    model) and its cache."""

    k: int | None
    estimate_scale: bool
    seed: int
    clock: StageClock
    rows: np.ndarray | None = None
    category: str | None = None
    cache: RequestCache = field(default_factory=RequestCache)


def _once(memo: dict[K, V], key: K, make: Callable[[], V]) -> V:
    """``memo[key]``, made by ``make()`` the first time."""
    if key not in memo:
        memo[key] = make()
    return memo[key]
