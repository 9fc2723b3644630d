"""Finishing answers: the category fit, the fit statistics, the evidence and confidence of each
refined answer, and the result they make.

A refined pose on another instance (a loose fit) is given the observed chair's frame by the
category fit (:mod:`~catalign.registration.stages.category_fit`, with an up); then its fit on the
query's key points is measured, the :class:`~catalign.registration.decision.confidence.Evidence`
for it gathered (against every pose tried), and the calibrator, when the weights ship one, reads the
probability that it is right from that evidence.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import KW_ONLY, dataclass, field, replace

import numpy as np

from catalign.geometry.se3 import scale_of, transform
from catalign.library.entry import LibraryEntry
from catalign.library.loaded import Library
from catalign.registration.decision.answers import best_other, category_share
from catalign.registration.decision.confidence import Calibrator, Evidence
from catalign.registration.decision.rules import Finished, Refined
from catalign.registration.prepare.validation import CheckedCloud
from catalign.registration.results import Alternative, RegistrationResult
from catalign.registration.stages.category_fit import CategoryFitter
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import Fit, Refiner
from catalign.registration.stages.request import RequestCache
from catalign.registration.stages.verify import Scored, best_per_model


@dataclass(frozen=True, eq=False)
class Finisher:
    """Makes refined answers final against ``library`` models. ``icp_distance`` (metres) is
    the unit of the evidence's RMS distance; ``exact_fitness`` the fitness from which a model
    is taken to be the observed instance itself (no category fit); ``calibrator`` None gives
    no confidence; ``calibrators`` are those fitted on one category's answers, by category,
    each reading the answers of its category's models in place of ``calibrator``."""

    library: Library
    refiner: Refiner
    category_fitter: CategoryFitter
    _: KW_ONLY
    icp_distance: float
    exact_fitness: float
    calibrator: Calibrator | None
    calibrators: Mapping[str, Calibrator] = field(default_factory=dict)

    def finish(
        self,
        refined: Refined,
        tried: Sequence[Scored],
        refit: bool,
        *,
        estimate_scale: bool,
        cache: RequestCache,
    ) -> Finished:
        """A refined answer made final: with an up, another instance (a loose fit) is given
        the observed chair's frame (the category fit, once per pose and ``refit`` in the
        ``cache``; its ICP at the observed size only with ``refit``, for the winner: for the
        alternatives it measured a tenth of the query's time and changed little); then its
        evidence (against every pose ``tried``) and confidence."""
        search, item = refined.search, refined.scored
        pose, fit = item.hypothesis, refined.fit
        turn = search.turn
        if turn is not None and not estimate_scale and fit.fitness < self.exact_fitness:
            pose, fit = cache.category_fit(pose, refit, lambda: self._fitted(refined, refit))
        explained, covered, _ = refined.parts
        score = max(item.score, 1e-9)
        evidence = Evidence(
            score=item.score,
            explained=explained,
            covered=covered,
            heading_margin=best_other(
                tried, item, same_model=True, symmetry_of=self.library.symmetry
            )
            / score,
            model_margin=best_other(tried, item, same_model=False) / score,
            fitness=float(fit.fitness),
            rmse=float(fit.inlier_rmse) / self.icp_distance,
            inlier_ratio=fit.num_inliers / len(search.keypoints),
            span=_spanned(self.library[pose.model_id], pose.transform, search.keypoints),
            up_given=search.orientation.given,
            up_belief=search.orientation.belief,
            keypoints=len(search.keypoints),
        )
        calibrator = self.calibrators.get(self.library[pose.model_id].category, self.calibrator)
        confidence = None if calibrator is None else calibrator.probability(evidence)
        return Finished(search, replace(item, hypothesis=pose), fit, evidence, confidence)

    def _fitted(self, refined: Refined, refit: bool) -> tuple[Hypothesis, Fit]:
        """The category fit of a refined pose (module docstring) and the fit it then has."""
        search = refined.search
        assert search.turn is not None
        pose = self.category_fitter.fit(
            refined.scored.hypothesis,
            search.keypoints,
            search.turn,
            solid=search.solid,
            floor_level=search.orientation.floor_level,
            refit=refit,
            rough_up=search.orientation.up_rough,
        )
        return pose, self.refiner.fit(pose, search.keypoints)

    def _category(self, finished: Finished) -> str:
        return self.library[finished.item.hypothesis.model_id].category

    def result(
        self,
        finished: Sequence[Finished],
        cloud: CheckedCloud,
        candidates: list[str],
        tried: Sequence[Scored],
        timings: dict[str, float],
    ) -> RegistrationResult:
        """The result for the first of the ``finished`` answers (the others are its
        alternatives): the fit statistics on the query's key points, the candidates'
        best scores among the poses ``tried``, and the matches of the pose."""
        best, others = finished[0], finished[1:]
        winner, fit, search = best.item.hypothesis, best.fit, best.search
        num_inliers = fit.num_inliers
        return RegistrationResult(
            model_id=winner.model_id,
            pose=winner.transform,
            fitness=float(fit.fitness),
            inlier_rmse=float(fit.inlier_rmse),
            num_inliers=num_inliers,
            inlier_ratio=num_inliers / len(search.keypoints),
            candidates=best_per_model(candidates, tried),
            timings_ms=timings,
            correspondences=(
                winner.view.keypoints[winner.matches[:, 0]],
                self.library[winner.model_id].keypoints[winner.matches[:, 1]],
            ),
            scale=scale_of(winner.transform),
            points_set_aside=cloud.set_aside,
            orientation=search.orientation,
            confidence=best.confidence,
            evidence=best.evidence,
            category_confidence=category_share(
                [(self._category(f), f.confidence) for f in finished]
            ),
            alternatives=tuple(
                Alternative(
                    model_id=other.item.hypothesis.model_id,
                    pose=other.item.hypothesis.transform,
                    score=other.item.score,
                    fitness=float(other.fit.fitness),
                    confidence=other.confidence,
                    evidence=other.evidence,
                )
                for other in others
            ),
        )


def _spanned(model: LibraryEntry, pose: np.ndarray, keypoints: np.ndarray) -> float:
    """The smallest share, over the model's axes, of its extent that the key points span in
    its frame under ``pose`` (2nd to 98th percentile: stray points do not stretch it)."""
    local = transform(keypoints, np.linalg.inv(pose))
    low, high = np.percentile(local, [2.0, 98.0], axis=0)
    return float(np.min((high - low) / np.maximum(model.size, 1e-6)))
