"""Reconstructions: an object cut out of a surface fused from many depth frames, as a mapping
robot sends it (TSDF or surfel mapping, as ScanNet's scans were made).

A reconstruction is made in four steps (:func:`reconstruct`):

1. the scene: the shape (its mesh, or the alpha mesh of its points: :func:`alpha_mesh`) placed
   upright on a floor (a large horizontal square at its lowest
   point), with a box beside it as a neighbour and, optionally, a wall behind it;
2. a camera trajectory (:func:`trajectory`): ``frames`` cameras on an arc of ``coverage_deg``
   degrees of azimuth around the object, distance and elevation wandering smoothly within their
   ranges, so one side may never be seen;
3. depth frames (:func:`depth_frame`): every pixel's ray cast into the scene, its depth given the
   structured-light noise of :class:`~catalign.data.camera.DepthNoise`, and each frame fused
   (Open3D's scalable TSDF volume, ``voxel`` metres) at the pose the mapper *believes*: the true
   camera pose after a random walk of drift (``drift_deg`` and ``drift_m`` per frame, about the
   object), so late frames land slightly off early ones as in a map without loop closure;
4. the cut-out (:func:`loose_cut`): the fused surface's vertices inside the object's box grown
   by a margin drawn per side, with the floor below it kept in a share ``floor_kept`` of
   reconstructions, and whatever of the neighbour (or wall) the grown box reaches.

The fused frame is the world frame, so the object's pose in the world is the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from catalign.data.camera import WORLD_UP, Camera, DepthNoise, camera_at
from catalign.data.shapes import Shape
from catalign.geometry.se3 import axis_angle, make_pose, transform

# The floor and wall are squares this many metres wide: larger than any camera's view of them.
_PLANE_SIZE = 8.0
# Room for the voxel blocks (8 voxels a side) of the map around one object.
_BLOCKS = 20_000


@dataclass(frozen=True)
class Reconstruction:
    """How a reconstruction is simulated; every range is drawn from uniformly per object.

    ``frames`` depth frames on an arc of ``coverage_deg`` degrees around the object, at
    ``distance`` metres and ``elevation_deg`` above the horizontal; fused at ``voxel`` metres;
    drift per frame (standard deviations of a random walk) ``drift_deg`` of rotation and
    ``drift_m`` of translation; the cut-out box grown by ``margin`` metres on each side, the
    floor kept with probability ``floor_kept``; a neighbour box ``neighbour_gap`` metres from
    the object's footprint (``None``: no neighbour), a wall ``wall_gap`` metres behind it
    (``None``: no wall); ``decimate`` keeps that share of the fused surface's triangles
    (quadric decimation, which thins flat parts and keeps edges, as ScanNet's ``vh_clean_2``
    meshes are; ``None``: every vertex of the fusion).
    """

    frames: int = 16
    coverage_deg: tuple[float, float] = (120.0, 300.0)
    distance: tuple[float, float] = (1.0, 2.0)
    elevation_deg: tuple[float, float] = (15.0, 50.0)
    voxel: float = 0.01
    drift_deg: float = 0.1
    drift_m: float = 0.001
    margin: tuple[float, float] = (0.02, 0.10)
    floor_kept: float = 0.5
    neighbour_gap: tuple[float, float] | None = (0.05, 0.3)
    wall_gap: tuple[float, float] | None = None
    width: int = 320
    height: int = 240
    fov_deg: float = 60.0
    decimate: float | None = None

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"a reconstruction needs at least one frame, not {self.frames}")
        if self.decimate is not None and not 0 < self.decimate <= 1:
            raise ValueError(f"decimate is a share of triangles in (0, 1], not {self.decimate}")
        if self.voxel <= 0:
            raise ValueError(f"the fusion voxel must be positive, not {self.voxel}")

    @property
    def focal_px(self) -> float:
        return 0.5 * self.height / np.tan(np.radians(self.fov_deg) / 2)


@dataclass(frozen=True)
class Fused:
    """A cut-out reconstruction (world frame) and what went into it: the cameras' true eyes
    and how many of its points lie on the object rather than the floor, neighbour or wall."""

    points: np.ndarray
    eyes: np.ndarray
    object_points: int


def alpha_mesh(points: np.ndarray, spacings: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A mesh a camera can see for a point-only shape: the boundary of its alpha shape, with
    alpha ``spacings`` times the median distance between neighbouring points. Its triangles join
    sample points only, so thin parts stay thin; at 3 spacings it leaves holes (a camera sees
    56 to 90 % of the pixels the CAD mesh covers) yet fused views of it are retrieved nearly as
    often as the CAD mesh's (``bench/fused_proxy.py``, seeds 0 and 1: 36 of 40, CAD 39; on seed
    0 alone, before the shake below, 19 of 20 at 3 spacings, 15 at 6, 17 at 10). Squares across
    each point's normal, wide enough to leave no holes, swelled legs and edges: 13 of 20."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    spacing = float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))
    # Samples on boards of no thickness make flat tetrahedra, which Open3D drops with the
    # triangles they carry: a shared chair of such boards kept 4 % of its points. A shake of a
    # tenth of a spacing (under a millimetre) keeps 91 to 100 %; a quarter swelled thin parts
    # (``bench/fused_proxy.py``, seeds 0 and 1: 30 of 40 against 36).
    shaken = points + np.random.default_rng(0).normal(0.0, 0.1 * spacing, points.shape)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(shaken))
    # Open3D warns of every degenerate tetrahedron it skips: thousands of lines per shape.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(
            cloud, spacings * spacing
        )
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def trajectory(
    target: np.ndarray,
    rng: np.random.Generator,
    config: Reconstruction,
    facing: np.ndarray | None = None,
) -> list[Camera]:
    """``config.frames`` cameras on an arc around ``target``: the azimuth sweeps a coverage
    drawn from ``coverage_deg`` (at most 180 degrees centred on the horizontal ``facing``
    when given: a wall behind the object); distance and elevation start at random in their
    ranges and wander along half a sine wave, as a robot driving past an object would."""
    sweep = rng.uniform(*config.coverage_deg)
    if facing is None:
        start = rng.uniform(0.0, 360.0)
    else:
        sweep = min(sweep, 180.0)
        start = float(np.degrees(np.arctan2(facing[1], facing[0]))) - sweep / 2
    phase = np.linspace(0.0, 1.0, config.frames)
    wander = np.sin(np.pi * phase + rng.uniform(0.0, np.pi))
    distance = _between(config.distance, 0.5 + 0.5 * rng.uniform(-1, 1) * wander)
    elevation = _between(config.elevation_deg, 0.5 + 0.5 * rng.uniform(-1, 1) * wander)
    return [
        camera_at(
            target,
            d,
            e,
            start + sweep * p,
            width=config.width,
            height=config.height,
            fov_deg=config.fov_deg,
        )
        for d, e, p in zip(distance, elevation, phase, strict=True)
    ]


def camera_to_world(camera: Camera) -> np.ndarray:
    """The camera's pose (OpenCV axes: x right, y down, z forward) in the world."""
    forward = (camera.target - camera.eye) / np.linalg.norm(camera.target - camera.eye)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_pose(np.column_stack([right, down, forward]), camera.eye)


