"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, each step timed under the stage names the HTTP
answer's ``timings_ms`` documents:

1. **validate** (:mod:`~catalign.registration.prepare.validation`): finite, enough occupied voxels,
   neither a line nor a plane; far points are set aside; the rest, and ``up``, are moved into
   the query's own frame (:mod:`~catalign.registration.prepare.frame`), where every later step works
   and from which the answer is moved back;
2. **orient** (:mod:`~catalign.registration.prepare.orient`): the ways up the query may stand (the
   given ``up``, or the proposed ones), the floor under it and the headings each is described
   at; the floor (:mod:`~catalign.registration.prepare.floor`), then small clusters detached
   from the object (:mod:`~catalign.registration.prepare.detached`), are set aside;
3. a **search round** (:meth:`Engine._round`), over the confident headings of the confident
   ups first:

   * **features** (:mod:`~catalign.registration.stages.describe`): key points and features at every
     heading of every orientation, in shared forward passes;
   * under each orientation (:mod:`~catalign.registration.stages.searcher`): **shortlist**
     (:mod:`~catalign.registration.stages.shortlist`), **match** and **hypothesise**
     (:mod:`~catalign.registration.stages.match`, :mod:`~catalign.registration.stages.hypothesise`,
     timed together as ``match_ransac``), **sweep** (:mod:`~catalign.registration.stages.sweep`,
     with an up) and **verify** (:mod:`~catalign.registration.stages.verify`), the scores weighed
     by the beliefs in the orientation;
   * the **decision** (:mod:`~catalign.registration.decision.rules`, timed as ``icp_score``): which
     poses ICP refines (:mod:`~catalign.registration.stages.refine`), which refined pose is the
     answer
     and which are its alternatives, each finished (:mod:`~catalign.registration.decision.finish`:
     the category fit, the evidence, the confidence);

4. a **second round** at every proposed heading under every proposed up (the first round's
   views kept) when the first answer is less confident than ``heading_fallback``;
