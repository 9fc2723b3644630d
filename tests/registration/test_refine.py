"""The refine stage: coarse-to-fine ICP from a rough pose, scale kept, surfaces cached; Open3D's
ICP and fit statistics are the reference it is checked against."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import axis_angle, invert, make_pose, rotation_error_deg, transform
from catalign.registration.baseline.open3d_recipe import point_cloud
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.refine import ICP_SCHEDULE, Refiner, may_be_within

reg = o3d.pipelines.registration
POSE = make_pose(axis_angle(np.array([0.1, 1.0, 0.2]), 0.9), np.array([0.3, -0.1, 1.1]))
# a two-point hypothesis a few degrees and centimetres off
NUDGE = make_pose(axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(4.0)), np.array([0.02, 0, 0]))
DISTANCE = 0.03


@pytest.fixture
def library(box_chair, make_entry, make_library):
    return make_library(make_entry("chair", box_chair.points))


@pytest.fixture
def refiner(library) -> Refiner:
    return Refiner(library, distance=DISTANCE, icp_iterations=30, icp_points=None)


def _observe(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    keypoints, _ = voxel_downsample(transform(points, pose), DISTANCE)
    return keypoints


def _hypothesis(pose: np.ndarray, keypoints: np.ndarray) -> Hypothesis:
    view = QueryView(keypoints, np.zeros((len(keypoints), 4), dtype=np.float32))
    return Hypothesis("chair", pose, np.zeros((0, 2), dtype=np.int64), view)


def _open3d_icp(points: np.ndarray, keypoints: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The reference: Open3D's point-to-plane ICP on the same schedule (model -> observation)."""
    surface = point_cloud(points, normal_radius=2 * DISTANCE)
    current = invert(start)
    for factor in ICP_SCHEDULE:
        current = reg.registration_icp(
            point_cloud(keypoints),
            surface,
            factor * DISTANCE,
            current,
            reg.TransformationEstimationPointToPlane(),
        ).transformation
    return invert(np.asarray(current))


def test_a_rough_pose_is_refined_onto_the_surface(refiner: Refiner, box_chair) -> None:
    keypoints = _observe(box_chair.points, POSE)
    rough = _hypothesis(NUDGE @ POSE, keypoints)
    refined = refiner.refine(rough, keypoints)
    assert rotation_error_deg(refined.transform[:3, :3], POSE[:3, :3]) < 0.5
    assert np.linalg.norm(refined.transform[:3, 3] - POSE[:3, 3]) < 0.005
    assert refined.view is rough.view and refined.model_id == "chair"
    assert refiner.fit(refined, keypoints).fitness > 0.95
    assert refiner.fit(rough, keypoints).fitness < refiner.fit(refined, keypoints).fitness


@pytest.mark.parametrize("seed", range(4))
def test_icp_lands_where_open3d_icp_lands(refiner: Refiner, box_chair, seed: int) -> None:
    """From random starts 6 degrees and 3 cm off, both ICPs end on the same pose."""
    rng = np.random.default_rng(seed)
    keypoints = _observe(box_chair.points, POSE)
    nudge = make_pose(axis_angle(rng.normal(size=3), np.radians(6.0)), rng.normal(size=3) * 0.017)
    ours = refiner.refine(_hypothesis(nudge @ POSE, keypoints), keypoints).transform
    reference = _open3d_icp(box_chair.points, keypoints, nudge @ POSE)
    assert rotation_error_deg(ours[:3, :3], reference[:3, :3]) < 0.5
    assert np.linalg.norm(ours[:3, 3] - reference[:3, 3]) < 0.005


@pytest.mark.parametrize("seed", range(6))
def test_the_fit_statistics_are_open3ds(refiner: Refiner, box_chair, seed: int) -> None:
    """Fitness, inlier RMSE and inlier count as Open3D's ``evaluate_registration`` gives them,
    on poses from exact to a few centimetres off, and (seeds 4, 5) far enough off that the
    distance grid sets most of the query aside before the KD-tree."""
    rng = np.random.default_rng(seed)
    keypoints = _observe(box_chair.points, POSE)
    degrees, metres = (3.0 * seed, 0.01 * seed) if seed < 4 else (10.0 * seed, 0.05 * seed)
    off = make_pose(
        axis_angle(rng.normal(size=3), np.radians(degrees)), rng.normal(size=3) * metres
    )
    ours = refiner.fit(_hypothesis(off @ POSE, keypoints), keypoints)
    reference = reg.evaluate_registration(
        point_cloud(keypoints), point_cloud(box_chair.points), DISTANCE, invert(off @ POSE)
    )
    assert abs(ours.num_inliers - len(reference.correspondence_set)) <= 1
    assert ours.fitness == pytest.approx(reference.fitness, abs=1.5 / len(keypoints))
    assert ours.inlier_rmse == pytest.approx(reference.inlier_rmse, rel=1e-3)


def test_a_similarity_pose_keeps_its_scale(refiner: Refiner, box_chair) -> None:
    scaled = POSE.copy()
    scaled[:3, :3] *= 1.1
    keypoints = _observe(box_chair.points, scaled)
    start = NUDGE @ POSE
    start[:3, :3] *= 1.1
    refined = refiner.refine(_hypothesis(start, keypoints), keypoints)
    assert np.cbrt(np.linalg.det(refined.transform[:3, :3])) == pytest.approx(1.1, rel=1e-9)
    assert rotation_error_deg(refined.transform[:3, :3] / 1.1, POSE[:3, :3]) < 0.5
    assert np.linalg.norm(refined.transform[:3, 3] - POSE[:3, 3]) < 0.005
    assert refiner.fit(refined, keypoints).fitness > 0.95


