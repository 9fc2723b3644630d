"""Verification: scoring pose hypotheses by the surfaces they put together, not by their votes.

Every pose is scored by how much of the query it lays onto the candidate's surface
(:class:`~catalign.registration.stages.surface_checks.SurfaceCheck`, cheap: every pose gets it),
and the ``verify_top`` best also by how much of that surface inside the observed region the query
covers (:class:`~catalign.registration.stages.surface_checks.CoverageCheck`). Their product tells a
chair's front from its side where inlier counts cannot. With ``up``, a layout factor
(:class:`~catalign.registration.stages.surface_checks.LayoutCheck`: does the query's top lean the
way the posed model's does) nudges it, which tells the front from the back of another instance. The
checks themselves live in :mod:`~catalign.registration.stages.surface_checks`; this module applies
them to hypotheses, with the per-model pieces (surface grid, coverage sample, top offset) cached.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field

import numpy as np

from catalign.frames import MODEL_UP
from catalign.library.loaded import Library
from catalign.registration.results import Candidate
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.model_cache import ModelCache
from catalign.registration.stages.surface_checks import (
    CoverageCheck,
    LayoutCheck,
    SurfaceCheck,
    top_offset,
)


@dataclass(frozen=True)
class QueryChecks:
    """The query's side of verification: the probe points the surface check carries onto each
    model, the coverage check of the observed region, and the layout check (None without
    ``up``)."""

    probes: np.ndarray
    coverage: CoverageCheck
    layout: LayoutCheck | None


@dataclass(frozen=True, eq=False)
class Scored:
    """A hypothesis and its verification score (higher is better)."""

    hypothesis: Hypothesis
    score: float


def surface_sample(points: np.ndarray, count: int) -> np.ndarray:
    """About ``count`` of a model's surface ``points`` (every n-th, float64): the coverage
    check's sample, and the model's extent where a stage needs it cheaply."""
    step = max(1, len(points) // count)
    return points[::step].astype(np.float64)


@dataclass(eq=False)
class Verifier:
    """Scores poses against ``library`` models, with each model's checks cached
    (``model_cache`` models at most).

    ``distance`` is the inlier distance (metres) of every check, ``coverage_points`` the model
    surface points the coverage check poses, ``verify_top`` the poses (best by the surface
    check) that get the full score in :meth:`rank`, ``cell`` the edge (metres) of the query's
    coverage grid.
    """

    library: Library
    _: KW_ONLY
    distance: float
    coverage_points: int
    verify_top: int
    cell: float
    model_cache: int | None = None
    _checks: ModelCache[tuple[SurfaceCheck, np.ndarray]] = field(init=False, repr=False)
    _top_offsets: dict[str, np.ndarray] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self._checks = ModelCache(self.model_cache)

    def query_checks(
        self, keypoints: np.ndarray, probes: np.ndarray, turn: np.ndarray | None
    ) -> QueryChecks:
        """The query's side of the checks: ``probes`` are rows of its ``keypoints``; ``turn``
        is the levelling turn when ``up`` is known (its second row is ``up``)."""
        return QueryChecks(
            probes=keypoints[probes],
            coverage=CoverageCheck(keypoints, margin=self.distance, cell=self.cell),
            layout=None if turn is None else LayoutCheck(keypoints, turn[1]),
        )

    def rank(self, hypotheses: list[Hypothesis], query: QueryChecks) -> list[Scored]:
        """The ``verify_top`` poses that explain most of the query, fully scored, best first."""
        explained = self.explained(hypotheses, query.probes)
        best_first = np.argsort(explained, kind="stable")[::-1][: self.verify_top]
        best = [hypotheses[i] for i in best_first]
        covered, leaning = self._covered_and_leaning(best, query)
        scores = explained[best_first] * covered * leaning
        scored = [Scored(h, float(s)) for h, s in zip(best, scores, strict=True)]
        scored.sort(key=lambda item: -item.score)
        return scored

    def score(self, hypothesis: Hypothesis, query: QueryChecks) -> Scored:
        """One pose, fully scored."""
        return Scored(hypothesis, float(np.prod(self.parts(hypothesis, query))))

    def parts(self, hypothesis: Hypothesis, query: QueryChecks) -> tuple[float, float, float]:
        """The three factors of one pose's score: the share of the query it explains, the
        share of the model surface in the observed region that the query covers, and the
        layout factor (1 without ``up``)."""
        explained = self.explained([hypothesis], query.probes)[0]
        covered, leaning = self._covered_and_leaning([hypothesis], query)
        return float(explained), float(covered[0]), float(leaning[0])

    def explained(self, hypotheses: list[Hypothesis], probes: np.ndarray) -> np.ndarray:
        """The share of the query each pose lays onto its model (:class:`SurfaceCheck`), one
        surface query per model."""
        explained = np.zeros(len(hypotheses))
        for model_id, rows, poses in _by_model(hypotheses):
            surface, _ = self._checks_of(model_id)
            explained[rows] = surface.explained(probes, poses, self.distance)
        return explained

    def _covered_and_leaning(
        self, hypotheses: list[Hypothesis], query: QueryChecks
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each pose's covered share (:class:`CoverageCheck`) and layout factor (1 without
        ``up``), one batch per model: the factors :meth:`explained` is multiplied by."""
        covered, leaning = np.zeros(len(hypotheses)), np.ones(len(hypotheses))
        for model_id, rows, poses in _by_model(hypotheses):
            _, sample = self._checks_of(model_id)
            covered[rows] = query.coverage.covered(sample, poses, self.distance)
            if query.layout is not None:
                leaning[rows] = query.layout.factor(self._top_offset_of(model_id), poses)
        return covered, leaning

    def _top_offset_of(self, model_id: str) -> np.ndarray:
        """Where the model's top leans from its middle, in its own frame (cached)."""
        if model_id not in self._top_offsets:
            points = self.library[model_id].points.astype(np.float64)
            self._top_offsets[model_id] = top_offset(points, MODEL_UP)
        return self._top_offsets[model_id]

    def _checks_of(self, model_id: str) -> tuple[SurfaceCheck, np.ndarray]:
        """The model's surface check and its sample for the coverage check (cached)."""
        model = self.library[model_id]
        return self._checks.get(
            model_id,
            lambda: (SurfaceCheck(model.grid), surface_sample(model.points, self.coverage_points)),
        )


def _by_model(hypotheses: list[Hypothesis]) -> list[tuple[str, list[int], np.ndarray]]:
    """``(model id, rows of hypotheses, their stacked poses)`` for each model among them."""
    rows: dict[str, list[int]] = {}
    for i, hypothesis in enumerate(hypotheses):
        rows.setdefault(hypothesis.model_id, []).append(i)
    return [
        (model_id, found, np.stack([hypotheses[i].transform for i in found]))
        for model_id, found in rows.items()
    ]


def best_per_model(model_ids: list[str], scored: list[Scored]) -> list[Candidate]:
    """Each of ``model_ids`` once, with its best score among ``scored`` (0 when none of its
    poses is there), best first: the candidates of the answer."""
    best = dict.fromkeys(model_ids, 0.0)
    for item in scored:
        model_id = item.hypothesis.model_id
        best[model_id] = max(item.score, best[model_id])
    return sorted((Candidate(i, s) for i, s in best.items()), key=lambda c: -c.score)
