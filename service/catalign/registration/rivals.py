"""Rival models: the winner's pose tried on the other leading models; a clearly better fit wins.

Every library model shares the canonical frame, so the winner's refined pose is a start for
any other model too. When the observed chair's own CAD is in the library and a near-twin won
verification (its features matched better, its pose scored as well), the own CAD, carried to
the twin's pose (:mod:`~catalign.registration.transfer`) and refined by ICP, explains more of
the query than the twin does: its fitness is higher. So the ``rival_models`` leading models
other than the winner are fitted at the carried pose, the ``rival_icp`` that fit best are
refined, and the best of those replaces the winner when its fitness beats the winner's by
``rival_margin``. A winner whose fitness reaches ``exact_fitness`` is taken to be the observed
instance already and is not challenged.

A rival changes the model, not the answer's pose: one whose refined pose turned more than
``rival_turn_deg`` from the winner's, or moved its category-level origin (the bounding-box
centre) more than ``rival_shift_m``, is not taken. Another instance that ICP slid along the
view fits better where it does not belong: on views of the training chairs, rivals taken
without this check lost more right poses than the models they got right.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass

import numpy as np

from catalign.geometry.se3 import rotation_error_deg, transform
from catalign.library.index import Library
from catalign.registration.hypothesise import Hypothesis
from catalign.registration.refine import Refiner
from catalign.registration.transfer import transferred
from catalign.registration.verify import Scored


@dataclass(eq=False)
class RivalCheck:
    """Challenges a refined winner with the leading other models (module docstring)."""

    library: Library
    refiner: Refiner
    _: KW_ONLY
    rival_models: int
    rival_icp: int
    rival_margin: float
    rival_turn_deg: float
    rival_shift_m: float
    exact_fitness: float

    def challenger(
        self, winner: Hypothesis, keypoints: np.ndarray, leading: list[str]
    ) -> Hypothesis | None:
        """The refined pose of a model among ``leading`` (model ids, best first) that fits
        ``keypoints`` better than the refined ``winner`` by the margin; None when none does."""
        if self.rival_models == 0:
            return None
        own = self.refiner.fit(winner, keypoints).fitness
        if own >= self.exact_fitness:
            return None
        others = [m for m in leading if m != winner.model_id][: self.rival_models]
        carried = transferred(
            self.library, [Scored(winner, 0.0)], others, poses=1, models=len(others)
        )
        at_once = [self.refiner.fit(h, keypoints).fitness for h in carried]
        screened = [carried[i] for i in np.argsort(at_once)[::-1][: self.rival_icp]]
        refined = [self.refiner.refine(h, keypoints) for h in screened]
        refined = [h for h in refined if self._agrees(h, winner)]
        fits = [self.refiner.fit(h, keypoints).fitness for h in refined]
        if not fits or max(fits) <= own + self.rival_margin:
            return None
        return refined[int(np.argmax(fits))]

    def _agrees(self, rival: Hypothesis, winner: Hypothesis) -> bool:
        """Whether ``rival`` poses its model where ``winner`` poses its own (module docstring)."""
        turn = rotation_error_deg(rival.transform[:3, :3], winner.transform[:3, :3])
        origins = [
            transform(self.library[h.model_id].centre[None], h.transform)[0]
            for h in (rival, winner)
        ]
        shift = float(np.linalg.norm(origins[0] - origins[1]))
        return turn <= self.rival_turn_deg and shift <= self.rival_shift_m
