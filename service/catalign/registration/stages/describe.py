"""Describing the query: its key points and features at the headings it is tried at.

Library models share the category's canonical frame (+Y up, :data:`~catalign.frames.MODEL_UP`),
and features trained on ``yaw-bin`` rotations only know headings within half a bin of it. So
the query is described after rotations that level it (its up onto +Y) and turn it about +Y:
the proposed headings of :mod:`~catalign.registration.prepare.orient`, or, without proposals,
:func:`even_headings` (8, 45 degrees apart, for the shipped model; 1 for
rotation-invariant features). The rotations share forward passes, as many per pass as
``pass_voxels`` allows: one pass for a typical view, several for the largest queries, whose
memory they bound (about 5 KB per voxel at the peak of a pass). Key points are turned back,
so every later stage works in the observation frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from catalign.features.extractor import FeatureExtractor
from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller
from catalign.geometry.se3 import axis_angle
from catalign.registration.results import Orientation


def turn_of(orientation: Orientation) -> np.ndarray | None:
    """The levelling turn of an orientation (its up onto the models'); None for a free
    search."""
    return None if orientation.up is None else leveller(orientation.up)


def rotations_of(orientation: Orientation) -> list[np.ndarray]:
    """The rotations (observation -> a heading of the canonical frame) that describe the
    query at each of the orientation's headings."""
    turn = turn_of(orientation)
    turn = np.eye(3) if turn is None else turn
    return [axis_angle(MODEL_UP, -heading) @ turn for heading in orientation.headings]


@dataclass(frozen=True, eq=False)
class QueryView:
    """The query described at one heading; key points are in the observation frame, and
    ``rotation`` (observation -> the canonical frame at that heading) is the one the features
    were computed after."""

    keypoints: np.ndarray
    features: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def canonical_keypoints(self) -> np.ndarray:
        """The key points as the features saw them: turned into the canonical frame."""
        return self.keypoints @ self.rotation.T


def describe(
    extractor: FeatureExtractor,
    points: np.ndarray,
    rotations: list[np.ndarray],
    *,
    voxels: int,
    pass_voxels: int,
) -> list[QueryView]:
    """The query ``points`` (occupying about ``voxels`` voxels) described after each of the
    ``rotations`` (observation -> a heading of the canonical frame, as :func:`rotations_of`
    gives them), key points back in the observation frame, with at most ``pass_voxels`` query
    voxels per forward pass (at least one rotation per pass)."""
    per_pass = max(1, pass_voxels // max(voxels, 1))
    described = []
    for first in range(0, len(rotations), per_pass):
        turned = [points @ r.T for r in rotations[first : first + per_pass]]
        described += extractor.describe_many(turned)
    return [
        QueryView(d.keypoints @ r, d.features, r) for d, r in zip(described, rotations, strict=True)
    ]
