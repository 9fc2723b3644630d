"""The depth camera of the synthetic views: a pinhole camera placed around a target, what it sees
of a mesh (ray casting into its depth image) or of a point-only shape (hidden point removal),
and the depth noise of a structured-light sensor (sigma growing with depth squared) along each
ray. :mod:`catalign.data.views` places shapes, floors and tables in front of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


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
    return _ray_cast(vertices, faces, camera)[0]


def _ray_cast(
    vertices: np.ndarray, faces: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """The hit points of the camera's pixel rays, in pixel order, and the face each hit."""
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
    points = (rays_np[keep, :3] + t_hit[keep, None] * rays_np[keep, 3:]).astype(np.float64)
    return points, hits["primitive_ids"].numpy().reshape(-1)[keep].astype(np.int64)


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
