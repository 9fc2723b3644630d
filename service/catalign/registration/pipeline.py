"""The correspondence-based registration pipeline, whatever the features.

A method is a :class:`~catalign.features.extractor.FeatureExtractor` plus distances;
:class:`FeatureRegistrar` does the rest, for every library model: mutual nearest neighbours in
feature space, RANSAC on them, point-to-plane ICP, and a score; the best-scoring model wins.

Learned features are learned for the orientations they were trained on. A model trained with
``upright`` augmentation expects clouds whose up direction is +Y, as the library models'; given
``up`` (the world direction the chair's up axis points to, gravity's opposite), the query is
turned so that ``up`` becomes +Y before it is described, and its key points are turned back.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from catalign.features.extractor import FeatureExtractor
from catalign.geometry.se3 import invert, rotation_between
from catalign.registration.alignment import (
    alignment_score,
    mutual_matches,
    point_cloud,
    ransac_icp,
)
from catalign.registration.base import Candidate, LibraryShape, Registrar, RegistrationResult

MODEL_UP = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class FeatureCloud:
    """Key points (N,3) as an Open3D cloud with normals, and their descriptors (N,D)."""

    cloud: o3d.geometry.PointCloud
    points: np.ndarray
    features: np.ndarray


class FeatureRegistrar(Registrar):
    """Correspondence-based registration against every library model.

    ``ransac_distance`` and ``icp_distance`` are in metres; ``ransac_distance`` is also the
    inlier distance of the score. ``up``: see the module docstring.
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        *,
        name: str,
        ransac_distance: float,
        icp_distance: float,
        up: np.ndarray | None = None,
        ransac_iterations: int = 100_000,
        confidence: float = 0.999,
    ) -> None:
        self.extractor = extractor
        self.name = name
        self.query_turn = None if up is None else rotation_between(up, MODEL_UP)
        self.ransac_distance = ransac_distance
        self.icp_distance = icp_distance
        self.ransac_iterations = ransac_iterations
        self.confidence = confidence
        self._library: dict[str, FeatureCloud] = {}

    def describe(self, points: np.ndarray, turn: np.ndarray | None = None) -> FeatureCloud:
        """Key points (with normals) and descriptors of ``points`` seen turned by ``turn``."""
        described = self.extractor.describe(points if turn is None else points @ turn.T)
        keypoints = described.keypoints if turn is None else described.keypoints @ turn
        cloud = point_cloud(keypoints, normal_radius=2 * self.extractor.voxel_size)
        return FeatureCloud(cloud=cloud, points=keypoints, features=described.features)

    def prepare(self, library: Sequence[LibraryShape]) -> None:
        """Describe the library models as they are (their up axis is +Y by convention)."""
        self._library = {shape.model_id: self.describe(shape.points) for shape in library}

    def register(self, points: np.ndarray, *, seed: int = 0) -> RegistrationResult:
        if not self._library:
            raise RuntimeError("prepare() the registrar with a library before registering")
        started = time.perf_counter()
        query = self.describe(points, self.query_turn)
        timings = {"features": (time.perf_counter() - started) * 1e3}

        started = time.perf_counter()
        candidates, best = [], None
        for model_id, model in self._library.items():
            matches = mutual_matches(query.features, model.features)
            result = ransac_icp(
                query.cloud,
                model.cloud,
                matches,
                ransac_distance=self.ransac_distance,
                icp_distance=self.icp_distance,
                seed=seed,
                iterations=self.ransac_iterations,
                confidence=self.confidence,
            )
            score = alignment_score(result, self.ransac_distance)
            candidates.append(Candidate(model_id=model_id, score=score))
            if best is None or score > best[0]:
                best = (score, model_id, result, matches)
        timings["match_ransac_icp"] = (time.perf_counter() - started) * 1e3

        _, model_id, result, matches = best
        num_inliers = len(result.correspondence_set)
        return RegistrationResult(
            model_id=model_id,
            pose=invert(np.asarray(result.transformation)),
            fitness=float(result.fitness),
            inlier_rmse=float(result.inlier_rmse),
            num_inliers=num_inliers,
            inlier_ratio=num_inliers / len(query.points),
            candidates=sorted(candidates, key=lambda c: -c.score),
            timings_ms=timings,
            correspondences=(
                query.points[matches[:, 0]],
                self._library[model_id].points[matches[:, 1]],
            ),
        )
