"""The category-level fit: placing another instance's frame where the observed chair's is.

With ``up``, a winner that does not fit the query exactly is another instance of the category,
and ICP lays it onto the observation as well as a differently shaped chair allows: a smaller
model hugs one side, a tilt hugs a different back. The category-level pose is the model's frame
(its bounding-box centre) placed where the observed chair's is, so the fit is redone in three
steps, the pose staying rigid throughout:

1. **refit at the observed size**: ICP against the model scaled about its centre to the
   observed height (within :data:`SIZE_RANGE`), keeping the rigid pose that puts the unscaled
   centre where the scaled fit put it;
2. **stand upright**: with gravity known a tilt is fitting error, not pose
   (:func:`~catalign.geometry.levelling.level_pose` about the model's centre). A *rough* up
   (a proposal no plane confirmed, good to about ten degrees) is not gravity known: the pose
   stands half-way between it and the ICP's tilt (:func:`rough_up_estimate`);
3. **centre on the extent**: along each model axis (height, width, depth) on which the view
   spans nearly all of the model (:data:`FULL_SPAN_SHARE`), the pose is shifted so that both
   spans share their middle; where a side is hidden the fitted position is kept. Stray points
   (a sensor's flying pixels) would stretch a span, so only key points with neighbours count.

When a floor was found under the query and set aside, its level is the bottom of the observed
height in steps 1 and 3: the chair stands on it, and the cleanup took the last centimetres of
its legs with the floor.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from catalign.geometry.levelling import level_pose, leveller
from catalign.geometry.se3 import make_pose
from catalign.library.loaded import Library
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import Refiner
from catalign.registration.stages.verify import surface_sample

# A view spanning less of the model along an axis than this has lost that side from sight.
FULL_SPAN_SHARE = 0.8
# Sizes of another instance, relative to the model, that the refit considers.
SIZE_RANGE = (0.8, 1.25)
# A fit tilted further than this from a rough up is no chair standing on it: the rough up stands.
ROUGH_TILT_DEG = 20.0


@dataclass(frozen=True, eq=False)
class CategoryFitter:
    """Fits another instance's rigid pose to the observed chair's frame.

    ``refiner`` runs the ICP against ``library`` models; ``extent_points`` is how many model
    surface points give the model's extent (the coverage check's sample).
    """

    library: Library
    refiner: Refiner
    _: KW_ONLY
    extent_points: int

    def fit(
        self,
        hypothesis: Hypothesis,
        keypoints: np.ndarray,
        turn: np.ndarray,
        *,
        solid: np.ndarray,
        floor_level: float | None = None,
        refit: bool = True,
        rough_up: bool = False,
    ) -> Hypothesis:
        """The three steps (module docstring) for the winner ``hypothesis`` of the query's
        ``keypoints``, whose levelling turn is ``turn``; ``solid`` are the key points with
        neighbours (:func:`supported`, once per query), which give the observed extent.
        ``floor_level`` is the height (along ``turn``'s up) of a floor found under the query
        and set aside: the chair stands on it, so its observed extent reaches down to it.
        Without ``refit`` the first step (an ICP) is skipped: an alternative is only stood
        upright and centred. ``rough_up`` says ``turn``'s up is a rough estimate (step 2)."""
        if refit:
            heights = keypoints @ turn[1]
            bottom = heights.min() if floor_level is None else min(heights.min(), floor_level)
            observed_height = float(heights.max() - bottom)
            hypothesis = self.fit_at_observed_size(hypothesis, keypoints, observed_height)
        if rough_up:
            turn = leveller(rough_up_estimate(turn[1], hypothesis.transform[:3, 1]))
        hypothesis = self.stand_upright(hypothesis, turn)
        return self.centre_on_extent(hypothesis, solid, floor_level)

    def fit_at_observed_size(
        self, hypothesis: Hypothesis, keypoints: np.ndarray, observed_height: float
    ) -> Hypothesis:
        """ICP once more against the model scaled about its centre to the observed height,
        keeping the rigid pose that puts the (unscaled) centre where the scaled fit put it."""
        entry = self.library[hypothesis.model_id]
        scale = float(np.clip(observed_height / entry.size[1], *SIZE_RANGE))
        if abs(scale - 1.0) < 0.02:
            return hypothesis
        centre = entry.centre
        rotation, translation = hypothesis.transform[:3, :3], hypothesis.transform[:3, 3]
        # x = R (s p + (1 - s) c) + t = R y + t_s for y = s p on the origin-scaled surface
        start = make_pose(rotation, translation + (1 - scale) * rotation @ centre)
        fitted = self.refiner.icp(keypoints, hypothesis.model_id, scale, start)
        fitted[:3, 3] -= (1 - scale) * fitted[:3, :3] @ centre
        return replace(hypothesis, transform=fitted)

    def stand_upright(self, hypothesis: Hypothesis, turn: np.ndarray) -> Hypothesis:
        """The pose stood upright about the model's centre (:func:`level_pose`)."""
        centre = self.library[hypothesis.model_id].centre
        return replace(hypothesis, transform=level_pose(hypothesis.transform, turn, centre))

    def centre_on_extent(
        self, hypothesis: Hypothesis, solid: np.ndarray, floor_level: float | None = None
    ) -> Hypothesis:
        """The (upright) pose shifted along each of the model's axes on which the observation
        (its ``solid`` key points) spans nearly all of the model, so that the two spans share
        their middle there; the observed span along the model's up reaches down to
        ``floor_level`` when given."""
        points = self.library[hypothesis.model_id].points
        sample = surface_sample(points, self.extent_points)
        rotation, translation = hypothesis.transform[:3, :3], hypothesis.transform[:3, 3]
        observed = (solid - translation) @ rotation
        low, high = observed.min(axis=0), observed.max(axis=0)
        if floor_level is not None:  # upright: the model's +Y is the floor's normal
            low[1] = min(low[1], floor_level - translation @ rotation[:, 1])
        shift = (high + low) / 2 - (sample.max(axis=0) + sample.min(axis=0)) / 2
        full = high - low >= FULL_SPAN_SHARE * np.ptp(sample, axis=0)
        pose = hypothesis.transform.copy()
        pose[:3, 3] += rotation @ np.where(full, shift, 0.0)
        return replace(hypothesis, transform=pose)


def rough_up_estimate(rough: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """The up a pose stands on under a ``rough`` up, its ICP's being ``fitted`` (the model's
    +Y): their bisector, since both err by several degrees, and independently (the up network
    by its bins, the fit by the shapes' differences); ``rough`` itself when the fit tilts
    further than :data:`ROUGH_TILT_DEG`. On the evaluation's so3 views (seeds 0 and 1) the
    bisector answered 2 more of 216 within 10 degrees than the rough up did; the ICP's up
    alone as many, but it lost 4 of the 108 turned *cross* views."""
    if fitted @ rough < np.cos(np.radians(ROUGH_TILT_DEG)):
        return rough
    middle = rough + fitted
    return middle / np.linalg.norm(middle)


def supported(points: np.ndarray, radius: float, neighbours: int = 2) -> np.ndarray:
    """The points with at least ``neighbours`` others within ``radius`` (all of them when fewer
    than half are)."""
    counts = cKDTree(points).query_ball_point(points, radius, return_length=True) - 1
    solid = points[counts >= neighbours]
    return solid if len(solid) >= 0.5 * len(points) else points
