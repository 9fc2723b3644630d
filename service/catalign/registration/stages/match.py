"""Matching: which query and model key points are compared, at which headings, and how.

Matching cost grows with the product of query and model key points, the pose found barely
does, so both sides take part through fixed random subsets: at most ``match_points`` of the
query's key points (the same rows for every candidate) and at most ``model_points`` of each
model's (drawn once per model and cached, as :class:`Matchable`). Correspondences are mutual
feature nearest neighbours (:func:`~catalign.registration.stages.nearest.mutual_nearest`).

Of the headings the query was described at, only the ``keep_headings`` whose features agree
best with the leading candidates' are matched in full. Library models share the category's
canonical orientation, so the heading at which the query looks canonical is one for all of
them: it is chosen once, on the best shortlisted models, instead of once per candidate.
Agreement is the number of mutual nearest neighbours among the probe key points
(:func:`probe_rows`); with ``up``, only those that one upright pose explains (a quick
two-point search per model), because at a wrong heading a symmetric part (a seat, four legs)
still collects mutual matches, just not geometrically consistent ones.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field

import numpy as np

from catalign.library.loaded import Library
from catalign.library.quantise import stored_rows
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.gravity import yaw_ransac
from catalign.registration.stages.model_cache import ModelCache
from catalign.registration.stages.nearest import mutual_count, mutual_nearest


@dataclass(frozen=True)
class Matchable:
    """The part of a model that takes part in matching: rows of its key points, and their
    features and positions."""

    rows: np.ndarray
    features: np.ndarray
    keypoints: np.ndarray


@dataclass(frozen=True)
class Matches:
    """The correspondences of one candidate at one heading: ``pairs`` (M,2) holds rows of the
    view's key points and of the library entry's, ``model_points`` (M,3) the latter's
    positions (model frame)."""

    model_id: str
    view: QueryView
    pairs: np.ndarray
    model_points: np.ndarray

    @property
    def observed(self) -> np.ndarray:
        """The matched query key points (M,3), in the observation frame."""
        return self.view.keypoints[self.pairs[:, 0]]


def probe_rows(count: int, probe_points: int, seed: int) -> np.ndarray:
    """A fixed random selection of at most ``probe_points`` of ``count`` query key points, in
    random order: the probes that rank headings here and poses in verification."""
    return np.random.default_rng(seed).permutation(count)[:probe_points]


def query_subset(count: int, match_points: int | None, seed: int) -> np.ndarray:
    """Which of ``count`` query key points take part in matching: at most ``match_points``
    (None: all), a fixed random subset in ascending order."""
    if match_points is None or count <= match_points:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).permutation(count)[:match_points])


def model_subset(
    keypoints: np.ndarray, features: np.ndarray, model_points: int | None
) -> Matchable:
    """At most ``model_points`` (None: all) of a model's key points, a fixed random subset in
    ascending order of rows, the same whatever the query (:func:`stored_rows`: the library
    keeps the subset of the default size)."""
    rows = stored_rows(len(keypoints), model_points)
    if len(rows) == len(keypoints):
        return Matchable(rows, features, keypoints)
    return Matchable(rows, features[rows], keypoints[rows])


@dataclass(eq=False)
class Matcher:
    """Matches the query against ``library`` models, with each model's :class:`Matchable`
    cached (``model_cache`` models at most).

    ``distance`` is the inlier distance (metres) of the two-point search that ranks headings
    with ``up``; ``heading_draws`` the pairs it draws per model; ``keep_headings`` how many
    headings are kept; ``match_points`` and ``model_points`` cap the key points matched
    (module docstring).
    """

    library: Library
    _: KW_ONLY
    distance: float
    keep_headings: int
    heading_draws: int
    match_points: int | None
    model_points: int | None
    model_cache: int | None = None
    _matchable: ModelCache[Matchable] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._matchable = ModelCache(self.model_cache)

    def matchable(self, model_id: str) -> Matchable:
        """The model's key points that take part in matching (cached)."""
        entry = self.library[model_id]
        return self._matchable.get(
            model_id, lambda: model_subset(entry.keypoints, entry.features, self.model_points)
        )

    def choose_headings(
        self,
        model_ids: list[str],
        views: list[QueryView],
        probes: np.ndarray,
        turn: np.ndarray | None,
        seed: int,
    ) -> list[QueryView]:
        """The ``keep_headings`` views whose features agree best with these models' (all of
        them when there are no more), best first; ``probes`` are rows of the first view's key
        points (:func:`probe_rows`), ``turn`` the levelling turn when ``up`` is known."""
        if len(views) <= self.keep_headings:
            return views
        agreement = np.zeros(len(views))
        for v, view in enumerate(views):
            # Headings voxelise differently, so their key point counts differ by a few.
            rows = probes % len(view.features)
            for model_id in model_ids:
                agreement[v] += self._agreement(view, rows, self.matchable(model_id), turn, seed)
        return [views[i] for i in np.argsort(-agreement, kind="stable")[: self.keep_headings]]

    def _agreement(
        self,
        view: QueryView,
        rows: np.ndarray,
        model: Matchable,
        turn: np.ndarray | None,
        seed: int,
    ) -> int:
        """Mutual matches of the probe ``rows`` with ``model``; with ``turn``, only those that
        the best upright pose of a quick two-point search explains."""
        if turn is None:
            return mutual_count(view.features[rows], model.features)
        pairs = mutual_nearest(view.features[rows], model.features, min_mutual=0)
        poses = yaw_ransac(
            model.keypoints[pairs[:, 1]],
            view.keypoints[rows[pairs[:, 0]]] @ turn.T,
            self.distance,
            seed=seed,
            draws=self.heading_draws,
            keep=1,
        )
        return int(poses.inliers[0]) if len(poses) else 0

    def match(self, model_id: str, view: QueryView, seed: int) -> Matches:
        """Mutual nearest neighbours between the query's matched subset at ``view`` and the
        model's."""
        model = self.matchable(model_id)
        subset = query_subset(len(view.features), self.match_points, seed)
        found = mutual_nearest(view.features[subset], model.features)
        pairs = np.stack([subset[found[:, 0]], model.rows[found[:, 1]]], axis=1)
        return Matches(model_id, view, pairs, model.keypoints[found[:, 1]])
