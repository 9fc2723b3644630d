"""Classic baseline: FPFH features, mutual nearest neighbours, RANSAC and ICP with Open3D.

Every library model is tried; the one with the best score wins. The score is the fraction of
*query* points that lie within the inlier distance of the posed model (fair to partial views: a
partial query is fully explained by its complete model), discounted by the inlier RMSE.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from catalign.geometry.se3 import invert
from catalign.registration.base import Candidate, LibraryShape, Registrar, RegistrationResult

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class FPFHCloud:
    """A voxel-down-sampled cloud with normals and its FPFH descriptors (N,33)."""

    cloud: o3d.geometry.PointCloud
    points: np.ndarray
    features: np.ndarray


def mutual_matches(query: np.ndarray, model: np.ndarray, min_mutual: int = 30) -> np.ndarray:
    """Index pairs (i, j) of feature nearest neighbours, mutual when there are enough of them."""
    forward = cKDTree(model).query(query, workers=-1)[1]
    backward = cKDTree(query).query(model, workers=-1)[1]
    mutual = np.flatnonzero(backward[forward] == np.arange(len(query)))
    if len(mutual) >= min_mutual:
        return np.stack([mutual, forward[mutual]], axis=1)
    return np.stack([np.arange(len(query)), forward], axis=1)


class FPFHRegistrar(Registrar):
    """FPFH + RANSAC + ICP against every library model (Open3D's global registration recipe).

    Parameters: ``voxel_size`` (metres) for down-sampling; normals use 2x and FPFH 5x that
    radius; RANSAC inliers within 1.5 voxels; ICP within 1 voxel.
    """

    name = "fpfh"

    def __init__(
        self, voxel_size: float = 0.025, ransac_iterations: int = 100_000, confidence: float = 0.999
    ) -> None:
        self.voxel_size = voxel_size
        self.ransac_iterations = ransac_iterations
        self.confidence = confidence
        self._library: list[tuple[str, FPFHCloud]] = []

    def describe(self, points: np.ndarray) -> FPFHCloud:
        """Down-sample, estimate normals and compute FPFH for a cloud."""
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud = cloud.voxel_down_sample(self.voxel_size)
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel_size, max_nn=30)
        )
        fpfh = reg.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel_size, max_nn=100)
        )
        return FPFHCloud(cloud=cloud, points=np.asarray(cloud.points), features=fpfh.data.T.copy())

    def prepare(self, library: Sequence[LibraryShape]) -> None:
        self._library = [(shape.model_id, self.describe(shape.points)) for shape in library]

    def register(self, points: np.ndarray, *, seed: int = 0) -> RegistrationResult:
        if not self._library:
            raise RuntimeError("prepare() the registrar with a library before registering")
        started = time.perf_counter()
        query = self.describe(points)
        timings = {"features": (time.perf_counter() - started) * 1e3}

        best: tuple[float, str, reg.RegistrationResult, np.ndarray] | None = None
        candidates = []
        started = time.perf_counter()
        for model_id, model in self._library:
            matches = mutual_matches(query.features, model.features)
            result = self._align(query, model, matches, seed)
            score = self._score(result)
            candidates.append(Candidate(model_id=model_id, score=score))
            if best is None or score > best[0]:
                best = (score, model_id, result, matches)
        timings["match_ransac_icp"] = (time.perf_counter() - started) * 1e3
        assert best is not None
        _, model_id, result, matches = best
        model_points = dict(self._library)[model_id].points
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
            correspondences=(query.points[matches[:, 0]], model_points[matches[:, 1]]),
        )

    def _align(
        self, query: FPFHCloud, model: FPFHCloud, matches: np.ndarray, seed: int
    ) -> reg.RegistrationResult:
        """RANSAC on the matches, then point-to-plane ICP; query -> model direction."""
        o3d.utility.random.seed(seed)
        distance = 1.5 * self.voxel_size
        coarse = reg.registration_ransac_based_on_correspondence(
            query.cloud,
            model.cloud,
            o3d.utility.Vector2iVector(matches.astype(np.int32)),
            distance,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [
                reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                reg.CorrespondenceCheckerBasedOnDistance(distance),
            ],
            reg.RANSACConvergenceCriteria(self.ransac_iterations, self.confidence),
        )
        return reg.registration_icp(
            query.cloud,
            model.cloud,
            self.voxel_size,
            coarse.transformation,
            reg.TransformationEstimationPointToPlane(),
        )

    def _score(self, result: reg.RegistrationResult) -> float:
        """Query inlier fraction, discounted by up to half for inlier RMSE."""
        rmse = float(result.inlier_rmse) / self.voxel_size
        return float(result.fitness) * (1.0 - 0.5 * min(rmse, 1.0))
