"""The upright sweep: a model's pose found from its surface alone, every yaw and shift of a grid."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.levelling import leveller, yaw_rotations
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.registration.assembly import build_sweeper
from catalign.registration.config import EngineConfig
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.surface_checks import SurfaceCheck
from catalign.registration.stages.sweep import Sweeper, closeness_table, sweep_model, sweep_yaws

Z_UP = np.array([0.0, 0.0, 1.0])
DISTANCE = 0.06  # the verification distance of a 3 cm library: two voxels
YAW, SHIFT = 0.9, np.array([0.35, -0.1, 0.8])


@pytest.fixture(scope="module")
def chair_points(box_chair) -> np.ndarray:
    return box_chair.points[::2]


@pytest.fixture
def chair(chair_points, make_entry):
    return make_entry("chair", chair_points)


@pytest.fixture(scope="module")
def view(chair_points) -> np.ndarray:
    """The chair's front half and seat, as a camera in front of it sees about that much."""
    centre = (chair_points.min(axis=0) + chair_points.max(axis=0)) / 2
    return chair_points[(chair_points - centre) @ np.array([0.3, 0.2, -1.0]) > -0.05]


def _levelled(points: np.ndarray) -> np.ndarray:
    """``points`` (model frame, +Y up) under the upright pose ``R(YAW) m + SHIFT``."""
    return points @ yaw_rotations(YAW)[0].T + SHIFT


def test_the_yaws_cover_the_turn_or_the_proposed_headings() -> None:
    assert np.allclose(sweep_yaws((), 5.0, 30.0), np.radians(np.arange(0, 360, 5)))
    assert np.allclose(sweep_yaws((1.0,), 10.0, None), np.radians(np.arange(0, 360, 10)))
    around = np.degrees(sweep_yaws((np.radians(2.0),), 5.0, 10.0))
    assert np.allclose(around, [352, 357, 2, 7, 12])  # centred on the heading, wrapped
    both = np.degrees(sweep_yaws((0.0, np.radians(17.0)), 5.0, 10.0))
    assert np.allclose(both, [350, 355, 0, 5, 10, 17, 22, 27])  # 7 and 12 too near 5 and 10
    assert np.allclose(  # the grid turns with the heading
        np.degrees(sweep_yaws((np.radians(33.0),), 5.0, 10.0)), [23, 28, 33, 38, 43]
    )


def test_the_closeness_table_scores_a_level_as_the_surface_check_scores_its_distance() -> None:
    table = closeness_table(0.001, 0.05)
    gaps = np.arange(256) * 0.001
    assert np.allclose(table[:255], np.clip(1 - (gaps[:255] / 0.05) ** 2, 0, None))
    assert table[0] == 1.0 and table[50] == 0.0 and table[255] == 0.0


def test_a_view_of_a_model_is_found_at_its_yaw_and_shift(chair, view) -> None:
    yaws = sweep_yaws((), 5.0, None)
    found = sweep_model(
        chair.grid,
        chair.bbox_min,
        chair.bbox_max,
        _levelled(view[::8]),
        yaws,
        distance=DISTANCE,
        step_cells=2,
        max_shifts=512,
    )
    best = int(np.argmax(found.scores))
    rotation = yaw_rotations(found.yaws[best])[0]
    assert abs(np.angle(np.exp(1j * (found.yaws[best] - YAW)))) <= np.radians(2.5) + 1e-9
    # x = R (m - shift): the translation is -R shift; within a grid step (1.5 cm) of the truth
    assert np.linalg.norm(-rotation @ found.shifts[best] - SHIFT) < 0.02
    assert found.scores[best] > 0.9
    assert np.sort(found.scores)[-2] < found.scores[best]  # no other yaw is as good
    # the score is the surface check's at that pose, read at whole cells instead of trilinearly
    pose = make_pose(rotation, -rotation @ found.shifts[best])
    reference = SurfaceCheck(chair.grid).explained(_levelled(view[::8]), pose, DISTANCE)[0]
    assert found.scores[best] == pytest.approx(reference, abs=0.05)


def test_a_view_larger_than_the_model_at_every_yaw_gets_no_pose(chair, chair_points) -> None:
    centre = (chair_points.min(axis=0) + chair_points.max(axis=0)) / 2
    larger = (chair_points[::8] - centre) * 1.5 + centre
    found = sweep_model(
        chair.grid,
        chair.bbox_min,
        chair.bbox_max,
        _levelled(larger),
        sweep_yaws((), 5.0, None),
        distance=DISTANCE,
        step_cells=2,
        max_shifts=512,
    )
    assert len(found.yaws) == len(found.shifts) == len(found.scores) == 0


def _sweeper(library, **options) -> Sweeper:
    """The engine's sweeper (its options at their defaults but for ``options``)."""
    config = EngineConfig(sweep={"models": 2} | options)
    return build_sweeper(config, library, distance=DISTANCE)


def test_the_sweepers_poses_are_model_to_observation_poses(
    chair, chair_points, view, make_entry, make_library
) -> None:
    """In a Z-up observation, with the heading proposed near the truth: the best pose is the
    chair's, within a yaw step and a grid step of the true pose; each swept model gives at
    most ``sweep_poses`` distinct poses, without matches."""
    stool = make_entry("stool", chair_points[chair_points[:, 1] < 0.5])
    library = make_library(chair, stool)
    turn = leveller(Z_UP)
    pose = make_pose(turn.T @ yaw_rotations(YAW)[0], np.array([1.0, 0.4, 0.3]))
    observed = transform(view, pose)
    probes = observed[np.random.default_rng(0).permutation(len(observed))]
    query = QueryView(observed, np.zeros((len(observed), 4), dtype=np.float32))
    heading = YAW + np.radians(12.0)  # a proposal a little off
    poses = _sweeper(library).poses(["chair", "stool"], probes, turn, (heading,), query)
    assert 1 <= sum(h.model_id == "chair" for h in poses) <= 2
    assert sum(h.model_id == "stool" for h in poses) <= 2
    assert all(len(h.matches) == 0 and h.view is query for h in poses)
    checks = SurfaceCheck(chair.grid)
    chair_poses = [h for h in poses if h.model_id == "chair"]
    scores = checks.explained(probes[:64], np.stack([h.transform for h in chair_poses]), DISTANCE)
    best = chair_poses[int(np.argmax(scores))].transform
    assert rotation_error_deg(best[:3, :3], pose[:3, :3]) <= 2.5 + 1e-6
    assert np.linalg.norm(best[:3, 3] - pose[:3, 3]) < 0.02
    assert _sweeper(library, models=0).poses(["chair"], probes, turn, (), query) == []


def test_the_yaws_reach_only_the_span_around_the_proposed_heading(
    chair, view, make_library
) -> None:
    """With the heading proposed half a turn off and a 30-degree span, the true yaw is never
    tried: the sweep's poses are all turned far from the truth."""
    library = make_library(chair)
    turn = leveller(Z_UP)
    pose = make_pose(turn.T @ axis_angle(np.array([0, 1.0, 0]), YAW), np.zeros(3))
    observed = transform(view, pose)
    query = QueryView(observed, np.zeros((len(observed), 4), dtype=np.float32))
    poses = _sweeper(library).poses(["chair"], observed[::5], turn, (YAW + np.pi,), query)
    assert poses and all(rotation_error_deg(h.transform[:3, :3], pose[:3, :3]) > 140 for h in poses)
