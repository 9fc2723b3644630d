"""The query as the engine searches it: one :class:`Search` per orientation (its views at each
heading, the key points and probe rows verification uses, its shortlist and checks once
searched), and the :class:`StageClock` that times the engine's steps and checks its deadline.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import cached_property
from typing import TypeVar

import numpy as np

from catalign.deadline import Deadline
from catalign.features.orientation import HEADING_DISTINCT_DEG
from catalign.geometry.levelling import yaw_of
from catalign.registration.results import Orientation
from catalign.registration.stages.category_fit import supported
from catalign.registration.stages.describe import QueryView, turn_of
from catalign.registration.stages.match import probe_rows
from catalign.registration.stages.verify import QueryChecks, Scored

T = TypeVar("T")
# A pose at a heading the heading network all but rules out keeps this much belief.
HEADING_BELIEF_FLOOR = 0.01


@dataclass(frozen=True, eq=False)
class Search:
    """The query under one orientation: its views (one per heading), the key points and probe
    rows that verification uses, and, once searched (a new :class:`Search`, from
    :meth:`searched`), its shortlist and the query's side of verification. Its ``solid`` key
    points are those with two neighbours within ``support_radius`` (metres)."""

    orientation: Orientation
    views: list[QueryView]
    probes: np.ndarray
    support_radius: float
    candidates: tuple[str, ...] = ()
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

    def searched(self, candidates: list[str], checks: QueryChecks) -> Search:
        """This search with its shortlist and checks."""
        return replace(self, candidates=tuple(candidates), checks=checks)

    def widened(self, orientation: Orientation, views: list[QueryView]) -> Search:
        """This search at more headings of its up (``orientation``), ``views`` added after
        its own: its probes and checks are kept, its shortlist is made again."""
        return replace(self, orientation=orientation, views=self.views + views, candidates=())

    def weighed(self, item: Scored, up_power: float, heading_power: float) -> Scored:
        """A verified pose found under this search's orientation, its score weighed by the
        belief in that orientation's up to ``up_power`` (verification alone prefers an
        upside-down chair too often) and by the heading network's belief in its heading to
        ``heading_power`` (verification alone turns another instance a quarter or half turn
        too often)."""
        orientation, turn = self.orientation, self.turn
        weight = orientation.belief**up_power
        if heading_power and turn is not None:
            yaw = yaw_of(turn @ item.hypothesis.transform[:3, :3])
            heading = orientation.heading_belief(yaw, HEADING_DISTINCT_DEG / 2)
            weight *= max(heading, HEADING_BELIEF_FLOOR) ** heading_power
        return Scored(item.hypothesis, item.score * weight)


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
