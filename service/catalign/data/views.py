"""Partial views: what a depth camera sees of a shape placed in the world.

A view is made in three steps: place the shape with an object pose (:func:`random_object_pose`,
world +Z up), put a camera around it (:func:`random_camera`, :func:`fixed_viewpoints`), and keep
the visible surface: ray casting of a mesh into a pinhole depth image (:func:`render_mesh_view`),
or hidden point removal for point-only shapes (:func:`visible_point_view`). Depth noise like a
structured-light sensor (:func:`add_depth_noise`, sigma growing with depth squared) is applied
along each camera ray. Returned points are in the world frame, the robot's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from catalign.data.shapes import Shape
from catalign.geometry.se3 import axis_angle, make_pose, random_rotation, transform

PoseMode = Literal["upright", "so3"]
WORLD_UP = np.array([0.0, 0.0, 1.0])
# The canonical chair frame has +Y up; standing upright in the world means model +Y -> world +Z.
MODEL_TO_WORLD_UP = axis_angle(np.array([1.0, 0.0, 0.0]), np.pi / 2)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera at ``eye`` looking at ``target``; ``fov_deg`` is the vertical field."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=WORLD_UP.copy)
    width: int = 320
    height: int = 240
    fov_deg: float = 60.0


@dataclass(frozen=True)
class DepthNoise:
    """Structured-light depth noise: ``sigma(z) = base + quadratic * z**2`` metres of depth.

    The defaults give about 2 mm at 1 m and 6.5 mm at 2 m, in line with published Kinect-v1
    error models (random error growing with the square of the distance).
    """

    base: float = 0.0005
    quadratic: float = 0.0015

    def sigma(self, depth: np.ndarray) -> np.ndarray:
        return self.base + self.quadratic * depth**2


def upright_rotation(yaw: float) -> np.ndarray:
    """Model-to-world rotation of a chair standing on the floor, turned by ``yaw`` about +Z."""
    return axis_angle(WORLD_UP, yaw) @ MODEL_TO_WORLD_UP


def random_object_pose(
    rng: np.random.Generator,
    mode: PoseMode = "upright",
    position_range: float = 1.0,
    height: float = 0.0,
) -> np.ndarray:
    """A model-to-world pose: yaw only (``upright``) or any rotation (``so3``).

    The shape's origin lands within ``position_range`` of the world origin in x and y, and at
    ``height`` above the floor (use half the chair's height for a bbox-centred chair).
    """
    if mode == "upright":
        rotation = upright_rotation(rng.uniform(0, 2 * np.pi))
    elif mode == "so3":
        rotation = random_rotation(rng)
    else:
        raise ValueError(f"unknown pose mode {mode!r}; expected 'upright' or 'so3'")
    xy = rng.uniform(-position_range, position_range, size=2)
    return make_pose(rotation, np.array([xy[0], xy[1], height]))


def camera_at(
    target: np.ndarray, distance: float, elevation_deg: float, azimuth_deg: float, **kwargs
) -> Camera:
    """A camera on a sphere around ``target`` (elevation above the world's horizontal plane)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    offset = distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Camera(eye=np.asarray(target) + offset, target=np.asarray(target), **kwargs)


def random_camera(
    target: np.ndarray,
    rng: np.random.Generator,
    distance: tuple[float, float] = (1.2, 3.0),
    elevation_deg: tuple[float, float] = (5.0, 50.0),
    **kwargs,
) -> Camera:
    """A camera at a random distance, elevation and azimuth, looking at ``target``."""
    return camera_at(
        target,
        rng.uniform(*distance),
        rng.uniform(*elevation_deg),
        rng.uniform(0.0, 360.0),
        **kwargs,
    )


def fixed_viewpoints(target: np.ndarray, distance: float = 2.0, **kwargs) -> list[Camera]:
    """The 10 fixed viewpoints per shape: azimuths every 36 degrees, elevations 15 and 35."""
    return [
        camera_at(target, distance, 15.0 if i % 2 == 0 else 35.0, 36.0 * i, **kwargs)
        for i in range(10)
    ]


def render_mesh_view(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """Ray-cast a mesh (world coordinates) into the camera; return the hit points."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    rays = scene.create_rays_pinhole(
        fov_deg=camera.fov_deg,
        center=camera.target.astype(np.float32).tolist(),
        eye=camera.eye.astype(np.float32).tolist(),
        up=camera.up.astype(np.float32).tolist(),
        width_px=camera.width,
        height_px=camera.height,
    )
    hits = scene.cast_rays(rays)
    t_hit = hits["t_hit"].numpy().reshape(-1)
    rays_np = rays.numpy().reshape(-1, 6)
    keep = np.isfinite(t_hit)
    return (rays_np[keep, :3] + t_hit[keep, None] * rays_np[keep, 3:]).astype(np.float64)


def visible_point_view(points: np.ndarray, camera: Camera) -> np.ndarray:
    """The points a camera at ``camera.eye`` sees (Katz et al. hidden point removal)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    diameter = float(np.linalg.norm(np.ptp(points, axis=0)))
    radius = 100.0 * max(diameter, float(np.linalg.norm(camera.eye - points.mean(axis=0))))
    _, visible = cloud.hidden_point_removal(camera.eye.tolist(), radius)
    return points[np.asarray(visible, dtype=np.int64)]


def add_depth_noise(
    points: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    noise: DepthNoise | None = None,
) -> np.ndarray:
    """Perturb each point along its camera ray so that its depth ``z`` (distance along the
    optical axis) gets Gaussian noise of standard deviation ``sigma(z)``, as a depth sensor's."""
    noise = noise or DepthNoise()
    axis = (camera.target - camera.eye) / np.linalg.norm(camera.target - camera.eye)
    rays = points - camera.eye
    depth = rays @ axis
    scale = 1.0 + rng.normal(size=len(points)) * noise.sigma(depth) / depth
    return camera.eye + rays * scale[:, None]


def render_view(
    shape: Shape,
    pose: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    noise: DepthNoise | None = None,
    noisy: bool = True,
) -> np.ndarray:
    """A partial, noisy observation of ``shape`` placed at ``pose``, in world coordinates.

    Meshes are ray-cast; point-only shapes use hidden point removal.
    """
    if shape.mesh is not None:
        seen = render_mesh_view(transform(shape.mesh.vertices, pose), shape.mesh.faces, camera)
    else:
        seen = visible_point_view(transform(shape.points, pose), camera)
    return add_depth_noise(seen, camera, rng, noise) if noisy else seen
