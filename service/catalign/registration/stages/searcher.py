"""The search under one orientation: shortlist, match, hypothesise, sweep and verify.

For one :class:`~catalign.registration.stages.search.Search` (the query levelled by one up and
described at its headings), the ``top_k`` models most like the query are shortlisted; the
headings the leading candidates agree with are kept and every candidate is matched there; poses
come from the matches (the two-point search with an up, the three-point RANSAC otherwise) and,
with an up, from the leading candidates' surfaces alone (the sweep); every pose is verified and
its score weighed by the beliefs in the orientation's up and in its heading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.features.retrieval import RetrievalHead
from catalign.library.loaded import Library
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis, Hypothesiser
from catalign.registration.stages.match import Matcher
from catalign.registration.stages.request import Request
from catalign.registration.stages.search import Search
from catalign.registration.stages.shortlist import shortlist
from catalign.registration.stages.sweep import Sweeper
from catalign.registration.stages.verify import Scored, Verifier


@dataclass(eq=False, kw_only=True)
class Searcher:
    """The stages of one orientation's search over ``library`` (module docstring), with the
    options the engine's configuration names: ``heading_models`` (the best shortlisted models
    the headings are chosen on), ``up_belief_power``, ``heading_belief_power``,
    ``index_from`` and ``index_candidates`` (when the shortlist reads the library's index),
    ``fit_from``, ``fit_candidates`` and ``fit_weight`` (its re-ranking by outlines); and
    the extractor's ``retrieval`` encoders that describe the query for the shortlist (None:
    its pooled features)."""

    library: Library
    matcher: Matcher
    hypothesiser: Hypothesiser
    sweeper: Sweeper
    verifier: Verifier
    heading_models: int
    up_belief_power: float
    heading_belief_power: float
    index_from: int | None
    index_candidates: int
    fit_from: int | None = None
    fit_candidates: int | None = None
    fit_weight: float = 0.0
    retrieval: RetrievalHead | None = None

    def search(self, search: Search, request: Request) -> tuple[Search, list[Scored]]:
        """The query searched under one orientation: the search with its shortlist and checks,
        and its verified poses, best first, weighed by the beliefs in the orientation."""
        turn, seed, clock = search.turn, request.seed, request.clock
        with clock("shortlist"):
            candidates = shortlist(
                self.library,
                search.views,
                request.k,
                turn,
                request.rows,
                self.retrieval,
                request.category,
                self.index_from,
                self.index_candidates,
                self.fit_from,
                self.fit_candidates,
                self.fit_weight,
            )

        # Match: keep the headings the leading candidates agree with, match every candidate
        # there, and hypothesise poses from each candidate's matches at each kept heading.
        with clock("match_ransac"):
            leading = candidates[: self.heading_models]
            views = self.matcher.choose_headings(leading, search.views, search.probes, turn, seed)
            hypotheses = [
                pose
                for model_id in clock.each(candidates)
                for view in views
                for pose in request.cache.poses_of(
                    model_id, view, lambda m=model_id, v=view: self._posed(m, v, turn, request)
                )
            ]

        # Sweep: with an up, the leading candidates also posed from their surfaces alone, at
        # yaws around the proposed headings (every yaw when none was proposed).
        with clock("sweep"):
            swept = []
            if turn is not None and not request.estimate_scale:
                orientation = search.orientation
                swept = self.sweeper.poses(
                    candidates,
                    search.keypoints[search.probes],
                    turn,
                    orientation.headings if orientation.headings_proposed else (),
                    search.views[0],
                )

        # Verify: every pose by the query it explains, the best also by coverage and layout
        # (the swept poses apart: they explain the most by design, and would crowd the matched
        # ones out).
        with clock("verify"):
            checks = search.checks or self.verifier.query_checks(
                search.keypoints, search.probes, turn
            )
            search = search.searched(candidates, checks)
            ranked = self.verifier.rank(hypotheses, checks) + self.verifier.rank(swept, checks)
            ranked.sort(key=lambda item: -item.score)
            return search, [self.weighed(search, item) for item in ranked]

    def weighed(self, search: Search, item: Scored) -> Scored:
        """``item``'s score weighed by the beliefs in ``search``'s orientation."""
        return search.weighed(item, self.up_belief_power, self.heading_belief_power)

    def _posed(
        self, model_id: str, view: QueryView, turn: np.ndarray | None, request: Request
    ) -> list[Hypothesis]:
        """The poses of a model from its matches with the query at one heading."""
        found = self.matcher.match(model_id, view, request.seed)
        return self.hypothesiser.poses(
            found, turn, estimate_scale=request.estimate_scale, seed=request.seed
        )
