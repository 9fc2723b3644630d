"""Refinement: coarse-to-fine point-to-plane ICP of the query onto a candidate's surface.

A hypothesis from two or three matches can be a few degrees off, which moves a chair's far side
further than one ICP distance; so ICP runs twice, within 3 and then 1 times ``distance``
(:data:`ICP_SCHEDULE`), from the hypothesis. The query is aligned *onto* the model (query ->
model, as in :mod:`~catalign.registration.alignment`) so that Open3D's fitness is the share of
the query the posed model explains; poses are reported model -> observation. A similarity pose
(``estimate_scale``) is refined rigidly against the model scaled by its scale. Each model's
surface, with normals, is built once and cached.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field, replace

import numpy as np
import open3d as o3d

from catalign.geometry.se3 import invert, split_scale
from catalign.library.index import Library
from catalign.registration.alignment import point_cloud
from catalign.registration.hypothesise import Hypothesis

reg = o3d.pipelines.registration
# ICP distances, in multiples of the ICP distance: coarse first, then fine.
ICP_SCHEDULE = (3.0, 1.0)


@dataclass(eq=False)
class Refiner:
    """ICP against ``library`` models' surfaces, each built once (with normals) and cached.

    ``distance`` is the ICP inlier distance (metres, the fine one); ``normal_radius`` the radius
    the models' surface normals are estimated within.
    """

    library: Library
    _: KW_ONLY
    distance: float
    normal_radius: float
    _surfaces: dict[str, o3d.geometry.PointCloud] = field(
        default_factory=dict, init=False, repr=False
    )

    def refine(self, hypothesis: Hypothesis, query: o3d.geometry.PointCloud) -> Hypothesis:
        """The hypothesis with its pose refined by ICP (its scale, if any, kept). The refined
        pose is kept even when it scores a little lower: a soft score rewards a slightly wrong
        pose about as much as the right one, ICP does not."""
        rigid, scale = split_scale(hypothesis.transform)
        pose = self.icp(query, hypothesis.model_id, scale, rigid)
        pose[:3, :3] *= scale
        return replace(hypothesis, transform=pose)

    def icp(
        self, query: o3d.geometry.PointCloud, model_id: str, scale: float, start: np.ndarray
    ) -> np.ndarray:
        """Point-to-plane ICP of the query onto the model surface (scaled by ``scale`` about
        the origin) from the rigid model -> observation pose ``start``; the refined rigid pose.
        """
        surface = self.surface(model_id, scale)
        current = invert(start)
        for factor in ICP_SCHEDULE:
            current = reg.registration_icp(
                query,
                surface,
                factor * self.distance,
                current,
                reg.TransformationEstimationPointToPlane(),
            ).transformation
        return invert(np.asarray(current))

    def fit(self, hypothesis: Hypothesis, query: o3d.geometry.PointCloud) -> reg.RegistrationResult:
        """Open3D's fitness and inlier RMSE of the query on the model under the pose."""
        rigid, scale = split_scale(hypothesis.transform)
        return reg.evaluate_registration(
            query, self.surface(hypothesis.model_id, scale), self.distance, invert(rigid)
        )

    def surface(self, model_id: str, scale: float = 1.0) -> o3d.geometry.PointCloud:
        """The model's surface points with normals (cached), scaled about the origin when
        ``scale`` is not 1."""
        if model_id not in self._surfaces:
            points = self.library[model_id].points.astype(np.float64)
            self._surfaces[model_id] = point_cloud(points, normal_radius=self.normal_radius)
        surface = self._surfaces[model_id]
        if abs(scale - 1.0) < 1e-9:
            return surface
        scaled = o3d.geometry.PointCloud(surface)
        scaled.scale(scale, center=np.zeros(3))
        return scaled
