"""The classic recipe's Open3D pieces: point clouds with normals, RANSAC with ICP, and the score.

The query is aligned *onto* the model (query -> model) so that Open3D's fitness is the share of
query points explained by the posed model; for a partial view against a complete model that is
the fair measure. Callers invert the transform to report the model -> observation pose.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

reg = o3d.pipelines.registration


def point_cloud(points: np.ndarray, normal_radius: float | None = None) -> o3d.geometry.PointCloud:
    """An Open3D cloud, with normals estimated within ``normal_radius`` when given."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normal_radius is not None:
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30)
        )
    return cloud


def open3d_ransac(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    matches: np.ndarray,
    distance: float,
    seed: int,
    iterations: int = 100_000,
    confidence: float = 0.999,
) -> np.ndarray:
    """Open3D's correspondence RANSAC (the classic recipe's checkers); source -> target 4x4."""
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_correspondence(
        source,
        target,
        o3d.utility.Vector2iVector(matches.astype(np.int32)),
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            reg.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        reg.RANSACConvergenceCriteria(iterations, confidence),
    )
    return np.asarray(result.transformation)


def ransac_icp(
    query: o3d.geometry.PointCloud,
    model: o3d.geometry.PointCloud,
    matches: np.ndarray,
    ransac_distance: float,
    icp_distance: float,
    seed: int,
    iterations: int = 100_000,
    confidence: float = 0.999,
) -> reg.RegistrationResult:
    """RANSAC on putative matches, then point-to-plane ICP (the model needs normals)."""
    coarse = open3d_ransac(query, model, matches, ransac_distance, seed, iterations, confidence)
    return reg.registration_icp(
        query, model, icp_distance, coarse, reg.TransformationEstimationPointToPlane()
    )


def alignment_score(result: reg.RegistrationResult, inlier_distance: float) -> float:
    """Query inlier fraction, discounted by up to half for the inlier RMSE."""
    rmse = float(result.inlier_rmse) / inlier_distance
    return float(result.fitness) * (1.0 - 0.5 * min(rmse, 1.0))
