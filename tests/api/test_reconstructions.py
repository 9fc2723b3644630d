"""Reconstructions as a mapping robot sends them, through a real server with the shipped model,
the default library and the SDK: a loose cut-out of a library chair, and the same with what a
loose segmentation or a map adds (a wall behind it, a wide floor patch, a neighbour touching it,
a loop-closure ghost of the whole surface). Each must either get the chair's model and pose
back, with what was not the chair set aside and counted, or a clear 422; never a 500.

A wall behind the chair and a neighbour touching it are not handled yet: the wall draws the
answer to another model (proc-0059), the neighbour pulls the right model 28 cm off. Those two
are strict expected failures, so that the day they pass the test says so.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from catalign.data.reconstruction import Reconstruction, reconstruct
from catalign.data.shapes import procedural_id, procedural_shape
from catalign.data.views import random_object_pose
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign_client import AlignResult, Client, InvalidInputError

SEED = 7  # proc-0007, a chair of the default library
BASE = Reconstruction(neighbour_gap=None, floor_kept=0.0)
VARIANTS = {
    "loose cut": BASE,
    "wall behind": replace(BASE, wall_gap=(0.02, 0.05), margin=(0.15, 0.2)),
    "wide floor patch": replace(BASE, floor_kept=1.0, margin=(0.5, 0.6)),
    "neighbour touching": replace(BASE, neighbour_gap=(0.0, 0.01), margin=(0.3, 0.4)),
}
NOT_YET = pytest.mark.xfail(strict=True, reason="the wall or neighbour is not set aside yet")


@pytest.fixture(scope="module")
def pose() -> np.ndarray:
    shape = procedural_shape(SEED)
    return random_object_pose(np.random.default_rng(3), "upright", height=shape.height / 2)


def fused(config: Reconstruction, pose: np.ndarray) -> np.ndarray:
    return reconstruct(procedural_shape(SEED), pose, np.random.default_rng(5), config).points


def assert_chair_back(result: AlignResult, pose: np.ndarray) -> None:
    assert result.model_id == procedural_id(SEED)
    assert rotation_error_deg(result.rotation, pose[:3, :3]) < 10.0
    assert np.linalg.norm(result.translation - pose[:3, 3]) < 0.05


@pytest.mark.slow
@pytest.mark.parametrize(
    "variant",
    [
        pytest.param(v, marks=NOT_YET) if v in ("wall behind", "neighbour touching") else v
        for v in VARIANTS
    ],
)
def test_a_reconstruction_gets_its_chair_back_with_the_rest_set_aside(
    shipped_client: Client, pose: np.ndarray, variant: str
):
    points = fused(VARIANTS[variant], pose)
    result = shipped_client.align(points, up=(0, 0, 1), seed=0)
    assert_chair_back(result, pose)
    if variant == "wide floor patch":
        assert result.points_set_aside > 0


@pytest.mark.slow
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_what_a_loose_cut_adds_gets_an_answer_or_a_clear_422(
    shipped_client: Client, pose: np.ndarray, variant: str
):
    try:
        result = shipped_client.align(fused(VARIANTS[variant], pose), up=(0, 0, 1), seed=0)
    except InvalidInputError as error:
        assert error.status_code == 422 and error.message
    else:
        assert result.model_id and result.fitness > 0


@pytest.mark.slow
def test_a_loop_closure_ghost_does_not_move_the_answer(shipped_client: Client, pose: np.ndarray):
    """The whole fused surface twice, the second copy 2 degrees and 3 cm off (a map whose loop
    closed late): the answer lies on one of the two layers."""
    points = fused(BASE, pose)
    centre = points.mean(axis=0)
    ghost = make_pose(axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(2.0)), np.zeros(3))
    ghost[:3, 3] = centre - ghost[:3, :3] @ centre + np.array([0.03, 0.0, 0.0])
    result = shipped_client.align(
        np.vstack([points, transform(points, ghost)]), up=(0, 0, 1), seed=0
    )
    assert result.model_id == procedural_id(SEED)
    assert (
        min(rotation_error_deg(result.rotation, layer[:3, :3]) for layer in (pose, ghost @ pose))
        < 10.0
    )
