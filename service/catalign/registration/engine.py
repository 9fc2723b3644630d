"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, one step per stage module, each timed under the
stage names the HTTP answer's ``timings_ms`` documents (two steps may share a name):

1. **validate** (:mod:`~catalign.registration.validation`): finite, enough occupied voxels,
   neither a line nor a plane; far points are set aside; the rest, and ``up``, are moved into
   the query's own frame (:mod:`~catalign.registration.frame`), where every later step works
   and from which the answer is moved back: it does not depend on where the sensor stood;
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
   * **sweep** (:mod:`~catalign.registration.sweep`): with an up, the leading candidates
     also posed from their surfaces alone, every yaw and shift of a grid;
   * **verify** (:mod:`~catalign.registration.verify`): poses scored by the query they explain
     times the model surface they cover, nudged by the layout with an up;

5. **refine** (:mod:`~catalign.registration.refine`, ``icp_score``): ICP for the ``refine`` best
   poses of all orientations and the best pose of each further distinct answer (the best
   swept answers too when none of them fits surely: ``sure_fitness``), scored again the same
   way; the best of the first wins, unless answers fit exactly (``exact_fitness``: the
   observed instance itself), when the best of those does, those that fit surely first
   (with ``rival_models``, unless another leading model fits the query clearly better at its
   pose: :mod:`~catalign.registration.rivals`);
6. **category fit** (:mod:`~catalign.registration.category_fit`, ``icp_score``): with an up, a
   winner that fits loosely (another instance) is refitted at the observed size, stood upright
   and centred on the observed extent; an alternative is only stood upright and centred;
7. **answer** (:mod:`~catalign.registration.finish`, with step 6): model, pose, fit
   statistics, evidence and confidence, the up it was found under, the alternatives, and each
   candidate's best verification score; an alternative clearly more confident than a winner
   that does not fit exactly (``confidence_margin``) takes its place.

With ``heading_mass`` (and, without ``up``, ``up_mass``), a query whose first answer is less
confident than ``heading_fallback`` is searched again (steps 3 to 7) at every proposed heading
under every proposed up, the first views kept: its answer is then the one it gets without
them. Without ``up``, a floor guessed under a proposed up is doubted (it may be the chair's
back) when the answer does not stand on it, or stands on it weakly without fitting exactly:
steps 3 to 7 run again with it kept, and an exact answer there wins.

Every option comes from one :class:`~catalign.registration.config.EngineConfig`; the engine
turns it into the stages' keyword arguments, and the stages keep their own per-model caches.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from catalign.deadline import Deadline
from catalign.errors import DegenerateInputError
from catalign.features.extractor import FeatureExtractor
from catalign.features.orientation import HEADING_DISTINCT_DEG
from catalign.library.index import Library
from catalign.registration.answers import distinct, promoted
from catalign.registration.base import Orientation, RegistrationResult
from catalign.registration.category_fit import CategoryFitter
from catalign.registration.cleanup import detached_mask
from catalign.registration.config import EngineConfig, from_config
from catalign.registration.describe import QueryView, describe, rotations_of
from catalign.registration.finish import Finished, Finisher
from catalign.registration.gravity import yaw_of
from catalign.registration.hypothesise import Hypothesis, Hypothesiser
from catalign.registration.match import Matcher
from catalign.registration.orient import Oriented, orient
from catalign.registration.refine import Refiner
from catalign.registration.rivals import RivalCheck
from catalign.registration.search import Request, Search, StageClock, query_searches
from catalign.registration.shortlist import shortlist
from catalign.registration.sweep import Sweeper
from catalign.registration.transfer import transferred
from catalign.registration.validation import (
    MAX_RECEIVED_VOXELS,
    MAX_VOXELS,
    CheckedCloud,
    validate_cloud,
)
from catalign.registration.verify import Scored, Verifier

