"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, one step per stage (each timed):

1. **validate**: finite, enough occupied voxels, neither a line nor a plane;
2. **features**: turn the cloud so that the caller's ``up`` becomes the models' +Y, and describe
   it once per heading (a model trained on ``yaw-bin`` rotations sees the query at 8 headings
   45 degrees apart; any other model at one);
3. **shortlist**: the ``top_k`` library entries by global-descriptor similarity and size;
4. **match + RANSAC**, per candidate: the ``keep_headings`` headings whose features agree
   best with the model's (most mutual nearest neighbours among a fixed subset of query key
   points) get full mutual matching and the vectorised RANSAC (with the up prior when ``up`` is
   given); all kept headings go on, since partial views of chairs are often nearly symmetric
   front to back and inlier counts alone confuse the two;
5. **ICP**: point-to-plane refinement of the query onto the candidate's surface, per kept
   hypothesis;
6. **score**: the share of query points the posed model explains, discounted by the RMSE; the
   best candidate wins.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from catalign.features.extractor import Described, FeatureExtractor
from catalign.geometry.se3 import axis_angle, invert, rotation_between
from catalign.library.index import Library
from catalign.library.retrieval import global_descriptor, retrieval_scores
from catalign.registration.alignment import (
    alignment_score,
    mutual_count,
    mutual_nearest,
    point_cloud,
)
from catalign.registration.base import Candidate, RegistrationResult
from catalign.registration.ransac import ransac
from catalign.registration.validation import validate_cloud

MODEL_UP = np.array([0.0, 1.0, 0.0])
reg = o3d.pipelines.registration


@dataclass(frozen=True)
class QueryView:
    """The query described at one heading; key points are in the observation frame."""

    keypoints: np.ndarray
    features: np.ndarray


@dataclass(frozen=True)
class Hypothesis:
    model_id: str
    transform: np.ndarray
    matches: np.ndarray
    view: QueryView
    num_inliers: int


