"""Describing the query: its key points and features at every heading the features need.

Library models share the category's canonical frame (+Y up, :data:`~catalign.frames.MODEL_UP`),
and features trained on ``yaw-bin`` rotations only know headings within half a bin of it. So
the query is first turned so that the caller's ``up`` becomes +Y (a :func:`leveller` turn; no
turn without ``up``) and then described at ``headings`` headings about +Y, evenly spaced (8,
45 degrees apart, for the shipped model; 1 for rotation-invariant features). The headings
share forward passes, as many per pass as ``pass_voxels`` allows: one pass for a typical view,
several for the largest queries, whose memory they bound (about 5 KB per voxel at the peak of
a pass). Key points are turned back, so every later stage works in the observation frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.features.extractor import FeatureExtractor
from catalign.frames import MODEL_UP
from catalign.geometry.se3 import axis_angle
from catalign.registration.validation import CheckedCloud


@dataclass(frozen=True)
class QueryView:
    """The query described at one heading; key points are in the observation frame."""

    keypoints: np.ndarray
    features: np.ndarray


def heading_turns(turn: np.ndarray | None, headings: int) -> list[np.ndarray]:
    """The rotations that take the observation to each heading: ``turn`` (the levelling, or
    none), then ``k / headings`` of a full turn about the models' up, for each ``k``."""
    turn = np.eye(3) if turn is None else turn
    return [axis_angle(MODEL_UP, -2 * np.pi * k / headings) @ turn for k in range(headings)]


def describe(
    extractor: FeatureExtractor,
    cloud: CheckedCloud,
    turn: np.ndarray | None,
    *,
    headings: int,
    pass_voxels: int,
) -> list[QueryView]:
    """The query described at every heading (:func:`heading_turns`), key points back in the
    observation frame, with at most ``pass_voxels`` query voxels per forward pass (at least
    one heading per pass)."""
    rotations = heading_turns(turn, headings)
    per_pass = max(1, pass_voxels // cloud.voxels)
    described = []
    for first in range(0, len(rotations), per_pass):
        turned = [cloud.points @ r.T for r in rotations[first : first + per_pass]]
        described += extractor.describe_many(turned)
    return [
        QueryView(d.keypoints @ r, d.features) for d, r in zip(described, rotations, strict=True)
    ]