5. without ``up``, a **floor round**: a floor guessed under a proposed up is doubted (it may
   be the chair's back) when the answer does not stand on it, or stands on it weakly without
   fitting exactly; steps 2 to 4 run again with it kept, and an exact answer there wins;
6. the **answer**: model, pose, fit statistics, confidence, the up it was found under, the
   alternatives and each candidate's best score, moved back to the caller's frame.

Every option comes from one :class:`~catalign.registration.config.EngineConfig`, a tree of
groups, one per stage; :mod:`~catalign.registration.assembly` builds the stages from it. Each
stage keeps its own per-model caches; what one call computes once (poses, refinements, category
fits) is in its :class:`~catalign.registration.stages.request.RequestCache`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from catalign.deadline import Deadline
from catalign.errors import DegenerateInputError
from catalign.features.extractor import FeatureExtractor
from catalign.features.orientation import OrientationProposer
from catalign.library.loaded import Library
from catalign.registration.assembly import assemble
from catalign.registration.config import EngineConfig
from catalign.registration.decision.confidence import (
    Calibrator,
    find_calibrator,
    find_category_calibrators,
)
from catalign.registration.decision.rules import Decision, Found, Refined, decide
from catalign.registration.prepare.detached import detached_mask
from catalign.registration.prepare.orient import Oriented, orient
from catalign.registration.prepare.validation import (
    MAX_RECEIVED_VOXELS,
    MAX_VOXELS,
    CheckedCloud,
    validate_cloud,
)
from catalign.registration.results import Orientation, RegistrationResult
from catalign.registration.stages.describe import QueryView, describe, rotations_of
from catalign.registration.stages.request import RefinedPose, Request
from catalign.registration.stages.search import Search, StageClock, query_searches
from catalign.registration.stages.verify import Scored


class FromWeights:
    """The default calibrator: the one in the extractor's weights folder, if it has one."""


FROM_WEIGHTS = FromWeights()
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


@dataclass(frozen=True, eq=False)
class Round:
    """One search round: the searches it ran (one per orientation) and what they decided
    (None: no pose was found)."""

    searches: tuple[Search, ...]
    decision: Decision | None


class Engine:
    """Registers clouds against a loaded library with one feature extractor.

    Example::

        engine = Engine(LearnedExtractor(), library, config=EngineConfig(top_k=5))
        result = engine.register(points, up=np.array([0.0, 0.0, 1.0]), seed=0)

    ``config`` holds every option (:class:`EngineConfig`, its defaults when not given);
    ``calibrator`` reads each answer's confidence (by default the one beside the extractor's
    weights, and a category's own for its models' answers where the folder has one; None:
    none). A query answered from one category alone (sent, or the library's only one) is
    oriented by that category's own networks where the folder has them. ``headings`` (the
    config's, else the extractor's), ``ransac_distance`` and ``icp_distance`` (metres) are what
    the engine made of it.
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        library: Library,
        *,
        config: EngineConfig | None = None,
        calibrator: Calibrator | FromWeights | None = FROM_WEIGHTS,
    ) -> None:
        config = EngineConfig() if config is None else config
        voxel = extractor.voxel_size
        self.extractor, self.library, self.config = extractor, library, config
        headings = config.orient.headings
        self.headings = extractor.headings if headings is None else headings
        self.ransac_distance = config.ransac.factor * voxel
        self.icp_distance = config.icp.factor * voxel
        general, own = _calibrators(extractor, calibrator)
        self.orientations = extractor.category_orientations
        stages = assemble(config, library, extractor, calibrator=general, calibrators=own)
        self.verifier, self.searcher = stages.verifier, stages.searcher
        self.refiner, self.rules, self.finisher = stages.refiner, stages.rules, stages.finisher

    def register(
        self,
        points: np.ndarray,
        *,
        top_k: int | None = None,
        up: np.ndarray | None = None,
        estimate_scale: bool = False,
        seed: int = 0,
        deadline: Deadline | None = None,
        category: str | None = None,
    ) -> RegistrationResult:
        """The best library model for ``points`` and its model -> observation pose.

        ``top_k`` overrides the configured shortlist size; ``up`` is the world's up direction in
        the cloud's frame, when known; ``category`` restricts the answer to that category's
        models (an unknown one raises InvalidInputError listing the library's). ``deadline`` is
        checked before every step and between models: a cancelled or expired one stops the work
        with :class:`~catalign.errors.DeadlineExceededError`.
        """
        config, clock = self.config, StageClock(deadline)
        rows = self.library.of_category(category)
        with clock("validate"):
            cloud = validate_cloud(
                points,
                voxel_size=self.extractor.voxel_size,
                up=up,
                min_points=config.input.min_points,
                fine_cells=config.input.fine_cells,
            )
            frame = cloud.frame
            up = frame.direction(up)
        k = config.top_k if top_k is None else top_k
        request = Request(k, estimate_scale, seed, clock, rows, category)

        # A query answered from one category is oriented by its own networks, where it has them.
        proposer = self.orientations.get(
            category or self.library.only_category(), self.extractor.orientation
        )
        oriented, kept = self._oriented(cloud, up, clock, proposer)
        searched = self._rounds(kept, oriented, request)
        # Without up, a chair's back or side under a wrong proposed up can pass for a floor
        # (1 to 3 of 54 so3 views a seed): set aside, it takes the part that would make the
        # observed instance fit. The floor round keeps it (where the features can describe
        # that much), and an exact answer there wins.
        guessed_floor = up is None and oriented.floor.any() and cloud.voxels <= MAX_VOXELS
        if guessed_floor and self._doubts_floor(searched.decision):
            bare, whole = self._oriented(cloud, up, clock, proposer, doubted=oriented)
            again = self._rounds(whole, bare, request)
            if self._fits_exactly(again.decision):
                oriented, kept, searched = bare, whole, again
        if searched.decision is None:
            raise DegenerateInputError(
                "no pose fits this cloud: its features matched no library model consistently "
                "(is it a whole object, in metres?)"
            )
        decision = searched.decision
        candidates = list(dict.fromkeys(i for s in searched.searches for i in s.candidates))
        result = self.finisher.result(
            decision.answers, kept, candidates, decision.tried, clock.timings
        )
        chosen = self.library[result.model_id]
        result = replace(
            result,
            orientations=tuple(oriented.orientations),
            category=chosen.category,
            symmetry=chosen.symmetry,
        )
        return frame.result(result)

    def _oriented(
        self,
        cloud: CheckedCloud,
        up: np.ndarray | None,
        clock: StageClock,
        proposer: OrientationProposer | None,
        *,
        doubted: Oriented | None = None,
    ) -> tuple[Oriented, CheckedCloud]:
        """The ways up ``cloud`` may stand (given, or proposed by ``proposer``), the floor
        under it and the headings; and the cloud with the floor, then small clusters detached
        from the chair, set aside. After a ``doubted`` look, no floor is sought and its proposed
        ups are reused."""
        config, voxel = self.config, self.extractor.voxel_size
        with clock("orient"):
            oriented = orient(
                cloud.points,
                up,
                proposer,
                headings=self.headings,
                voxel=voxel,
                min_voxels=config.input.min_points,
                options=config.orient,
                floor_options=config.floor,
                guessed_ups=() if doubted is None else doubted.guessed_ups,
            )
            least = config.input.min_points
            kept = cloud.without(oriented.floor, voxel, least, MAX_RECEIVED_VOXELS)
            aside = detached_mask(kept.points, options=config.cleanup)
            kept = kept.without(aside, voxel, least)
        return oriented, kept

    def _rounds(self, cloud: CheckedCloud, oriented: Oriented, request: Request) -> Round:
        """The first round, at the first headings of the first orientations (all of them, or
        the confident ones), and the second, at every proposed heading of every orientation
        (the first round's views kept), when the first answer is weak."""
        first = self._round(self._described(cloud, oriented.described_first, request), request)
        if not oriented.held_back or not self._weak(first.decision):
            return first
        return self._round(self._widened(first.searches, oriented, cloud, request), request)

    def _round(self, searches: list[Search], request: Request) -> Round:
        """One search round: every search's verified poses, best first, and the decision."""
        searched, found = [], []
        for search in searches:
            search, ranked = self.searcher.search(search, request)
            searched.append(search)
            found += [Found(search, item) for item in ranked]
        found.sort(key=lambda item: -item.scored.score)
        refine = partial(self._refined, request=request)
        finish = partial(
            self.finisher.finish, estimate_scale=request.estimate_scale, cache=request.cache
        )
        with request.clock("icp_score"):
            decision = decide(
                found, self.rules, refine=refine, finish=finish, symmetry_of=self.library.symmetry
            )
        return Round(tuple(searched), decision)

    def _doubts_floor(self, decision: Decision | None) -> bool:
        """Whether the answer casts doubt on the guessed floor set aside: the winner was not
        found standing on it, or it was but neither fits exactly nor is sure enough."""
        if decision is None or decision.winner.search.orientation.floor_level is None:
            return True
        return not self._fits_exactly(decision) and self._weak(decision)

    def _fits_exactly(self, decision: Decision | None) -> bool:
        return decision is not None and decision.fits_exactly(self.rules.exact_fitness)

    def _weak(self, decision: Decision | None) -> bool:
        """Whether an answer (or none) is too unsure to keep without searching the other
        proposed headings and ups (``heading_fallback``)."""
        return decision is None or decision.weak(self.config.decision.heading_fallback)

    def _described(
        self, cloud: CheckedCloud, orientations: list[Orientation], request: Request
    ) -> list[Search]:
        """The query described at every heading of every one of ``orientations``, in shared
        forward passes: one search each."""
        return self._split(orientations, self._views(cloud, orientations, request.clock), request)

    def _widened(
        self,
        searches: tuple[Search, ...],
        oriented: Oriented,
        cloud: CheckedCloud,
        request: Request,
    ) -> list[Search]:
        """The first round's ``searches`` widened to every orientation at every heading: the
        views described already kept, the others described."""
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
                widened.append(search.widened(whole, added))
        return widened

    def _split(
        self, orientations: list[Orientation], views: list[QueryView], request: Request
    ) -> list[Search]:
        """``views`` (in the order of the orientations' rotations): one search for each."""
        radius, probes = 2 * self.extractor.voxel_size, self.config.verify.probe_points
        return query_searches(orientations, views, probes, request.seed, support_radius=radius)

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
                pass_voxels=self.config.input.pass_voxels,
            )

    def _refined(self, item: Found, request: Request) -> Refined:
        """``item``'s pose refined by ICP onto its model, scored again and fitted (once a
        call)."""
        search = item.search

        def refine() -> RefinedPose:
            pose = self.refiner.refine(item.scored.hypothesis, search.keypoints)
            parts = self.verifier.parts(pose, search.checks)
            scored = self.searcher.weighed(search, Scored(pose, float(np.prod(parts))))
            return RefinedPose(scored, parts, self.refiner.fit(pose, search.keypoints))

        done = request.cache.refined_pose(item.scored.hypothesis, refine)
        return Refined(item, done.scored, done.parts, done.fit)


def _calibrators(
    extractor: FeatureExtractor, calibrator: Calibrator | FromWeights | None
) -> tuple[Calibrator | None, dict[str, Calibrator]]:
    """The general calibrator (``calibrator``, or the weights folder's) and the categories' own
    (the folder's, unless one was given)."""
    folder = extractor.model_dir
    weights = isinstance(calibrator, FromWeights) and folder is not None
    own = find_category_calibrators(folder) if weights else {}
    return _weights_calibrator(extractor, calibrator), own


def _weights_calibrator(
    extractor: FeatureExtractor, calibrator: Calibrator | FromWeights | None
) -> Calibrator | None:
    """``calibrator``, or the one in the extractor's weights folder (None without one)."""
    if not isinstance(calibrator, FromWeights):
        return calibrator
    return None if extractor.model_dir is None else find_calibrator(extractor.model_dir)