class Engine:
    """Registers clouds against a loaded library with one feature extractor.

    Parameters: ``headings`` (1, or 8 for ``yaw-bin`` models), ``top_k`` default shortlist size
    (None: every entry), ``ransac_factor`` and ``icp_factor`` (inlier distances in voxels),
    ``up_tolerance_deg`` (how far the chair's up may tilt from the given ``up``), ``min_points``
    (occupied voxels a query needs), ``keep_headings`` (headings per candidate that go through
    RANSAC and ICP), ``ransac_iterations`` (cap on hypotheses per RANSAC), ``probe_points``
    (query key points used to rank headings).
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        library: Library,
        *,
        headings: int = 1,
        top_k: int | None = None,
        ransac_factor: float = 2.0,
        icp_factor: float = 1.0,
        up_tolerance_deg: float = 30.0,
        min_points: int = 50,
        keep_headings: int = 2,
        ransac_iterations: int = 5_000,
        probe_points: int = 256,
    ) -> None:
        self.extractor = extractor
        self.library = library
        self.headings = headings
        self.top_k = top_k
        self.ransac_distance = ransac_factor * extractor.voxel_size
        self.icp_distance = icp_factor * extractor.voxel_size
        self.up_tolerance_deg = up_tolerance_deg
        self.min_points = min_points
        self.keep_headings = keep_headings
        self.ransac_iterations = ransac_iterations
        self.probe_points = probe_points
        self._surfaces: dict[str, o3d.geometry.PointCloud] = {}

    def register(
        self,
        points: np.ndarray,
        *,
        top_k: int | None = None,
        up: np.ndarray | None = None,
        estimate_scale: bool = False,
        seed: int = 0,
    ) -> RegistrationResult:
        """The best library model for ``points`` and its model -> observation pose."""
        timings: dict[str, float] = {}
        with _timed(timings, "validate"):
            cloud = validate_cloud(
                points, voxel_size=self.extractor.voxel_size, min_points=self.min_points
            )
            up = None if up is None else np.asarray(up, dtype=np.float64)

        with _timed(timings, "features"):
            views = self._describe(cloud, up)
            query_cloud = point_cloud(views[0].keypoints)

        with _timed(timings, "shortlist"):
            candidates = self._shortlist(views, top_k if top_k is not None else self.top_k)

        with _timed(timings, "match_ransac"):
            hypotheses = [
                hypothesis
                for model_id in candidates
                for hypothesis in self._hypotheses(model_id, views, up, estimate_scale, seed)
            ]

        with _timed(timings, "icp_score"):
            scored = [self._refine(h, query_cloud) for h in hypotheses]
        hypothesis, _, refined, pose = max(scored, key=lambda item: item[1])
        num_inliers = len(refined.correspondence_set)
        return RegistrationResult(
            model_id=hypothesis.model_id,
            pose=pose,
            fitness=float(refined.fitness),
            inlier_rmse=float(refined.inlier_rmse),
            num_inliers=num_inliers,
            inlier_ratio=num_inliers / len(views[0].keypoints),
            candidates=_best_per_model(scored),
            timings_ms=timings,
            correspondences=(
                hypothesis.view.keypoints[hypothesis.matches[:, 0]],
                self.library[hypothesis.model_id].keypoints[hypothesis.matches[:, 1]],
            ),
            scale=float(np.cbrt(np.linalg.det(pose[:3, :3]))),
        )

    def _describe(self, cloud: np.ndarray, up: np.ndarray | None) -> list[QueryView]:
        """The query described at every heading, key points back in the observation frame."""
        turn = np.eye(3) if up is None else rotation_between(up, MODEL_UP)
        views = []
        for k in range(self.headings):
            rotation = axis_angle(MODEL_UP, -2 * np.pi * k / self.headings) @ turn
            described: Described = self.extractor.describe(cloud @ rotation.T)
            views.append(QueryView(described.keypoints @ rotation, described.features))
        return views

    def _shortlist(self, views: list[QueryView], k: int | None) -> list[str]:
        ids = self.library.ids
        if k is None or k >= len(ids):
            return list(ids)
        size = np.ptp(views[0].keypoints, axis=0)
        scores = np.max(
            [retrieval_scores(self.library, global_descriptor(v.features), size) for v in views],
            axis=0,
        )
        return [ids[i] for i in np.argsort(-scores, kind="stable")[:k]]

    def _hypotheses(
        self,
        model_id: str,
        views: list[QueryView],
        up: np.ndarray | None,
        estimate_scale: bool,
        seed: int,
    ) -> list[Hypothesis]:
        """RANSAC hypotheses of one candidate at its ``keep_headings`` most consistent headings."""
        entry = self.library[model_id]
        if len(views) > self.keep_headings:
            probe = np.random.default_rng(seed).permutation(len(views[0].features))
            agreement = [
                mutual_count(
                    v.features[probe[: self.probe_points] % len(v.features)], entry.features
                )
                for v in views
            ]
            views = [views[i] for i in np.argsort(agreement)[::-1][: self.keep_headings]]
        found = []
        for view in views:
            matches = mutual_nearest(view.features, entry.features)
            result = ransac(
                entry.keypoints[matches[:, 1]],
                view.keypoints[matches[:, 0]],
                self.ransac_distance,
                seed=seed,
                up=up,
                up_tolerance_deg=self.up_tolerance_deg,
                estimate_scale=estimate_scale,
                iterations=self.ransac_iterations,
            )
            found.append(Hypothesis(model_id, result.transform, matches, view, result.num_inliers))
        return found

    def _refine(
        self, hypothesis: Hypothesis, query: o3d.geometry.PointCloud
    ) -> tuple[Hypothesis, float, reg.RegistrationResult, np.ndarray]:
        """ICP of the query onto the (scaled) model surface; returns the score and the pose."""
        scale = float(np.cbrt(np.linalg.det(hypothesis.transform[:3, :3])))
        rigid = hypothesis.transform.copy()
        rigid[:3, :3] /= scale
        surface = self._surface(hypothesis.model_id, scale)
        refined = reg.registration_icp(
            query,
            surface,
            self.icp_distance,
            invert(rigid),
            reg.TransformationEstimationPointToPlane(),
        )
        pose = invert(np.asarray(refined.transformation))
        pose[:3, :3] *= scale
        return hypothesis, alignment_score(refined, self.ransac_distance), refined, pose

    def _surface(self, model_id: str, scale: float) -> o3d.geometry.PointCloud:
        """The model's surface points with normals (cached), scaled when ``scale`` is not 1."""
        if model_id not in self._surfaces:
            points = self.library[model_id].points.astype(np.float64)
            self._surfaces[model_id] = point_cloud(
                points, normal_radius=2 * self.extractor.voxel_size
            )
        surface = self._surfaces[model_id]
        if abs(scale - 1.0) < 1e-9:
            return surface
        scaled = o3d.geometry.PointCloud(surface)
        scaled.scale(scale, center=np.zeros(3))
        return scaled


def _best_per_model(scored: list[tuple[Hypothesis, float, object, np.ndarray]]) -> list[Candidate]:
    """Each candidate model once, with its best score, best first."""
    best: dict[str, float] = {}
    for hypothesis, score, _, _ in scored:
        best[hypothesis.model_id] = max(score, best.get(hypothesis.model_id, -np.inf))
    return sorted((Candidate(i, s) for i, s in best.items()), key=lambda c: -c.score)


@contextmanager
def _timed(timings: dict[str, float], stage: str) -> Iterator[None]:
    started = time.perf_counter()
    yield
    timings[stage] = (time.perf_counter() - started) * 1e3
