"""The describe stage: headings about the models' up, few forward passes, observation frame."""

from __future__ import annotations

from collections.abc import Sequence
from types import MappingProxyType

import numpy as np
import pytest

from catalign.features.extractor import Described
from catalign.frames import MODEL_UP
from catalign.geometry.levelling import even_headings
from catalign.geometry.se3 import axis_angle, rotation_error_deg
from catalign.registration.prepare.validation import CheckedCloud
from catalign.registration.results import Orientation
from catalign.registration.stages.describe import describe, rotations_of


class RecordingExtractor:
    """Key points are the given points; each point's feature is its position as the extractor
    saw it (turned). Records the clouds of every forward pass."""

    voxel_size = 0.05
    fingerprint = "recording"
    headings = 1
    orientation = None
    category_orientations = MappingProxyType({})
    retrieval = None

    def __init__(self) -> None:
        self.passes: list[int] = []

    def describe(self, points: np.ndarray) -> Described:
        return self.describe_many([points])[0]

    def describe_many(self, clouds: Sequence[np.ndarray]) -> list[Described]:
        self.passes.append(len(clouds))
        return [Described(c.copy(), c.astype(np.float32)) for c in clouds]


def _cloud(voxels: int = 100) -> CheckedCloud:
    points = np.random.default_rng(0).uniform(-0.3, 0.3, (voxels, 3))
    return CheckedCloud(points=points, received=voxels, set_aside=0, voxels=voxels)


def heading_turns(turn_up: np.ndarray | None, count: int) -> list[np.ndarray]:
    return rotations_of(Orientation(turn_up, turn_up is not None, even_headings(count)))


def test_headings_are_even_turns_about_the_models_up() -> None:
    turns = heading_turns(None, 4)
    assert len(turns) == 4
    for k, rotation in enumerate(turns):
        assert np.allclose(rotation @ MODEL_UP, MODEL_UP)
        assert rotation_error_deg(rotation, axis_angle(MODEL_UP, -np.pi / 2 * k)) < 1e-6


def test_every_heading_takes_the_given_up_onto_the_models_up() -> None:
    up = np.array([0.3, -0.2, 1.0])
    for rotation in heading_turns(up, 8):
        assert np.allclose(rotation @ (up / np.linalg.norm(up)), MODEL_UP)


@pytest.mark.parametrize(
    ("pass_voxels", "passes"), [(32_000, [8]), (250, [2, 2, 2, 2]), (1, [1] * 8)]
)
def test_headings_share_as_few_passes_as_the_voxel_budget_allows(
    pass_voxels: int, passes: list[int]
) -> None:
    extractor = RecordingExtractor()
    cloud = _cloud(100)
    views = describe(
        extractor, cloud.points, heading_turns(None, 8), voxels=100, pass_voxels=pass_voxels
    )
    assert extractor.passes == passes
    assert len(views) == 8


def test_key_points_come_back_in_the_observation_frame() -> None:
    cloud = _cloud()
    rotations = heading_turns(np.array([0.0, 0.0, 1.0]), 3)
    views = describe(RecordingExtractor(), cloud.points, rotations, voxels=100, pass_voxels=32_000)
    for view, rotation in zip(views, rotations, strict=True):
        assert np.allclose(view.keypoints, cloud.points)
        # the features saw the cloud turned to that heading
        assert np.allclose(view.features, cloud.points @ rotation.T, atol=1e-6)
