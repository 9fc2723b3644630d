"""Training pairs: two voxelised clouds and the voxel pairs that should match.

* **same-instance**: a noisy partial view of shape A against the full CAD of A; positives are
  voxels within ``tau`` of each other once the view is carried back by its known pose.
* **cross-instance**: a view (or the CAD) of A against the CAD of one of A's EMD neighbours B;
  both are mapped into NCC, where corresponding parts of different chairs land near each other,
  and positives are voxels within the enlarged ``tau_ncc``.

Both inputs get an independent random rotation (augmentation), so the features learn to ignore
orientation: ``upright`` rotations (any yaw about the up axis, tilted by at most 10 degrees)
for a robot that knows gravity, ``yaw-bin`` rotations (yaw within +-22.5 degrees of the
canonical heading, same tilt: the query is then tried at 8 headings, 45 degrees apart),
``yaw-quarter`` (+-45 degrees: 4 headings, half the query's feature cost), or any rotation
(``so3``). Each sample keeps the *aligned* position of every voxel (the frame
positives were found in), which the loss uses to pick negatives far from any positive.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from catalign.data.camera import random_camera
from catalign.data.shapes import Shape
from catalign.data.views import random_object_pose, render_view
from catalign.features.weights import YAW_BINS
from catalign.frames import MODEL_UP
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.sampling import subsample, voxel_grid
from catalign.geometry.se3 import axis_angle, invert, random_rotation, transform

PairKind = Literal["same", "cross"]
RotationMode = Literal["upright", "yaw-bin", "yaw-quarter", "so3"]


def augmentation_rotation(
    rng: np.random.Generator, mode: RotationMode, max_tilt_deg: float = 10.0
) -> np.ndarray:
    """A random rotation: yaw about +Y with a small tilt (any yaw for ``upright``, within half a
    bin of :data:`YAW_BINS` for the binned modes), or uniform (``so3``)."""
    if mode == "so3":
        return random_rotation(rng)
    max_yaw = np.pi / YAW_BINS.get(mode, 1)
    heading = rng.uniform(0, 2 * np.pi)
    tilt_axis = np.array([np.cos(heading), 0.0, np.sin(heading)])
    tilt = axis_angle(tilt_axis, np.radians(rng.uniform(0, max_tilt_deg)))
    return tilt @ axis_angle(MODEL_UP, rng.uniform(-max_yaw, max_yaw))


@dataclass(frozen=True)
class VoxelCloud:
    """Network input for one cloud: voxel keys, and each voxel's position in the aligned frame."""

    coords: np.ndarray
    aligned: np.ndarray


@dataclass(frozen=True)
class PairSample:
    """Two clouds and their positive voxel pairs ``(i in a, j in b)``."""

    a: VoxelCloud
    b: VoxelCloud
    positives: np.ndarray
    kind: PairKind
    neg_radius: float


def voxel_cloud(points: np.ndarray, aligned: np.ndarray, voxel_size: float) -> VoxelCloud:
    """Voxelise ``points`` (the network's view) and average ``aligned`` per voxel."""
    keys, _, inverse = voxel_grid(points, voxel_size)
    counts = np.bincount(inverse, minlength=len(keys))[:, None]
    sums = np.stack(
        [np.bincount(inverse, weights=aligned[:, k], minlength=len(keys)) for k in range(3)],
        axis=1,
    )
    return VoxelCloud(coords=keys, aligned=sums / counts)


def positive_pairs(
    a: np.ndarray, b: np.ndarray, tau: float, limit: int, rng: np.random.Generator
) -> np.ndarray:
    """Pairs (i, j): ``b[j]`` is the nearest point of ``b`` to ``a[i]`` and closer than ``tau``."""
    distance, nearest = cKDTree(b).query(a, distance_upper_bound=tau)
    rows = np.flatnonzero(np.isfinite(distance))
    pairs = np.stack([rows, nearest[rows]], axis=1)
    if len(pairs) > limit:
        pairs = pairs[rng.choice(len(pairs), size=limit, replace=False)]
    return pairs