def depth_frame(
    scene: object,
    camera: Camera,
    config: Reconstruction,
    rng: np.random.Generator,
    noise: DepthNoise | None = None,
    within: tuple[np.ndarray, float] | None = None,
) -> np.ndarray:
    """The noisy depth image (metres along the optical axis, 0 where nothing was hit) of the
    Open3D raycasting ``scene`` seen by ``camera``, pixel (u, v) looking through its centre.

    ``within`` (a centre and a radius) keeps only the pixels whose surface lies in that ball:
    the part of the map around the object, which is all a cut-out can hold."""
    import open3d as o3d

    noise = noise or DepthNoise()
    focal = config.focal_px
    u, v = np.meshgrid(np.arange(config.width), np.arange(config.height))
    in_camera = np.stack(
        [
            (u + 0.5 - config.width / 2) / focal,
            (v + 0.5 - config.height / 2) / focal,
            np.ones_like(u, dtype=float),
        ],
        axis=-1,
    ).reshape(-1, 3)
    pose = camera_to_world(camera)
    # Directions with unit depth: the hit distance along each ray is the pixel's depth.
    directions = in_camera @ pose[:3, :3].T
    rays = np.hstack([np.broadcast_to(camera.eye, directions.shape), directions])
    depth = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    depth = depth.astype(np.float64)
    hit = np.isfinite(depth)
    if within is not None:
        centre, radius = within
        seen = camera.eye + directions * np.where(hit, depth, 0.0)[:, None]
        hit &= np.linalg.norm(seen - centre, axis=1) <= radius
    depth[hit] += rng.normal(size=int(hit.sum())) * noise.sigma(depth[hit])
    depth[~hit | (depth <= 0)] = 0.0
    return depth.reshape(config.height, config.width)


