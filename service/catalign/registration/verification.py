"""Checking pose hypotheses against a model's surface, many at once.

Correspondence inliers measure agreement among feature matches, which for weak cross-instance
features is a noisy vote: a chair seen from behind has nearly the inlier count of the same chair
turned round. The surface itself settles it: under the right pose the observed points lie on
the model. :class:`SurfaceCheck` carries a fixed sample of observed points into the model frame
under every hypothesis and asks a KD-tree of the model surface how far each lands, with the
search cut off at the inlier distance so that a miss costs almost nothing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class SurfaceCheck:
    """A model surface, ready to score poses by how much of an observation they explain."""

    def __init__(self, surface: np.ndarray) -> None:
        self.tree = cKDTree(np.asarray(surface, dtype=np.float64))

    def explained(
        self,
        probes: np.ndarray,
        poses: np.ndarray,
        distance: float,
    ) -> np.ndarray:
        """For each model -> observation pose (H,4,4; rigid or similarity), the mean over
        ``probes`` (observed points) of ``1 - (d / distance)**2``, ``d`` their distance to the
        surface, and 0 beyond ``distance``: the share of the observation explained, softened
        by the fit."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        inverse = np.linalg.inv(poses[:, :3, :3])
        local = np.einsum("hij,hpj->hpi", inverse, probes[None] - poses[:, None, :3, 3])
        gaps, _ = self.tree.query(local.reshape(-1, 3), distance_upper_bound=distance)
        closeness = np.clip(1.0 - (gaps.reshape(len(poses), -1) / distance) ** 2, 0.0, None)
        return closeness.mean(axis=1)


class CoverageCheck:
    """The observation's side of the check: of the model surface that a pose puts inside the
    observed region, the share that was actually observed.

    :class:`SurfaceCheck` alone favours models with surface everywhere: a bulky armchair
    explains any view of a slender chair, at several headings. Surface that lands where the
    sensor looked but found nothing is evidence against the pose. Without the camera the region
    is the observation's bounding box (grown by ``margin``), and surface hidden behind the
    observed side counts against every pose alike, which is why this is a factor in the score and
    not a verdict of its own.
    """

    def __init__(self, observed: np.ndarray, margin: float) -> None:
        observed = np.asarray(observed, dtype=np.float64)
        self.tree = cKDTree(observed)
        self.low = observed.min(axis=0) - margin
        self.high = observed.max(axis=0) + margin

    def covered(self, surface: np.ndarray, poses: np.ndarray, distance: float) -> np.ndarray:
        """For each model -> observation pose (H,4,4), the share of the posed ``surface``
        points inside the observed region that have an observed point within ``distance``
        (0 when none falls inside)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        posed = np.einsum("hij,pj->hpi", poses[:, :3, :3], surface) + poses[:, None, :3, 3]
        inside = np.all((posed >= self.low) & (posed <= self.high), axis=2)
        gaps, _ = self.tree.query(posed[inside], distance_upper_bound=distance)
        near = np.zeros(inside.shape)
        near[inside] = gaps < distance
        counts = inside.sum(axis=1)
        return np.divide(near.sum(axis=1), counts, out=np.zeros(len(poses)), where=counts > 0)