class PairSampler:
    """Draws same- and cross-instance pairs from metric shapes and their EMD neighbours.

    ``tau`` (metres) is the same-instance positive radius; ``tau_ncc`` the cross-instance one in
    NCC units (a chair's bounding-box diagonal is 1). Negatives are pairs farther apart than
    ``neg_factor`` times the positive radius.
    """

    def __init__(
        self,
        shapes: Mapping[str, Shape],
        neighbours: Mapping[str, Sequence[str]],
        voxel_size: float,
        tau: float | None = None,
        tau_ncc: float = 0.04,
        neg_factor: float = 2.0,
        max_positives: int = 1024,
        cad_points: int = 10_000,
        view_probability: float = 0.8,
        rotation: RotationMode = "upright",
        view_so3_share: float = 0.0,
    ) -> None:
        self.shapes = shapes
        self.neighbours = neighbours
        self.voxel_size = voxel_size
        self.tau = 1.5 * voxel_size if tau is None else tau
        self.tau_ncc = tau_ncc
        self.neg_factor = neg_factor
        self.max_positives = max_positives
        self.cad_points = cad_points
        self.view_probability = view_probability
        self.rotation = rotation
        self.view_so3_share = view_so3_share
        self.frames = {i: NCCFrame.fit(s.points) for i, s in shapes.items()}

    def sample(self, kind: PairKind, shape_id: str, rng: np.random.Generator) -> PairSample:
        if kind == "same":
            return self.same_instance(shape_id, rng)
        return self.cross_instance(shape_id, rng)

    def same_instance(self, shape_id: str, rng: np.random.Generator) -> PairSample:
        """A partial view of the shape against its own CAD."""
        view, canonical = self._view(shape_id, rng)
        cad = self._cad(shape_id, rng)
        return self._pair(view, canonical, cad, cad, self.tau, "same", rng)

    def cross_instance(self, shape_id: str, rng: np.random.Generator) -> PairSample:
        """A view (or the CAD) of the shape against the CAD of a random EMD neighbour, in NCC."""
        other = str(rng.choice(list(self.neighbours[shape_id])))
        if rng.random() < self.view_probability:
            points, canonical = self._view(shape_id, rng)
        else:
            points = canonical = self._cad(shape_id, rng)
        cad = self._cad(other, rng)
        return self._pair(
            points,
            self.frames[shape_id].to_ncc(canonical),
            cad,
            self.frames[other].to_ncc(cad),
            self.tau_ncc,
            "cross",
            rng,
        )

    def _view(self, shape_id: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A noisy partial view of the shape, carried back into the shape's canonical frame (the
        augmentation rotation then places it). The shape stands upright, so the camera looks
        down on it, except for ``view_so3_share`` of the views, where it lies in any rotation:
        a low or hand-held sensor sees a chair from below or from its side."""
        shape = self.shapes[shape_id]
        # No draw at share 0: runs without the option see the pairs they always did.
        so3 = self.view_so3_share > 0 and rng.random() < self.view_so3_share
        pose = random_object_pose(rng, "so3" if so3 else "upright", height=shape.height / 2)
        camera = random_camera(pose[:3, 3], rng)
        view = transform(
            subsample(render_view(shape, pose, camera, rng), 20_000, rng), invert(pose)
        )
        return view, view

    def _cad(self, shape_id: str, rng: np.random.Generator) -> np.ndarray:
        return subsample(self.shapes[shape_id].points, self.cad_points, rng)

    def _pair(
        self,
        points_a: np.ndarray,
        aligned_a: np.ndarray,
        points_b: np.ndarray,
        aligned_b: np.ndarray,
        tau: float,
        kind: PairKind,
        rng: np.random.Generator,
    ) -> PairSample:
        """Rotate each input at random, voxelise, and find positives in the aligned frame."""
        rotate_a = augmentation_rotation(rng, self.rotation)
        rotate_b = augmentation_rotation(rng, self.rotation)
        a = voxel_cloud(points_a @ rotate_a.T, aligned_a, self.voxel_size)
        b = voxel_cloud(points_b @ rotate_b.T, aligned_b, self.voxel_size)
        positives = positive_pairs(a.aligned, b.aligned, tau, self.max_positives, rng)
        return PairSample(a, b, positives, kind, neg_radius=self.neg_factor * tau)
