from __future__ import annotations

from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from catalign.data.camera import DepthNoise, camera_at
from catalign.data.reconstruction import (
    Reconstruction,
    alpha_mesh,
    camera_to_world,
    depth_frame,
    drift_walk,
    fuse,
    reconstruct,
    trajectory,
)
from catalign.data.shapes import Shape, procedural_shape
from catalign.data.views import random_object_pose
from catalign.geometry.se3 import transform

# No neighbour, no drift, no noise: what is left is the TSDF's own error.
CLEAN = Reconstruction(drift_deg=0.0, drift_m=0.0, neighbour_gap=None, floor_kept=0.0)
SILENT = DepthNoise(base=0.0, quadratic=0.0)


@pytest.fixture(scope="module")
def chair() -> Shape:
    return procedural_shape(3)


def placed(shape: Shape, seed: int = 0) -> np.ndarray:
    return random_object_pose(np.random.default_rng(seed), "upright", height=shape.height / 2)


def distance_to_surface(points: np.ndarray, shape: Shape, pose: np.ndarray) -> np.ndarray:
    return cKDTree(transform(shape.points, pose)).query(points)[0]


def test_depth_frame_of_a_plane_is_its_distance_along_the_optical_axis():
    scene = o3d.t.geometry.RaycastingScene()
    wall = np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], dtype=np.float32)
    scene.add_triangles(
        o3d.core.Tensor(wall), o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    )
    camera = camera_at(np.zeros(3), 1.5, 90.0, 0.0, up=np.array([1.0, 0.0, 0.0]))
    depth = depth_frame(scene, camera, CLEAN, np.random.default_rng(0), SILENT)
    assert depth.shape == (CLEAN.height, CLEAN.width)
    np.testing.assert_allclose(depth, 1.5, atol=1e-5)


def test_frames_that_saw_nothing_are_left_out_of_the_fusion():
    """A camera turned away from the object gives an empty frame (training rendered some):
    it adds nothing, and frames that all saw nothing give no surface, not an Open3D error."""
    scene = o3d.t.geometry.RaycastingScene()
    wall = np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], dtype=np.float32)
    scene.add_triangles(
        o3d.core.Tensor(wall), o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    )
    camera = camera_at(np.zeros(3), 1.5, 90.0, 0.0, up=np.array([1.0, 0.0, 0.0]))
    seen = depth_frame(scene, camera, CLEAN, np.random.default_rng(0), SILENT)
    empty = np.zeros_like(seen)
    pose = camera_to_world(camera)
    surface = fuse([empty, seen, empty], [pose, pose, pose], CLEAN)
    assert len(surface) > 1000 and np.allclose(surface[:, 2], 0.0, atol=CLEAN.voxel)
    assert fuse([empty, empty], [pose, pose], CLEAN).shape == (0, 3)


def test_depth_frame_pixels_unproject_onto_the_surface_they_saw(chair):
    """The pinhole model of the depth image is the one the fusion uses: unprojecting every
    pixel with it lands on the chair."""
    pose = placed(chair)
    scene = o3d.t.geometry.RaycastingScene()
    vertices = transform(chair.mesh.vertices, pose)
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)),
        o3d.core.Tensor(chair.mesh.faces.astype(np.uint32)),
    )
    camera = camera_at(pose[:3, 3], 1.4, 30.0, 75.0)
    depth = depth_frame(scene, camera, CLEAN, np.random.default_rng(0), SILENT)
    v, u = np.nonzero(depth)
    focal = CLEAN.focal_px
    z = depth[v, u]
    in_camera = np.stack(
        [(u - (CLEAN.width / 2 - 0.5)) * z / focal, (v - (CLEAN.height / 2 - 0.5)) * z / focal, z],
        axis=1,
    )
    world = transform(in_camera, camera_to_world(camera))
    assert len(world) > 1000
    assert np.quantile(distance_to_surface(world, chair, pose), 0.95) < 0.01