def drift_walk(
    frames: int, centre: np.ndarray, config: Reconstruction, rng: np.random.Generator
) -> list[np.ndarray]:
    """Where the mapper believes each frame is, relative to the truth: world-to-world
    corrections, the identity at the first frame, then a random walk of small rotations about
    ``centre`` and small translations."""
    walk, current = [], np.eye(4)
    for index in range(frames):
        if index:
            axis = rng.normal(size=3)
            angle = np.radians(rng.normal() * config.drift_deg)
            step = make_pose(axis_angle(axis / np.linalg.norm(axis), angle), np.zeros(3))
            about = make_pose(np.eye(3), centre) @ step @ make_pose(np.eye(3), -centre)
            about[:3, 3] += rng.normal(size=3) * config.drift_m
            current = about @ current
        walk.append(current.copy())
    return walk


def fuse(
    depths: list[np.ndarray], believed: list[np.ndarray], config: Reconstruction
) -> np.ndarray:
    """Fuse depth frames, each at its believed camera-to-world pose, in a TSDF voxel block grid
    of ``config.voxel`` metres (truncation 4 voxels); return the vertices of the surface it
    extracts (marching cubes over every voxel some frame saw; decimated to ``config.decimate``
    of its triangles if set), in lexicographic order."""
    import open3d as o3d

    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3d.core.float32, o3d.core.float32),
        attr_channels=((1), (1)),
        voxel_size=config.voxel,
        block_resolution=8,
        block_count=_BLOCKS,
    )
    focal, cx, cy = config.focal_px, config.width / 2 - 0.5, config.height / 2 - 0.5
    intrinsic = o3d.core.Tensor([[focal, 0, cx], [0, focal, cy], [0, 0, 1]], o3d.core.float64)
    far = config.distance[1] + 2.0
    touched = False
    for depth, pose in zip(depths, believed, strict=True):
        if not (depth > 0).any():
            continue  # a frame that saw nothing near the object: Open3D refuses to integrate it
        touched = True
        image = o3d.t.geometry.Image(o3d.core.Tensor(depth.astype(np.float32)))
        extrinsic = o3d.core.Tensor(np.linalg.inv(pose), o3d.core.float64)
        blocks = grid.compute_unique_block_coordinates(image, intrinsic, extrinsic, 1.0, far)
        grid.integrate(blocks, image, intrinsic, extrinsic, 1.0, far, 4.0)
    if not touched:
        return np.empty((0, 3))
    surface = grid.extract_triangle_mesh(weight_threshold=0.5)
    if config.decimate is None:
        vertices = surface.vertex.positions.numpy().astype(np.float64)
    else:  # Open3D decimates legacy meshes only
        mesh = surface.to_legacy()
        kept = max(1, round(len(mesh.triangles) * config.decimate))
        mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=kept)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
    # The grid's hash map hands blocks out in no fixed order: sort, so a seed fixes the cloud.
    return vertices[np.lexsort(vertices.T[::-1])]


def loose_cut(
    points: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    rng: np.random.Generator,
    config: Reconstruction,
) -> np.ndarray:
    """Which ``points`` a loose segmentation keeps: those in the object's box (``low``,
    ``high``) grown by a margin drawn per side; the floor under it is kept in a share
    ``floor_kept`` of cuts (the box reaches a few centimetres below the floor), else cut just
    above it."""
    grow_low = rng.uniform(*config.margin, size=3)
    grow_high = rng.uniform(*config.margin, size=3)
    bottom = low[2] - 0.05 if rng.random() < config.floor_kept else low[2] + 1.5 * config.voxel
    lower = np.array([low[0] - grow_low[0], low[1] - grow_low[1], bottom])
    upper = high + grow_high
    return np.all((points >= lower) & (points <= upper), axis=1)


