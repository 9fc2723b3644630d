"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, one step per stage module, each timed under the
stage names the HTTP answer's ``timings_ms`` documents (two steps may share a name):

1. **validate** (:mod:`~catalign.registration.validation`): finite, enough occupied voxels,
   neither a line nor a plane; far points are set aside;
2. **orient** (:mod:`~catalign.registration.orient`): the ways up the query may stand (the
   given ``up``, or the proposed ones), the floor under it, and the headings each is described
   at (proposed, or every heading without a proposer); the floor, then small clusters
   detached from the chair (:mod:`~catalign.registration.cleanup`), are set aside;
3. **describe** (:mod:`~catalign.registration.describe`, timed as ``features``): key points and
   features at every heading of every orientation (with ``heading_mass``, the confident
   headings first), in shared forward passes;
4. under each orientation (:meth:`Engine._search`):

   * **shortlist** (:mod:`~catalign.registration.shortlist`): the ``top_k`` library models
     most like the query, by global descriptor, size and height;
   * **match** (:mod:`~catalign.registration.match`, ``match_ransac``): the ``keep_headings``
     headings whose features agree best with the leading candidates', then every candidate's
     mutual nearest neighbours at them;
   * **hypothesise** (:mod:`~catalign.registration.hypothesise`, ``match_ransac``): poses from
     the matches, the two-point search with an up, the three-point RANSAC otherwise;
   * **verify** (:mod:`~catalign.registration.verify`): poses scored by the query they explain
     times the model surface they cover, nudged by the layout with an up;

5. **refine** (:mod:`~catalign.registration.refine`, ``icp_score``): ICP for the ``refine`` best
   poses of all orientations, scored again the same way; the best wins;
6. **category fit** (:mod:`~catalign.registration.category_fit`, ``icp_score``): with an up, a
   winner that fits loosely (another instance) is refitted at the observed size, stood upright
   and centred on the observed extent; an alternative is only stood upright and centred;
7. **answer**: model, pose, fit statistics, the up it was found under, and each candidate's
   best verification score.

With ``heading_mass``, a query whose first answer is weaker than ``heading_fallback`` goes
through steps 3 to 6 again at its other proposed headings, every pose found competing with
the first round's (each refined once).

Every option comes from one :class:`~catalign.registration.config.EngineConfig`; the engine
turns it into the stages' keyword arguments, and the stages keep their own per-model caches.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from catalign.deadline import Deadline
from catalign.errors import DegenerateInputError
from catalign.features.extractor import FeatureExtractor
from catalign.geometry.se3 import scale_of, transform
from catalign.library.entry import LibraryEntry
from catalign.library.index import Library
from catalign.registration.answers import best_other, distinct
from catalign.registration.base import Alternative, Orientation, RegistrationResult
from catalign.registration.category_fit import CategoryFitter
from catalign.registration.cleanup import detached_mask
from catalign.registration.confidence import Evidence
from catalign.registration.config import EngineConfig, from_config
from catalign.registration.describe import describe, rotations_of
from catalign.registration.hypothesise import Hypothesiser
from catalign.registration.match import Matcher
from catalign.registration.orient import Oriented, orient
from catalign.registration.refine import Fit, Refiner
from catalign.registration.search import Search, StageClock, query_searches
from catalign.registration.shortlist import shortlist
from catalign.registration.transfer import transferred
from catalign.registration.validation import (
    MAX_RECEIVED_VOXELS,
    CheckedCloud,
    validate_cloud,
)
from catalign.registration.verify import Scored, Verifier, best_per_model


