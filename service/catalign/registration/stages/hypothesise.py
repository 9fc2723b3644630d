"""Pose hypotheses: model -> observation poses of one candidate from its matches at one heading.

Cross-instance feature matches are mostly wrong (a few percent are right), and inlier counts
confuse a chair's front with its back, so the search proposes poses and leaves the choice to
verification. With ``up`` (and no scale) the pose has four degrees of freedom once the query is
levelled, and the two-point search of :mod:`~catalign.registration.stages.gravity` finds them from
pairs of matches, keeping the ``poses_per_view`` best *distinct* ones. Otherwise (no ``up``, or
``estimate_scale``) the three-point :func:`~catalign.registration.stages.ransac.ransac` gives its
one best pose, with ``up`` (when given) refusing rotations that tip the chair over.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.frames import MODEL_UP
from catalign.geometry.se3 import make_pose
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.gravity import yaw_ransac
from catalign.registration.stages.match import Matches
from catalign.registration.stages.ransac import ransac

# The matches of a pose that came from no matches (carried over, or swept).
NO_MATCHES = np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A model -> observation pose of one candidate, with the matches it came from (rows of
    the view's key points and of the library entry's); ``swept`` when the sweep found it from
    the model's surface alone (:mod:`~catalign.registration.stages.sweep`)."""

    model_id: str
    transform: np.ndarray
    matches: np.ndarray
    view: QueryView
    swept: bool = False


@dataclass(frozen=True, kw_only=True)
class Hypothesiser:
    """Proposes poses from matches.

    ``distance`` is the inlier distance (metres); ``pair_draws`` and ``poses_per_view`` the
    pairs the two-point search draws and the distinct poses it keeps; ``ransac_iterations``
    caps the three-point RANSAC's draws, and ``up_tolerance_deg`` is how far its rotations may
    tilt the model's up from the given ``up``.
    """

    distance: float
    pair_draws: int
    poses_per_view: int
    ransac_iterations: int
    up_tolerance_deg: float

    def poses(
        self, matches: Matches, turn: np.ndarray | None, *, estimate_scale: bool, seed: int
    ) -> list[Hypothesis]:
        """Hypotheses from ``matches``: several distinct ones from the two-point search when
        the levelling ``turn`` is known and no scale is estimated, else the three-point
        RANSAC's best (a similarity with ``estimate_scale``)."""
        if turn is not None and not estimate_scale:
            return self._upright(matches, turn, seed)
        result = ransac(
            matches.model_points,
            matches.observed,
            self.distance,
            seed=seed,
            up=None if turn is None else turn.T @ MODEL_UP,
            up_tolerance_deg=self.up_tolerance_deg,
            estimate_scale=estimate_scale,
            iterations=self.ransac_iterations,
        )
        return [Hypothesis(matches.model_id, result.transform, matches.pairs, matches.view)]

    def _upright(self, matches: Matches, turn: np.ndarray, seed: int) -> list[Hypothesis]:
        """The two-point search in the levelled frame, its poses turned back."""
        poses = yaw_ransac(
            matches.model_points,
            matches.observed @ turn.T,
            self.distance,
            seed=seed,
            draws=self.pair_draws,
            keep=self.poses_per_view,
        )
        unlevel = make_pose(turn.T, np.zeros(3))
        return [
            Hypothesis(
                matches.model_id,
                unlevel @ make_pose(rotation, translation),
                matches.pairs,
                matches.view,
            )
            for rotation, translation in zip(poses.rotations, poses.translations, strict=True)
        ]