def test_icp_against_a_scaled_surface_is_icp_against_the_scaled_points(
    refiner: Refiner, box_chair
) -> None:
    """``icp`` with a scale aligns to the surface scaled about the origin (the category fit's
    refit), as Open3D's ICP does against those scaled points."""
    keypoints = _observe(box_chair.points * 1.2, POSE)
    ours = refiner.icp(keypoints, "chair", 1.2, NUDGE @ POSE)
    reference = _open3d_icp(box_chair.points * 1.2, keypoints, NUDGE @ POSE)
    assert rotation_error_deg(ours[:3, :3], reference[:3, :3]) < 0.5
    assert np.linalg.norm(ours[:3, 3] - reference[:3, 3]) < 0.005
    assert np.linalg.norm(ours[:3, 3] - POSE[:3, 3]) < 0.005


def test_a_subset_of_the_query_refines_as_well(library, box_chair) -> None:
    """150 of the query's points."""
    keypoints = _observe(box_chair.points, POSE)
    few = Refiner(
        library,
        distance=DISTANCE,
        icp_iterations=30,
        icp_points=150,
    )
    assert len(keypoints) > 300
    refined = few.refine(_hypothesis(NUDGE @ POSE, keypoints), keypoints)
    assert rotation_error_deg(refined.transform[:3, :3], POSE[:3, :3]) < 1.0
    assert np.linalg.norm(refined.transform[:3, 3] - POSE[:3, 3]) < 0.008


def test_surfaces_are_built_once_with_normals(refiner: Refiner) -> None:
    surface = refiner.surface("chair")
    assert refiner.surface("chair") is surface
    normals = surface.cloud.normals()[:, :3]
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert np.allclose(surface.cloud.points()[:, :3], refiner.library["chair"].points, atol=1e-6)


@pytest.mark.parametrize("distance", [0.01, 0.025, 0.05])
def test_the_grid_never_rules_out_a_point_within_the_distance(
    library, box_chair, distance: float
) -> None:
    """Against exact nearest distances (a KD-tree) on points scattered in and around the chair,
    down to a millimetre from the threshold: every point within it may be."""
    from scipy.spatial import cKDTree

    grid = library["chair"].grid
    rng = np.random.default_rng(1)
    surface = box_chair.points[rng.choice(len(box_chair.points), 4000)]
    points = surface + rng.normal(size=surface.shape) * rng.uniform(0.0, 0.1, (len(surface), 1))
    exact, _ = cKDTree(library["chair"].points).query(points)
    flagged = may_be_within(grid, points, distance)
    assert flagged[exact < distance].all()
    assert (exact < distance).sum() > 500 and (~flagged).sum() > 500  # both sides are tested


@pytest.mark.parametrize(
    "seed",
    [
        0,
        1,
        pytest.param(
            2,
            marks=pytest.mark.xfail(
                strict=True,
                reason="from this start the ICP ends 1.2 degrees from its landing from the truth",
            ),
        ),
    ],
)
def test_the_engines_icp_converges_from_10_degrees_and_5_cm_off(
    make_entry, make_library, seed: int
) -> None:
    """A rendered, noisy view of a library chair (the default library's procedural chairs), a
    start turned 10 degrees about a random axis through the chair and shifted 5 cm: the
    engine's ICP (its distance and points) ends within 1 degree and 5 mm of where it ends from
    the true pose, which the sensor's noise leaves within 2 degrees and 1 cm of the truth."""
    from catalign.data.camera import camera_at
    from catalign.data.shapes import procedural_shape
    from catalign.data.views import render_view
    from catalign.registration.config import EngineConfig

    chair = procedural_shape(seed)
    config = EngineConfig()
    refiner = Refiner(
        make_library(make_entry("chair", chair.points)),
        distance=0.025,
        icp_iterations=config.icp.iterations,
        icp_points=config.icp.points,
    )
    rng = np.random.default_rng(seed)
    camera = camera_at(POSE[:3, 3], 1.8, 30.0, rng.uniform(0.0, 360.0))
    view = render_view(chair, POSE, camera, rng)
    centre = transform(chair.points.mean(axis=0, keepdims=True), POSE)[0]
    shift = rng.normal(size=3)
    turn = make_pose(axis_angle(rng.normal(size=3), np.radians(10.0)), np.zeros(3))
    start = make_pose(np.eye(3), centre + 0.05 * shift / np.linalg.norm(shift))
    start = start @ turn @ make_pose(np.eye(3), -centre) @ POSE
    refined = refiner.refine(_hypothesis(start, view), view).transform
    best = refiner.refine(_hypothesis(POSE, view), view).transform
    assert rotation_error_deg(start[:3, :3], POSE[:3, :3]) == pytest.approx(10.0)
    assert rotation_error_deg(best[:3, :3], POSE[:3, :3]) < 2.0
    assert np.linalg.norm(best[:3, 3] - POSE[:3, 3]) < 0.01
    assert rotation_error_deg(refined[:3, :3], best[:3, :3]) < 1.0
    assert np.linalg.norm(refined[:3, 3] - best[:3, 3]) < 0.005