# The stages a query's ``timings_ms`` name, in the order they run.
STAGES = (
    "validate",
    "orient",
    "features",
    "shortlist",
    "match_ransac",
    "sweep",
    "verify",
    "icp_score",
)
# A pose at a heading the heading network all but rules out keeps this much belief.
HEADING_BELIEF_FLOOR = 0.01


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
        self.sweeper = from_config(Sweeper, config, library, distance=self.ransac_distance)
        self.verifier = from_config(
            Verifier,
            config,
            library,
            distance=self.ransac_distance,
            cell=config.coverage_cell * voxel,
        )
        self.refiner = from_config(Refiner, config, library, distance=self.icp_distance)
        self.rival_check = from_config(RivalCheck, config, library, self.refiner)
        self.finisher = Finisher(
            library,
            self.refiner,
            self.verifier,
            CategoryFitter(library, self.refiner, extent_points=config.coverage_points),
            icp_distance=self.icp_distance,
            exact_fitness=config.exact_fitness,
            calibrator=extractor.confidence,
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
        # Validate the cloud (and bound every later step's work), in the query's own frame.
        with clock("validate"):
            cloud = validate_cloud(
                points,
                voxel_size=voxel,
                up=up,
                min_points=config.min_points,
                fine_cells=config.fine_cells,
            )
            frame = cloud.frame
            up = frame.direction(up)

        k = config.top_k if top_k is None else top_k
        oriented, kept = self._oriented(cloud, up, clock)
        searches, answered = self._searched(kept, oriented, Request(k, estimate_scale, seed, clock))
        # Without up, a chair's back or side under a wrong proposed up can pass for a floor
        # (1 to 3 of 54 so3 views a seed): set aside, it takes the part that would make the
        # observed instance fit. A guessed floor is doubted when the answer does not stand on
        # it, or stands on it weakly without fitting exactly: the search runs again with the
        # floor kept (where the features can describe that much), and an exact answer there
        # wins.
        guessed_floor = up is None and oriented.floor.any() and cloud.voxels <= MAX_VOXELS
        if guessed_floor and self._doubts_floor(answered):
            bare, whole = self._oriented(cloud, up, clock, doubted=oriented)
            again = self._searched(whole, bare, Request(k, estimate_scale, seed, clock))
            if self._fits_exactly(again[1]):
                oriented, kept, (searches, answered) = bare, whole, again
        cloud = kept
        if answered is None:
            raise DegenerateInputError(
                "no pose fits this cloud: its features matched no library model consistently "
                "(is it a whole object, in metres?)"
            )

        # Answer: the winner, its fit, its alternatives and every candidate's best score.
        finished, tried = answered
        candidates = list(dict.fromkeys(i for s in searches for i in s.candidates))
        result = self.finisher.result(finished, cloud, candidates, tried, clock.timings)
        return frame.result(replace(result, orientations=tuple(oriented.orientations)))

    def _oriented(
        self,
        cloud: CheckedCloud,
        up: np.ndarray | None,
        clock: StageClock,
        *,
        doubted: Oriented | None = None,
    ) -> tuple[Oriented, CheckedCloud]:
        """The ways up ``cloud`` may stand (given, or proposed), the floor under it and the
        headings; and the cloud with the floor, then small clusters detached from the chair,
        set aside. After a ``doubted`` look, no floor is sought and its proposed ups are
        reused."""
        config, voxel = self.config, self.extractor.voxel_size
        with clock("orient"):
            oriented = orient(
                cloud.points,
                up,
                self.extractor.orientation,
                headings=self.headings,
                up_proposals=config.up_proposals,
                heading_proposals=config.heading_proposals,
                heading_mass=config.heading_mass,
                up_mass=config.up_mass,
                voxel=voxel,
                min_voxels=config.min_points,
                guessed_ups=() if doubted is None else doubted.guessed_ups,
                given_snap_deg=config.up_snap_deg,
            )
            kept = cloud.without(oriented.floor, voxel, config.min_points, MAX_RECEIVED_VOXELS)
            kept = kept.without(detached_mask(kept.points), voxel, config.min_points)
        return oriented, kept

    def _searched(
        self, cloud: CheckedCloud, oriented: Oriented, request: Request
    ) -> tuple[list[Search], tuple[list[Finished], list[Scored]] | None]:
        """The searches and the answers: the query described and searched at the first
        headings of the first orientations (all of them, or the confident ones), and again at
        every proposed heading of every orientation (the first ones' views kept) when the
        answer found there is weak."""
        searches = self._described(cloud, oriented.described_first, request)
        answered = self._answered(self._found(searches, request), request)
        if oriented.held_back and (answered is None or self._weak(answered[0][0])):
            searches = self._widened(searches, oriented, cloud, request)
            answered = self._answered(self._found(searches, request), request)
        return searches, answered

    def _doubts_floor(self, answered: tuple[list[Finished], list[Scored]] | None) -> bool:
        """Whether the answers cast doubt on the guessed floor set aside: the winner was not
        found standing on it, or it was but neither fits exactly nor is sure enough
        (``heading_fallback``)."""
        if answered is None:
            return True
        winner = answered[0][0]
        if winner.search.orientation.floor_level is None:
            return True
        return not self._fits_exactly(answered) and self._weak(winner)

    def _fits_exactly(self, answered: tuple[list[Finished], list[Scored]] | None) -> bool:
        """Whether the winner of ``answered`` fits the query as only the observed instance
        itself does (``exact_fitness``)."""
        return answered is not None and answered[0][0].fit.fitness >= self.config.exact_fitness

    def _described(
        self, cloud: CheckedCloud, orientations: list[Orientation], request: Request
    ) -> list[Search]:
        """The query described at every heading of every one of ``orientations``, in shared
        forward passes: one search each."""
        return self._split(orientations, self._views(cloud, orientations, request.clock), request)

    def _split(
        self, orientations: list[Orientation], views: list[QueryView], request: Request
    ) -> list[Search]:
        """``views`` (in the order of the orientations' rotations) split into one search for
        each of ``orientations``."""
        return query_searches(
            orientations,
            views,
            self.config.probe_points,
            request.seed,
            support_radius=2 * self.extractor.voxel_size,
        )

    def _widened(
        self, searches: list[Search], oriented: Oriented, cloud: CheckedCloud, request: Request
    ) -> list[Search]:
        """``searches`` (of ``oriented``'s orientations described first) widened to every
        orientation at every heading: the views described already kept, the others described."""
        started = iter(searches)
        searched = [next(started) if n else None for n in oriented.first]
        further = [
            replace(whole, headings=whole.headings[len(search.views) if search else 0 :])
            for search, whole in zip(searched, oriented.orientations, strict=True)
        ]
        views = iter(self._views(cloud, further, request.clock))
        widened = []
        for search, whole, extra in zip(searched, oriented.orientations, further, strict=True):
            added = [next(views) for _ in extra.headings]
            if search is None:
                widened += self._split([whole], added, request)
            else:
                widened.append(
                    Search(whole, search.views + added, search.probes, search.support_radius)
                )
        return widened

    def _views(
        self, cloud: CheckedCloud, orientations: list[Orientation], clock: StageClock
    ) -> list[QueryView]:
        """The query described at every heading of every one of ``orientations``, in that
        order, in shared forward passes."""
        with clock("features"):
            rotations = [r for o in orientations for r in rotations_of(o)]
            return describe(
                self.extractor,
                cloud.points,
                rotations,
                voxels=cloud.voxels,
                pass_voxels=self.config.pass_voxels,
            )

    def _found(self, searches: list[Search], request: Request) -> list[tuple[Search, Scored]]:
        """The verified poses under every search (shortlist, match, hypothesise and verify),
        best first."""
        found = [(search, item) for search in searches for item in self._search(search, request)]
        return sorted(found, key=_best)

    def _answered(
        self, found: list[tuple[Search, Scored]], request: Request
    ) -> tuple[list[Finished], list[Scored]] | None:
        """The finished answers from the verified poses ``found`` (the winner first, then its
        alternatives) and every pose tried; None when nothing was found."""
        if not found:
            return None
        config, clock = self.config, request.clock
        # Refine the best matched poses by ICP and score them again; the best pose of each
        # further distinct answer is refined too (the alternatives). Unless one of them fits
        # surely (``sure_fitness``), so are the best swept answers, kept only if they then fit
        # exactly: a view of a chair's underside can fit its own CAD exactly turned the wrong
        # way, and the sweep finds the right turn. The winner is the best-scored answer that
        # fits surely, else exactly, else the best of the refined best matches.
        with clock("icp_score"):
            matched = [pair for pair in found if not pair[1].hypothesis.swept] or found
            best = matched[: config.refine]
            others = [
                pair
                for pair in distinct(matched, 1 + config.alternatives, _scored)
                if not any(pair is chosen for chosen in best)
            ]
            leading = best + others
            refined = [(search, self._refined(search, item, request)) for search, item in leading]
            if not any(self._sure(pair, request) for pair in refined):
                for pair, done in self._exact_sweeps(found, request):
                    if not any(done[1] is item for _, item in refined):
                        leading.append(pair)
                        refined.append(done)
            exact = [pair for pair in refined if self._exact(pair, request)]
            exact = [pair for pair in exact if self._sure(pair, request)] or exact
            winner = max(exact or refined[: len(best)], key=lambda pair: pair[1].score)
            challenged = self._challenged(winner, matched)
            if challenged is not winner:  # a rival won; the winner may stay an alternative
                refined.append(challenged)
                winner = challenged
            rest = sorted((p for p in refined if p is not winner), key=_best)
            answers = distinct([winner, *rest], 1 + config.alternatives, _scored)

        # Finish each answer: the category fit (another instance, up known), its statistics,
        # and the evidence its confidence is read from.
        with clock("icp_score"):
            sources = {id(item) for _, item in leading}
            tried = [item for _, item in refined]
            tried += [item for _, item in matched if id(item) not in sources]
            finished = [
                self.finisher.finish(search, item, tried, request.estimate_scale, refit=rank == 0)
                for rank, (search, item) in enumerate(answers)
            ]
            # An alternative clearly more confident than the winner takes its place, if it
            # still is once finished as the winner was (refitted at the observed size); a
            # winner that fits exactly (the observed instance itself) keeps its place.
            first = 0
            if finished[0].fit.fitness < config.exact_fitness:
                first = promoted([f.confidence for f in finished], config.confidence_margin)
            if first:
                search, item = answers[first]
                challenger = self.finisher.finish(
                    search, item, tried, request.estimate_scale, refit=True
                )
                pair = [finished[0].confidence, challenger.confidence]
                if promoted(pair, config.confidence_margin):
                    del finished[first]
                    finished.insert(0, challenger)
        return finished, tried

    def _challenged(
        self, winner: tuple[Search, Scored], found: list[tuple[Search, Scored]]
    ) -> tuple[Search, Scored]:
        """The refined ``winner``, or a rival model that fits the query clearly better at its
        pose (:mod:`~catalign.registration.rivals`), the models led by their best pose
        ``found``."""
        search, item = winner
        leading = list(dict.fromkeys(pair[1].hypothesis.model_id for pair in found))
        rival = self.rival_check.challenger(item.hypothesis, search.keypoints, leading)
        if rival is None:
            return winner
        return search, self._weighed(search, self.verifier.score(rival, search.checks))

    def _exact(self, pair: tuple[Search, Scored], request: Request) -> bool:
        """Whether a refined pose fits the query as only the observed instance itself does
        (``exact_fitness``; once a call): such a pose beats any that does not, whatever their
        scores."""
        return self._fitness(pair, request) >= self.config.exact_fitness

    def _sure(self, pair: tuple[Search, Scored], request: Request) -> bool:
        """Whether a refined pose fits the query so closely (``sure_fitness``) that no other
        pose need be sought, and one that fits only exactly gives way to it."""
        return self._fitness(pair, request) >= self.config.sure_fitness

    def _fitness(self, pair: tuple[Search, Scored], request: Request) -> float:
        """The share of the query a refined pose fits within one ICP distance (once a call)."""
        search, item = pair
        key = id(item.hypothesis)
        if key not in request.fitness:
            request.fitness[key] = self.refiner.fit(item.hypothesis, search.keypoints).fitness
        return request.fitness[key]

    def _exact_sweeps(
        self, found: list[tuple[Search, Scored]], request: Request
    ) -> list[tuple[tuple[Search, Scored], tuple[Search, Scored]]]:
        """The ``sweep_refine`` best distinct swept answers among ``found``, and the best one
        under each orientation, that fit exactly once refined, each with its refinement. The
        sweep looks for the observed instance itself: its pose of another instance fits that
        surface without matching its parts, and measured a worse category-level pose than the
        matched ones, so it is dropped."""
        swept = [pair for pair in found if pair[1].hypothesis.swept]
        leading = distinct(swept, self.config.sweep_refine, _scored)
        # The best of each orientation too: a proposed up believed little weighs its poses
        # down, yet the observed instance fits exactly under it when it is the right one.
        for search in {id(search): search for search, _ in swept}.values():
            best = next(pair for pair in swept if pair[0] is search)  # swept is best first
            if not any(best is chosen for chosen in leading):
                leading.append(best)
        exact = []
        for search, item in leading:
            done = (search, self._refined(search, item, request))
            if self._exact(done, request):
                exact.append(((search, item), done))
        return exact

    def _weak(self, answer: Finished) -> bool:
        """Whether an answer found at the confident headings alone is too unsure to keep
        without searching the other proposed headings (always, without a calibrator)."""
        return answer.confidence is None or answer.confidence < self.config.heading_fallback

    def _search(self, search: Search, request: Request) -> list[Scored]:
        """The verified poses of the query under one orientation, best first; ``search``
        records its shortlist and its verification checks."""
        turn, seed, clock = search.turn, request.seed, request.clock
        # Shortlist the models most like the query, best first.
        with clock("shortlist"):
            search.candidates = shortlist(self.library, search.views, request.k, turn)

        # Match: keep the headings the leading candidates agree with, match every candidate
        # there, and hypothesise poses from each candidate's matches at each kept heading.
        with clock("match_ransac"):
            leading = search.candidates[: self.config.heading_models]
            views = self.matcher.choose_headings(leading, search.views, search.probes, turn, seed)
            hypotheses = [
                hypothesis
                for model_id in clock.each(search.candidates)
                for view in views
                for hypothesis in self._posed(model_id, view, turn, request)
            ]

        # Sweep: with an up, the leading candidates also posed from their surfaces alone, at
        # yaws around the proposed headings (every yaw when none was proposed).
        with clock("sweep"):
            swept = []
            if turn is not None and not request.estimate_scale:
                orientation = search.orientation
                swept = self.sweeper.poses(
                    search.candidates,
                    search.keypoints[search.probes],
                    turn,
                    orientation.headings if orientation.headings_proposed else (),
                    search.views[0],
                )

        # Verify: every pose by the query it explains, the best also by coverage and layout
        # (the swept poses apart: they explain the most by design, and would crowd the matched
        # ones out); then the best poses carried over to the leading candidates, verified the
        # same way.
        with clock("verify"):
            search.checks = self.verifier.query_checks(search.keypoints, search.probes, turn)
            ranked = self.verifier.rank(hypotheses, search.checks)
            ranked += self.verifier.rank(swept, search.checks)
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
        often) and by the heading network's belief in its heading (verification alone turns
        another instance a quarter or half turn too often)."""
        config, orientation = self.config, search.orientation
        weight = orientation.belief**config.up_belief_power
        turn = search.turn
        if config.heading_belief_power and turn is not None:
            yaw = yaw_of(turn @ item.hypothesis.transform[:3, :3])
            heading = orientation.heading_belief(yaw, HEADING_DISTINCT_DEG / 2)
            weight *= max(heading, HEADING_BELIEF_FLOOR) ** config.heading_belief_power
        return Scored(item.hypothesis, item.score * weight)

    def _posed(
        self, model_id: str, view: QueryView, turn: np.ndarray | None, request: Request
    ) -> list[Hypothesis]:
        """The poses of a model from its matches with the query at one heading (once a call)."""
        key = (model_id, id(view))
        if key not in request.poses:
            found = self.matcher.match(model_id, view, request.seed)
            request.poses[key] = self.hypothesiser.poses(
                found, turn, estimate_scale=request.estimate_scale, seed=request.seed
            )
        return request.poses[key]

    def _refined(self, search: Search, item: Scored, request: Request) -> Scored:
        """``item``'s pose refined by ICP onto its model and scored again (once a call)."""
        key = id(item.hypothesis)
        if key not in request.refined:
            pose = self.refiner.refine(item.hypothesis, search.keypoints)
            scored = self._weighed(search, self.verifier.score(pose, search.checks))
            request.refined[key] = (item.hypothesis, scored)
        return request.refined[key][1]


def _scored(pair: tuple[Search, Scored]) -> Scored:
    return pair[1]


def _best(pair: tuple[Search, Scored]) -> float:
    """Sorts verified poses best first."""
    return -pair[1].score
