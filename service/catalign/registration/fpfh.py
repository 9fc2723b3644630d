"""Classic baseline: FPFH descriptors in the shared pipeline (Open3D's global registration).

Normals use 2x and FPFH 5x the voxel radius; RANSAC inliers lie within 1.5 voxels, ICP within 1.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from catalign.registration.alignment import point_cloud
from catalign.registration.pipeline import FeatureCloud, FeatureRegistrar


class FPFHRegistrar(FeatureRegistrar):
    """FPFH + mutual matching + RANSAC + ICP against every library model."""

    name = "fpfh"

    def __init__(self, voxel_size: float = 0.025, **kwargs: float) -> None:
        super().__init__(ransac_distance=1.5 * voxel_size, icp_distance=voxel_size, **kwargs)
        self.voxel_size = voxel_size

    def describe(self, points: np.ndarray) -> FeatureCloud:
        cloud = point_cloud(points).voxel_down_sample(self.voxel_size)
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel_size, max_nn=30)
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel_size, max_nn=100)
        )
        return FeatureCloud(
            cloud=cloud, points=np.asarray(cloud.points), features=fpfh.data.T.copy()
        )