def test_trajectory_sweeps_its_coverage_around_the_target():
    config = replace(CLEAN, coverage_deg=(90.0, 90.0), frames=7)
    target = np.array([0.5, -0.2, 0.4])
    cameras = trajectory(target, np.random.default_rng(1), config)
    assert len(cameras) == 7
    azimuths = [np.arctan2(*(c.eye - target)[1::-1]) for c in cameras]
    span = np.degrees(np.abs(np.angle(np.exp(1j * (azimuths[-1] - azimuths[0])))))
    assert span == pytest.approx(90.0, abs=1e-6)
    for camera in cameras:
        distance = np.linalg.norm(camera.eye - target)
        assert config.distance[0] - 1e-9 <= distance <= config.distance[1] + 1e-9
        elevation = np.degrees(np.arcsin((camera.eye - target)[2] / distance))
        assert config.elevation_deg[0] - 1e-6 <= elevation <= config.elevation_deg[1] + 1e-6


def test_drift_starts_at_the_truth_and_wanders_further_with_more_frames():
    config = replace(CLEAN, drift_deg=0.2, drift_m=0.002)
    walk = drift_walk(40, np.zeros(3), config, np.random.default_rng(2))
    np.testing.assert_array_equal(walk[0], np.eye(4))
    offsets = [np.linalg.norm(step[:3, 3]) for step in walk]
    assert np.mean(offsets[30:]) > np.mean(offsets[1:10]) > 0
    assert np.all([np.allclose(s[:3, :3] @ s[:3, :3].T, np.eye(3)) for s in walk])


def test_a_clean_reconstruction_lies_on_the_chair_and_sees_more_of_it_than_one_view(chair):
    pose = placed(chair)
    fused = reconstruct(chair, pose, np.random.default_rng(0), CLEAN, SILENT)
    distances = distance_to_surface(fused.points, chair, pose)
    assert np.median(distances) < CLEAN.voxel
    assert fused.object_points == len(fused.points)  # no floor, no neighbour
    # Most of the chair's surface has a fused point near it.
    covered = cKDTree(fused.points).query(transform(chair.points, pose))[0] < 2 * CLEAN.voxel
    assert covered.mean() > 0.6


def test_a_decimated_reconstruction_keeps_few_points_on_the_same_surface(chair):
    """ScanNet-like thinning: a twentieth of the triangles leaves far fewer vertices, still on
    the chair, and its edges: the points are spread over the chair, not gathered in one part."""
    pose = placed(chair)
    full = reconstruct(chair, pose, np.random.default_rng(0), CLEAN, SILENT)
    thin = reconstruct(chair, pose, np.random.default_rng(0), replace(CLEAN, decimate=0.05), SILENT)
    assert len(thin.points) < 0.15 * len(full.points)
    assert np.median(distance_to_surface(thin.points, chair, pose)) < CLEAN.voxel
    extent = np.ptp(thin.points, axis=0)
    assert np.all(extent > 0.9 * np.ptp(full.points, axis=0))


def test_the_loose_cut_keeps_floor_only_when_asked(chair):
    pose = placed(chair)
    floor_height = transform(chair.mesh.vertices, pose)[:, 2].min()
    for kept, expect_floor in ((0.0, False), (1.0, True)):
        config = replace(CLEAN, floor_kept=kept)
        fused = reconstruct(chair, pose, np.random.default_rng(0), config, SILENT)
        on_floor = np.abs(fused.points[:, 2] - floor_height) < CLEAN.voxel
        assert (on_floor.sum() > 500) == expect_floor
        assert fused.object_points < len(fused.points) or not expect_floor


def test_a_neighbour_and_a_wall_add_points_that_are_not_the_object(chair):
    pose = placed(chair)
    config = replace(CLEAN, neighbour_gap=(0.01, 0.02), wall_gap=(0.01, 0.02), margin=(0.2, 0.2))
    fused = reconstruct(chair, pose, np.random.default_rng(0), config, SILENT)
    far = distance_to_surface(fused.points, chair, pose) > 3 * CLEAN.voxel
    assert far.sum() > 300
    assert fused.object_points < len(fused.points)