def reconstruct(
    shape: Shape,
    pose: np.ndarray,
    rng: np.random.Generator,
    config: Reconstruction | None = None,
    noise: DepthNoise | None = None,
) -> Fused:
    """A reconstruction of ``shape`` (its mesh, else the alpha mesh of its points) placed at
    ``pose`` (model to world; upright, or lying on the floor below it), cut out loosely; see
    the module's docstring for the steps."""
    import open3d as o3d

    config = config or Reconstruction()
    if shape.mesh is None:
        vertices, faces = alpha_mesh(transform(shape.points, pose))
    else:
        vertices, faces = transform(shape.mesh.vertices, pose), shape.mesh.faces
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre = (low + high) / 2
    scene = o3d.t.geometry.RaycastingScene()
    parts = [(vertices, faces)]
    parts.append(_square(np.array([centre[0], centre[1], low[2]]), WORLD_UP, _PLANE_SIZE))
    direction = _unit_xy(rng.uniform(0, 2 * np.pi))
    if config.neighbour_gap is not None:
        parts.append(_neighbour_box(low, high, direction, rng, config.neighbour_gap))
    if config.wall_gap is not None:
        reach = _half_width(low, high, direction) + rng.uniform(*config.wall_gap)
        wall_centre = np.array([*(centre[:2] - reach * direction[:2]), low[2] + 1.0])
        parts.append(_square(wall_centre, direction, _PLANE_SIZE / 4))
    for part_vertices, faces in parts:
        scene.add_triangles(
            o3d.core.Tensor(part_vertices.astype(np.float32)),
            o3d.core.Tensor(faces.astype(np.uint32)),
        )
    cameras = trajectory(centre, rng, config, None if config.wall_gap is None else direction)
    around = (centre, float(np.linalg.norm(high - low)) / 2 + 0.5)
    depths = [depth_frame(scene, camera, config, rng, noise, around) for camera in cameras]
    believed = [
        drift @ camera_to_world(camera)
        for drift, camera in zip(
            drift_walk(len(cameras), centre, config, rng), cameras, strict=True
        )
    ]
    surface = fuse(depths, believed, config)
    points = surface[loose_cut(surface, low, high, rng, config)]
    on_object = np.all((points >= low - 2 * config.voxel) & (points <= high + 2 * config.voxel), 1)
    on_object &= points[:, 2] > low[2] + 1.5 * config.voxel
    return Fused(points, np.array([c.eye for c in cameras]), int(on_object.sum()))


def _between(bounds: tuple[float, float], fraction: np.ndarray) -> np.ndarray:
    return bounds[0] + (bounds[1] - bounds[0]) * np.clip(fraction, 0.0, 1.0)


def _half_width(low: np.ndarray, high: np.ndarray, direction: np.ndarray) -> float:
    """Half the extent of the box (``low``, ``high``) along the horizontal ``direction``."""
    return float(np.abs((high - low)[:2]) @ np.abs(direction[:2])) / 2


def _unit_xy(angle: float) -> np.ndarray:
    return np.array([np.cos(angle), np.sin(angle), 0.0])


def _square(centre: np.ndarray, normal: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles: a square of side ``size`` centred at ``centre``, facing ``normal``."""
    normal = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    second = np.cross(normal, first)
    corners = [
        centre + size / 2 * (a * first + b * second)
        for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    return np.array(corners), np.array([[0, 1, 2], [0, 2, 3]])


def _neighbour_box(
    low: np.ndarray,
    high: np.ndarray,
    direction: np.ndarray,
    rng: np.random.Generator,
    gap: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """A box standing on the floor beside the object's footprint, ``gap`` metres away along
    ``direction``: another piece of furniture a loose cut may catch a bit of."""
    import trimesh

    size = np.array([rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6), rng.uniform(0.4, 1.0)])
    centre_xy = (low[:2] + high[:2]) / 2
    reach = _half_width(low, high, direction) + rng.uniform(*gap) + size[0] / 2
    box = trimesh.creation.box(extents=size)
    turn = make_pose(
        axis_angle(WORLD_UP, float(np.arctan2(direction[1], direction[0]))), np.zeros(3)
    )
    box.apply_transform(turn)
    box.apply_translation([*(centre_xy + reach * direction[:2]), low[2] + size[2] / 2])
    return np.asarray(box.vertices), np.asarray(box.faces)
