"""The query as the engine searches it: one :class:`Search` per orientation (its views at each
heading, the key points and probe rows verification uses, its shortlist and checks once
searched), the :class:`Request` that holds one call's options and what its search rounds
share, and the :class:`StageClock` that times the engine's steps and checks its deadline.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from typing import TypeVar

import numpy as np

from catalign.deadline import Deadline
from catalign.registration.base import Orientation
from catalign.registration.category_fit import supported
from catalign.registration.describe import QueryView, turn_of
from catalign.registration.hypothesise import Hypothesis
from catalign.registration.match import probe_rows
from catalign.registration.verify import QueryChecks, Scored

T = TypeVar("T")


@dataclass(eq=False)
class Search:
    """The query under one orientation: its views (one per heading), the key points and probe
    rows that verification uses, and, once searched, its shortlist and checks. Its ``solid``
    key points are those with two neighbours within ``support_radius`` (metres)."""

    orientation: Orientation
    views: list[QueryView]
    probes: np.ndarray
    support_radius: float
    candidates: list[str] = field(default_factory=list)
    checks: QueryChecks | None = None

    @property
    def keypoints(self) -> np.ndarray:
        return self.views[0].keypoints

    @cached_property
    def solid(self) -> np.ndarray:
        """The key points that count in the observed extent (stray points would stretch it)."""
        return supported(self.keypoints, self.support_radius)

    @cached_property
    def turn(self) -> np.ndarray | None:
        return turn_of(self.orientation)


def query_searches(
    orientations: list[Orientation],
    views: list[QueryView],
    probe_points: int,
    seed: int,
    *,
    support_radius: float,
) -> list[Search]:
    """``views`` (in the order of the orientations' rotations) split by orientation."""
    searches, first = [], 0
    for orientation in orientations:
        mine = views[first : first + len(orientation.headings)]
        first += len(orientation.headings)
        probes = probe_rows(len(mine[0].keypoints), probe_points, seed)
        searches.append(Search(orientation, mine, probes, support_radius))
    return searches


@dataclass(eq=False)
class Request:
    """One call of the engine: its shortlist size ``k`` (None: every model), whether it
    estimates scale, its seed and clock, and what a second search round (more headings of the
    same orientations) takes over from the first: each model's poses at each view (by the
    view's id: the searches hold their views for the whole call), each pose's refinement (by
    the pose's id; the entry keeps the pose alive) and the share of the query it fits, all
    deterministic."""

    k: int | None
    estimate_scale: bool
    seed: int
    clock: StageClock
    poses: dict[tuple[str, int], list[Hypothesis]] = field(default_factory=dict)
    refined: dict[int, tuple[Hypothesis, Scored]] = field(default_factory=dict)
    fitness: dict[int, float] = field(default_factory=dict)


class StageClock:
    """The steps' timings (milliseconds; a step may add to an earlier step's name) and the
    deadline, checked before every step and between the items of a loop."""

    def __init__(self, deadline: Deadline | None) -> None:
        self.timings: dict[str, float] = {}
        self.check: Callable[[], None] = (lambda: None) if deadline is None else deadline.check

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        self.check()
        started = time.perf_counter()
        yield
        elapsed = (time.perf_counter() - started) * 1e3
        self.timings[stage] = self.timings.get(stage, 0.0) + elapsed

    def each(self, items: Iterable[T]) -> Iterator[T]:
        """``items``, with the deadline checked before each."""
        for item in items:
            self.check()
            yield item