class Engine:
    """Registers clouds against a loaded library with one feature extractor.

    Example::

        engine = Engine(LearnedExtractor(), library, config=EngineConfig(top_k=5))
        result = engine.register(points, up=np.array([0.0, 0.0, 1.0]), seed=0)

    ``config`` holds every option (:class:`EngineConfig`, its defaults when not given);
    ``headings`` (the config's, else the extractor's), ``ransac_distance`` and ``icp_distance``
    (metres) are what the engine made of it.
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        library: Library,
        *,
        config: EngineConfig | None = None,
    ) -> None:
        config = EngineConfig() if config is None else config
        voxel = extractor.voxel_size
        self.extractor = extractor
        self.library = library
        self.config = config
        self.headings = extractor.headings if config.headings is None else config.headings
        self.ransac_distance = config.ransac_factor * voxel
        self.icp_distance = config.icp_factor * voxel
        # The stages, each with its options from the config (from_config: same names).
        self.matcher = from_config(Matcher, config, library, distance=self.ransac_distance)
        self.hypothesiser = from_config(Hypothesiser, config, distance=self.ransac_distance)
        self.verifier = from_config(
            Verifier,
            config,
            library,
            distance=self.ransac_distance,
            cell=config.coverage_cell * voxel,
        )
        self.refiner = from_config(Refiner, config, library, distance=self.icp_distance)
        self.category_fitter = CategoryFitter(
            library, self.refiner, extent_points=config.coverage_points
        )

    def register(
        self,
        points: np.ndarray,
        *,
        top_k: int | None = None,
        up: np.ndarray | None = None,
        estimate_scale: bool = False,
        seed: int = 0,
        deadline: Deadline | None = None,
    ) -> RegistrationResult:
        """The best library model for ``points`` and its model -> observation pose.

        ``top_k`` overrides the configured shortlist size; ``up`` is the world's up direction in
        the cloud's frame, when known. ``deadline`` is checked before every step and between
        models: a cancelled or expired one stops the work with
        :class:`~catalign.errors.DeadlineExceededError`.
        """
        config, clock = self.config, StageClock(deadline)
        voxel = self.extractor.voxel_size
        # Validate the cloud (and bound every later step's work).
        with clock("validate"):
            cloud = validate_cloud(
                points,
                voxel_size=voxel,
                min_points=config.min_points,
                fine_cells=config.fine_cells,
            )

        # Orient: the ways up it may stand (given, or proposed), the floor under it, headings;
        # the floor, then small clusters detached from the chair, are set aside.
        with clock("orient"):
            oriented = orient(
                cloud.points,
                up,
                self.extractor.orientation,
                headings=self.headings,
                up_proposals=config.up_proposals,
                heading_proposals=config.heading_proposals,
                heading_mass=config.heading_mass,
                voxel=voxel,
            )
            cloud = cloud.without(oriented.floor, voxel, config.min_points, MAX_RECEIVED_VOXELS)
            cloud = cloud.without(detached_mask(cloud.points), voxel, config.min_points)

        # Describe and search the query at the first headings of every orientation (all of
        # them, or the confident ones); then at the rest, when the answer found is weak.
        k = config.top_k if top_k is None else top_k
        first, rest = _split(oriented)
        searches = self._described(cloud, first, seed, clock)
        found = self._found(searches, k, estimate_scale, seed, clock)
        refined: dict[int, Scored] = {}  # kept for a second round: ICP once per pose
        answered = self._answered(found, refined, estimate_scale, clock)
        if rest and (answered is None or self._weak(answered[0][0])):
            more = self._described(cloud, rest, seed, clock)
            searches += more
            found = sorted(found + self._found(more, k, estimate_scale, seed, clock), key=_best)
            answered = self._answered(found, refined, estimate_scale, clock)
        if answered is None:
            raise DegenerateInputError(
                "no pose fits this cloud: its features matched no library model consistently "
                "(is it a whole object, in metres?)"
            )

        # Answer: the winner, its fit, its alternatives and every candidate's best score.
        finished, tried = answered
        candidates = list(dict.fromkeys(i for s in searches for i in s.candidates))
        result = self._answer(finished, cloud, candidates, tried, clock.timings)
        return replace(result, orientations=tuple(oriented.orientations))

    def _described(
        self, cloud: CheckedCloud, orientations: list[Orientation], seed: int, clock: StageClock
    ) -> list[Search]:
        """The query described at every heading of every one of ``orientations``, in shared
        forward passes: one search each."""
        voxel = self.extractor.voxel_size
        with clock("features"):
            rotations = [r for o in orientations for r in rotations_of(o)]
            views = describe(
                self.extractor,
                cloud.points,
                rotations,
                voxels=cloud.voxels,
                pass_voxels=self.config.pass_voxels,
            )
            return query_searches(
                orientations, views, self.config.probe_points, seed, support_radius=2 * voxel
            )

    def _found(
        self,
        searches: list[Search],
        k: int | None,
        estimate_scale: bool,
        seed: int,
        clock: StageClock,
    ) -> list[tuple[Search, Scored]]:
        """The verified poses under every search (shortlist, match, hypothesise and verify),
        best first."""
        found = [
            (search, item)
            for search in searches
            for item in self._search(search, k, estimate_scale, seed, clock)
        ]
        return sorted(found, key=_best)

    def _answered(
        self,
        found: list[tuple[Search, Scored]],
        refined_by_source: dict[int, Scored],
        estimate_scale: bool,
        clock: StageClock,
    ) -> tuple[list[_Finished], list[Scored]] | None:
        """The finished answers from the verified poses ``found`` (the winner first, then its
        alternatives) and every pose tried; None when nothing was found. ``refined_by_source``
        keeps the refined poses by their source's id, for a second call with more poses found."""
        if not found:
            return None
        config = self.config
        # Refine the best poses by ICP and score them again: the best one wins. The best pose
        # of each further distinct answer is refined too: the alternatives.
        with clock("icp_score"):
            best = found[: config.refine]
            others = [
                pair
                for pair in distinct(found, 1 + config.alternatives, _scored)
                if not any(pair is chosen for chosen in best)
            ]
            for search, item in best + others:
                if id(item) not in refined_by_source:
                    refined_by_source[id(item)] = self._refined(search, item)
            refined = [(search, refined_by_source[id(item)]) for search, item in best + others]
            winner = max(refined[: len(best)], key=lambda pair: pair[1].score)
            rest = sorted((p for p in refined if p is not winner), key=_best)
            answers = distinct([winner, *rest], 1 + config.alternatives, _scored)
            leading = best + others

        # Finish each answer: the category fit (another instance, up known), its statistics,
        # and the evidence its confidence is read from.
        with clock("icp_score"):
            sources = {id(item) for _, item in leading}
            tried = [item for _, item in refined]
            tried += [item for _, item in found if id(item) not in sources]
            finished = [
                self._finish(search, item, tried, estimate_scale, refit=rank == 0)
                for rank, (search, item) in enumerate(answers)
            ]
        return finished, tried

    def _weak(self, answer: _Finished) -> bool:
        """Whether an answer found at the confident headings alone is too unsure to keep
        without searching the other proposed headings (always, without a calibrator)."""
        return answer.confidence is None or answer.confidence < self.config.heading_fallback

    def _search(
        self, search: Search, k: int | None, estimate_scale: bool, seed: int, clock: StageClock
    ) -> list[Scored]:
        """The verified poses of the query under one orientation, best first; ``search``
        records its shortlist and its verification checks."""
        turn = search.turn
        # Shortlist the models most like the query, best first.
        with clock("shortlist"):
            search.candidates = shortlist(self.library, search.views, k, turn)

        # Match: keep the headings the leading candidates agree with, match every candidate there.
        with clock("match_ransac"):
            leading = search.candidates[: self.config.heading_models]
            views = self.matcher.choose_headings(leading, search.views, search.probes, turn, seed)
            matches = [
                self.matcher.match(model_id, view, seed)
                for model_id in clock.each(search.candidates)
                for view in views
            ]

        # Hypothesise poses from each candidate's matches at each kept heading.
        with clock("match_ransac"):
            hypotheses = [
                hypothesis
                for found in clock.each(matches)
                for hypothesis in self.hypothesiser.poses(
                    found, turn, estimate_scale=estimate_scale, seed=seed
                )
            ]

        # Verify: every pose by the query it explains, the best also by coverage and layout;
        # then the best poses carried over to the leading candidates, verified the same way.
        with clock("verify"):
            search.checks = self.verifier.query_checks(search.keypoints, search.probes, turn)
            ranked = self.verifier.rank(hypotheses, search.checks)
            carried = transferred(
                self.library,
                ranked,
                search.candidates,
                poses=self.config.transfer_poses,
                models=self.config.transfer_models,
            )
            ranked += self.verifier.rank(carried, search.checks)
            ranked.sort(key=lambda item: -item.score)
            return [self._weighed(search, item) for item in ranked]

    def _weighed(self, search: Search, item: Scored) -> Scored:
        """A verified pose found under ``search``'s orientation, its score weighed by the
        belief in that orientation's up (verification alone prefers an upside-down chair too
        often)."""
        belief = search.orientation.belief**self.config.up_belief_power
        return Scored(item.hypothesis, item.score * belief)

    def _refined(self, search: Search, item: Scored) -> Scored:
        """``item``'s pose refined by ICP onto its model and scored again."""
        pose = self.refiner.refine(item.hypothesis, search.keypoints)
        return self._weighed(search, self.verifier.score(pose, search.checks))

    def _finish(
        self,
        search: Search,
        item: Scored,
        tried: list[Scored],
        estimate_scale: bool,
        *,
        refit: bool,
    ) -> _Finished:
        """A refined answer made final: with an up, another instance (a loose fit) is given
        the observed chair's frame (the category fit; its ICP at the observed size only with
        ``refit``, for the winner: for the alternatives it measured a tenth of the query's time
        and changed little); then its statistics, and the evidence (against every pose
        ``tried``) and confidence of it."""
        pose = item.hypothesis
        fit = self.refiner.fit(pose, search.keypoints)
        turn = search.turn
        if turn is not None and not estimate_scale and fit.fitness < self.config.exact_fitness:
            pose = self.category_fitter.fit(
                pose,
                search.keypoints,
                turn,
                solid=search.solid,
                floor_level=search.orientation.floor_level,
                refit=refit,
            )
            fit = self.refiner.fit(pose, search.keypoints)
        explained, covered, _ = self.verifier.parts(item.hypothesis, search.checks)
        score = max(item.score, 1e-9)
        evidence = Evidence(
            score=item.score,
            explained=explained,
            covered=covered,
            heading_margin=best_other(tried, item, same_model=True) / score,
            model_margin=best_other(tried, item, same_model=False) / score,
            fitness=float(fit.fitness),
            rmse=float(fit.inlier_rmse) / self.icp_distance,
            inlier_ratio=fit.num_inliers / len(search.keypoints),
            span=_spanned(self.library[pose.model_id], pose.transform, search.keypoints),
            up_given=search.orientation.given,
            up_belief=search.orientation.belief,
            keypoints=len(search.keypoints),
        )
        calibrator = self.extractor.confidence
        confidence = None if calibrator is None else calibrator.probability(evidence)
        return _Finished(search, replace(item, hypothesis=pose), fit, evidence, confidence)

    def _answer(
        self,
        finished: list[_Finished],
        cloud: CheckedCloud,
        candidates: list[str],
        tried: list[Scored],
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


@dataclass(frozen=True, eq=False)
class _Finished:
    """An answer made final: where it was found, its pose and score, its fit, evidence and
    confidence."""

    search: Search
    item: Scored
    fit: Fit
    evidence: Evidence
    confidence: float | None


def _scored(pair: tuple[Search, Scored]) -> Scored:
    return pair[1]


def _best(pair: tuple[Search, Scored]) -> float:
    """Sorts verified poses best first."""
    return -pair[1].score


def _split(oriented: Oriented) -> tuple[list[Orientation], list[Orientation]]:
    """The orientations at the headings described first, and those at the rest (only the
    orientations that have any)."""
    pairs = zip(oriented.orientations, oriented.first, strict=True)
    first, rest = [], []
    for orientation, count in pairs:
        first.append(replace(orientation, headings=orientation.headings[:count]))
        if count < len(orientation.headings):
            rest.append(replace(orientation, headings=orientation.headings[count:]))
    return first, rest


def _spanned(model: LibraryEntry, pose: np.ndarray, keypoints: np.ndarray) -> float:
    """The smallest share, over the model's axes, of its extent that the key points span in
    its frame under ``pose`` (2nd to 98th percentile: stray points do not stretch it)."""
    local = transform(keypoints, np.linalg.inv(pose))
    low, high = np.percentile(local, [2.0, 98.0], axis=0)
    return float(np.min((high - low) / np.maximum(model.size, 1e-6)))
