"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, one step per stage module, each timed under the
stage names the HTTP answer's ``timings_ms`` documents (two steps may share a name):

1. **validate** (:mod:`~catalign.registration.validation`): finite, enough occupied voxels,
   neither a line nor a plane; ``up`` becomes the turn that levels the query;
2. **describe** (:mod:`~catalign.registration.describe`, timed as ``features``): the levelled
   query's key points and features at every heading the features need;
3. **shortlist** (:mod:`~catalign.registration.shortlist`): the ``top_k`` library models most
   like the query, by global descriptor, size and height;
4. **match** (:mod:`~catalign.registration.match`, ``match_ransac``): the ``keep_headings``
   headings whose features agree best with the leading candidates', then every candidate's
   mutual nearest neighbours at them;
5. **hypothesise** (:mod:`~catalign.registration.hypothesise`, ``match_ransac``): poses from the
   matches, the two-point search with ``up``, the three-point RANSAC otherwise;
6. **verify** (:mod:`~catalign.registration.verify`): poses scored by the query they explain
   times the model surface they cover, nudged by the layout with ``up``;
7. **refine** (:mod:`~catalign.registration.refine`, ``icp_score``): ICP for the ``refine`` best
   poses, scored again the same way; the best wins;
8. **category fit** (:mod:`~catalign.registration.category_fit`, ``icp_score``): with ``up``, a
   winner that fits loosely (another instance) is refitted at the observed size, stood upright
   and centred on the observed extent;
9. **answer**: model, pose, fit statistics, and each candidate's best verification score.

Every option comes from one :class:`~catalign.registration.config.EngineConfig`; the engine
turns it into the stages' keyword arguments, and the stages keep their own per-model caches.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import numpy as np
import open3d as o3d

from catalign.deadline import Deadline
from catalign.errors import DegenerateInputError
from catalign.features.extractor import FeatureExtractor
from catalign.geometry.distance_grid import CELL_VOXELS
from catalign.geometry.se3 import scale_of
from catalign.library.index import Library
from catalign.registration.alignment import point_cloud
from catalign.registration.base import RegistrationResult
from catalign.registration.category_fit import CategoryFitter
from catalign.registration.config import EngineConfig, from_config
from catalign.registration.describe import describe
from catalign.registration.gravity import leveller
from catalign.registration.hypothesise import Hypothesis, Hypothesiser
from catalign.registration.match import Matcher, probe_rows
from catalign.registration.refine import Refiner
from catalign.registration.shortlist import shortlist
from catalign.registration.validation import CheckedCloud, validate_cloud
from catalign.registration.verify import Scored, Verifier, best_per_model

T = TypeVar("T")


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
            Verifier, config, library, distance=self.ransac_distance, cell=CELL_VOXELS * voxel
        )
        self.refiner = Refiner(library, distance=self.icp_distance, normal_radius=2 * voxel)
        self.category_fitter = CategoryFitter(
            library, self.refiner, support_radius=2 * voxel, extent_points=config.coverage_points
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
        config, clock = self.config, _Clock(deadline)
        # Validate the cloud (and bound every later step's work); level it when up is known.
        with clock("validate"):
            cloud = validate_cloud(
                points,
                voxel_size=self.extractor.voxel_size,
                min_points=config.min_points,
                fine_cells=config.fine_cells,
            )
            turn = None if up is None else leveller(up)

        # Describe the query at every heading; fix the probe key points that rank everything.
        with clock("features"):
            views = describe(
                self.extractor, cloud, turn, headings=self.headings, pass_voxels=config.pass_voxels
            )
            keypoints = views[0].keypoints
            probes = probe_rows(len(keypoints), config.probe_points, seed)

        # Shortlist the models most like the query, best first.
        with clock("shortlist"):
            k = config.top_k if top_k is None else top_k
            candidates = shortlist(self.library, views, k, turn)

        # Match: keep the headings the leading candidates agree with, match every candidate there.
        with clock("match_ransac"):
            leading = candidates[: config.heading_models]
            views = self.matcher.choose_headings(leading, views, probes, turn, seed)
            matches = [
                self.matcher.match(model_id, view, seed)
                for model_id in clock.each(candidates)
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

        # Verify: every pose by the query it explains, the best also by coverage and layout.
        with clock("verify"):
            checks = self.verifier.query_checks(keypoints, probes, turn)
            scored = self.verifier.rank(hypotheses, checks)
        if not scored:
            raise DegenerateInputError(
                "no pose fits this cloud: its features matched no library model consistently "
                "(is it a whole object, in metres?)"
            )

        # Refine the best poses by ICP and score them again; the best one wins.
        with clock("icp_score"):
            query = point_cloud(keypoints)
            refined = [
                self.verifier.score(self.refiner.refine(item.hypothesis, query), checks)
                for item in scored[: config.refine]
            ]
            winner = max(refined, key=lambda item: item.score).hypothesis
            fit = self.refiner.fit(winner, query)

        # Category fit: another instance (a loose fit, up known) gets the observed chair's frame.
        if turn is not None and not estimate_scale and fit.fitness < config.exact_fitness:
            with clock("icp_score"):
                winner = self.category_fitter.fit(winner, query, keypoints, turn)
                fit = self.refiner.fit(winner, query)

        # Answer: the winner, its fit, and every candidate's best score.
        tried = refined + scored[config.refine :]
        return self._answer(winner, fit, cloud, keypoints, candidates, tried, clock.timings)

    def _answer(
        self,
        winner: Hypothesis,
        fit: o3d.pipelines.registration.RegistrationResult,
        cloud: CheckedCloud,
        keypoints: np.ndarray,
        candidates: list[str],
        tried: list[Scored],
        timings: dict[str, float],
    ) -> RegistrationResult:
        """The result for ``winner``: Open3D's ``fit`` statistics on the query's key points,
        the candidates' best scores among the poses ``tried``, and the matches of the pose."""
        num_inliers = len(fit.correspondence_set)
        return RegistrationResult(
            model_id=winner.model_id,
            pose=winner.transform,
            fitness=float(fit.fitness),
            inlier_rmse=float(fit.inlier_rmse),
            num_inliers=num_inliers,
            inlier_ratio=num_inliers / len(keypoints),
            candidates=best_per_model(candidates, tried),
            timings_ms=timings,
            correspondences=(
                winner.view.keypoints[winner.matches[:, 0]],
                self.library[winner.model_id].keypoints[winner.matches[:, 1]],
            ),
            scale=scale_of(winner.transform),
            points_set_aside=cloud.set_aside,
        )


class _Clock:
    """The steps' timings (milliseconds; a step may add to an earlier step's name) and the
    deadline, checked before every step and between the items of a loop."""

    def __init__(self, deadline: Deadline | None) -> None:
        self.timings: dict[str, float] = {}
        self.check: Callable[[], None] = (lambda: None) if deadline is None else deadline.check

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        self.check()
        started = time.perf_counter()
        yield
        elapsed = (time.perf_counter() - started) * 1e3
        self.timings[stage] = self.timings.get(stage, 0.0) + elapsed

    def each(self, items: Iterable[T]) -> Iterator[T]:
        """``items``, with the deadline checked before each."""
        for item in items:
            self.check()
            yield item
