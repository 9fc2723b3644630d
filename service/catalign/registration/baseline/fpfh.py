"""The correspondence-based registration pipeline, whatever the features.

A method is a :class:`~catalign.features.extractor.FeatureExtractor` plus distances;
:class:`FeatureRegistrar` does the rest, for every library model: mutual nearest neighbours in
feature space, RANSAC on them, point-to-plane ICP, and a score; the best-scoring model wins.

It tries every model with Open3D's RANSAC: the classic recipe the FPFH baseline follows. The
learned method uses :mod:`catalign.registration.engine` instead.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from catalign.features.extractor import FeatureExtractor
from catalign.geometry.se3 import invert
from catalign.registration.baseline.open3d_recipe import alignment_score, point_cloud, ransac_icp
from catalign.registration.results import Candidate, LibraryShape, Registrar, RegistrationResult
from catalign.registration.stages.nearest import mutual_nearest


@dataclass(frozen=True)
class FeatureCloud:
    """Key points (N,3) as an Open3D cloud with normals, and their descriptors (N,D)."""

    cloud: o3d.geometry.PointCloud
    points: np.ndarray
    features: np.ndarray


class FeatureRegistrar(Registrar):
    """Correspondence-based registration against every library model.

    ``ransac_distance`` and ``icp_distance`` are in metres; ``ransac_distance`` is also the
    inlier distance of the score.
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        *,
        name: str,
        ransac_distance: float,
        icp_distance: float,
        ransac_iterations: int = 100_000,
        confidence: float = 0.999,
    ) -> None:
        self.extractor = extractor
        self.name = name
        self.ransac_distance = ransac_distance
        self.icp_distance = icp_distance
        self.ransac_iterations = ransac_iterations
        self.confidence = confidence
        self._library: dict[str, FeatureCloud] = {}

    def describe(self, points: np.ndarray) -> FeatureCloud:
        """Key points (with normals) and descriptors of ``points``."""
        described = self.extractor.describe(points)
        cloud = point_cloud(described.keypoints, normal_radius=2 * self.extractor.voxel_size)
        return FeatureCloud(cloud=cloud, points=described.keypoints, features=described.features)

    def prepare(self, library: Sequence[LibraryShape]) -> None:
        self._library = {shape.model_id: self.describe(shape.points) for shape in library}

    def register(
        self, points: np.ndarray, *, seed: int = 0, category: str | None = None
    ) -> RegistrationResult:
        """The classic recipe against every model (its library holds one category: the
        evaluation's, so ``category`` changes nothing)."""
        if not self._library:
            raise RuntimeError("prepare() the registrar with a library before registering")
        started = time.perf_counter()
        query = self.describe(points)
        timings = {"features": (time.perf_counter() - started) * 1e3}

        started = time.perf_counter()
        candidates, best = [], None
        for model_id, model in self._library.items():
            matches = mutual_nearest(query.features, model.features)
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