def test_drift_and_noise_blur_the_surface_but_keep_it_near(chair):
    pose = placed(chair)
    clean = reconstruct(chair, pose, np.random.default_rng(0), CLEAN, SILENT)
    drifted = reconstruct(
        chair, pose, np.random.default_rng(0), replace(CLEAN, drift_deg=0.3, drift_m=0.003)
    )
    near = np.median(distance_to_surface(clean.points, chair, pose))
    blurred = np.median(distance_to_surface(drifted.points, chair, pose))
    assert near < blurred < 4 * CLEAN.voxel


def test_a_point_only_shape_is_reconstructed_through_its_alpha_mesh(chair):
    points_only = Shape(chair.shape_id, chair.points)
    pose = placed(chair)
    fused = reconstruct(points_only, pose, np.random.default_rng(0), CLEAN, SILENT)
    assert np.median(distance_to_surface(fused.points, chair, pose)) < CLEAN.voxel
    assert len(fused.points) > 3000


def test_the_alpha_mesh_of_exactly_flat_panels_keeps_their_points():
    """Some shared chairs are sampled on boards of no thickness (thousands of points with one
    coordinate exactly equal): their Delaunay tetrahedra are flat, and the alpha mesh must still
    pass near nearly every sample."""
    rng = np.random.default_rng(0)
    board = rng.uniform(0.0, 0.4, size=(4000, 2))
    seat = np.column_stack([board[:2000], np.full(2000, 0.45)])
    back = np.column_stack([board[2000:, 0], np.full(2000, 0.4), 0.45 + board[2000:, 1]])
    points = np.vstack([seat, back])
    vertices, _ = alpha_mesh(points)
    assert len(vertices) > 0
    near = cKDTree(vertices).query(points)[0] < 0.01
    assert near.mean() > 0.9


def test_a_camera_sees_an_alpha_mesh_about_where_it_sees_the_cad_mesh(chair):
    """The alpha mesh of a chair's surface points stands in for its CAD mesh: from a few
    cameras, most pixels that hit the CAD mesh hit the alpha mesh too (it leaves some holes),
    at nearly the same depth, and it adds few pixels of its own (it does not swell the chair)."""
    rng = np.random.default_rng(0)
    meshes = {"cad": (chair.mesh.vertices, chair.mesh.faces), "alpha": alpha_mesh(chair.points)}
    scenes = {}
    for name, (vertices, faces) in meshes.items():
        scenes[name] = o3d.t.geometry.RaycastingScene()
        scenes[name].add_triangles(
            o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
        )
    for azimuth in (0.0, 120.0, 240.0):
        camera = camera_at(np.zeros(3), 1.5, 30.0, azimuth, up=np.array([0.0, 1.0, 0.0]))
        camera = replace(camera, eye=camera.eye[[0, 2, 1]])  # the canonical frame is +Y up
        cad, alpha = (depth_frame(scenes[n], camera, CLEAN, rng, SILENT) for n in ("cad", "alpha"))
        both = (cad > 0) & (alpha > 0)
        assert both.sum() > 0.6 * (cad > 0).sum()
        assert (alpha > 0).sum() < 1.05 * (cad > 0).sum()
        assert np.median(np.abs(cad[both] - alpha[both])) < 0.01


def test_a_reconstruction_refuses_settings_that_cannot_make_one():
    with pytest.raises(ValueError, match="at least one frame"):
        Reconstruction(frames=0)
    with pytest.raises(ValueError, match="voxel"):
        Reconstruction(voxel=0.0)
    for share in (0.0, 1.5):
        with pytest.raises(ValueError, match="decimate"):
            Reconstruction(decimate=share)
