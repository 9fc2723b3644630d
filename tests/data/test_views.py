from __future__ import annotations

import numpy as np
import pytest
import trimesh

from catalign.data.camera import (
    Camera,
    DepthNoise,
    add_depth_noise,
    camera_at,
    fixed_viewpoints,
    random_camera,
    render_mesh_view,
    visible_point_view,
)
from catalign.data.shapes import Shape, procedural_shape
from catalign.data.views import (
    MODEL_TO_WORLD_UP,
    Floor,
    Table,
    disc_points,
    random_object_pose,
    render_view,
    surface_density,
    under_table,
    upright_rotation,
)
from catalign.geometry.se3 import axis_angle, make_pose, transform

RADIUS = 0.3
CENTRE = np.array([0.2, -0.1, 0.5])


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


@pytest.fixture
def sphere_shape(shape_from_trimesh) -> Shape:
    return shape_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=RADIUS), "sphere")


@pytest.fixture
def camera() -> Camera:
    return camera_at(CENTRE, 1.5, 25.0, 40.0)


def test_mesh_view_sees_only_camera_facing_surface(sphere_shape: Shape, camera: Camera, rng):
    pose = make_pose(np.eye(3), CENTRE)
    seen = render_view(sphere_shape, pose, camera, rng, noisy=False)
    assert len(seen) > 1000
    # the hits lie on the (faceted) sphere
    distance = np.linalg.norm(seen - CENTRE, axis=1)
    assert distance.max() <= RADIUS + 1e-5
    assert distance.min() >= 0.98 * RADIUS
    rays = unit_rows(seen - camera.eye)
    # the true surface normal of each hit's triangle faces against the viewing ray
    posed = trimesh.Trimesh(
        transform(sphere_shape.mesh.vertices, pose), sphere_shape.mesh.faces, process=False
    )
    _, _, triangles = trimesh.proximity.closest_point(posed, seen)
    facet_dots = np.einsum("ij,ij->i", posed.face_normals[triangles], rays)
    assert (facet_dots < 0).all()
    # and so does the radial direction, up to faceting at the silhouette
    radial_dots = np.einsum("ij,ij->i", unit_rows(seen - CENTRE), rays)
    assert (radial_dots < 0).mean() > 0.99
    assert radial_dots.max() < 0.1


def test_mesh_view_hides_occluded_geometry():
    eye, target = np.array([0.0, -3.0, 0.5]), np.array([0.0, 0.0, 0.5])
    camera = Camera(eye=eye, target=target)
    front = trimesh.creation.box(extents=(1.0, 0.1, 1.0))
    front.apply_translation([0.0, -1.0, 0.5])
    hidden = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    hidden.apply_translation([0.0, 1.0, 0.5])
    both = trimesh.util.concatenate([front, hidden])
    seen = render_mesh_view(np.asarray(both.vertices), np.asarray(both.faces), camera)
    assert len(seen) > 100
    # every hit is on the front face of the occluder (y = -1.05); nothing of the hidden box
    np.testing.assert_allclose(seen[:, 1], -1.05, atol=1e-4)
    alone = render_mesh_view(np.asarray(hidden.vertices), np.asarray(hidden.faces), camera)
    assert len(alone) > 100 and (alone[:, 1] > 0.8).all()


def test_point_view_keeps_the_camera_facing_hemisphere(camera: Camera, rng):
    directions = unit_rows(rng.normal(size=(6000, 3)))
    points = CENTRE + RADIUS * directions
    seen = visible_point_view(points, camera)
    assert 0.25 * len(points) < len(seen) < 0.55 * len(points)
    # a subset of the input
    assert len({p.tobytes() for p in seen} - {p.tobytes() for p in points}) == 0
    towards_camera = (camera.eye - CENTRE) / np.linalg.norm(camera.eye - CENTRE)
    facing = (seen - CENTRE) @ towards_camera > 0
    assert facing.mean() > 0.97  # a few points at the rim may slip through
    # the hemisphere away from the camera is (almost) entirely dropped
    back = points[(points - CENTRE) @ towards_camera < -0.2 * RADIUS]
    kept = {p.tobytes() for p in seen}
    assert sum(p.tobytes() in kept for p in back) <= 0.01 * len(back)


def test_render_view_uses_point_view_for_point_shapes(camera: Camera, rng):
    directions = unit_rows(rng.normal(size=(3000, 3)))
    shape = Shape("ball", RADIUS * directions)
    pose = make_pose(np.eye(3), CENTRE)
    seen = render_view(shape, pose, camera, rng, noisy=False)
    np.testing.assert_array_equal(seen, visible_point_view(transform(shape.points, pose), camera))


def _plane_at_depth(depth: float, count: int, half_width: float, rng) -> np.ndarray:
    """Points on the plane x = depth in front of a camera at the origin looking along +x."""
    yz = rng.uniform(-half_width, half_width, size=(count, 2)) * depth
    return np.c_[np.full(count, depth), yz]


def _ray_residuals(depth: float, rng, half_width: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    camera = Camera(eye=np.zeros(3), target=np.array([1.0, 0.0, 0.0]))
    points = _plane_at_depth(depth, 40_000, half_width, rng)
    noisy = add_depth_noise(points, camera, rng)
    rays = unit_rows(points - camera.eye)
    along = np.einsum("ij,ij->i", noisy - points, rays)
    across = noisy - points - along[:, None] * rays
    return along, across


def test_depth_noise_statistics(rng):
    noise = DepthNoise()
    # the documented magnitudes: about 2 mm at 1 m and 6.5 mm at 2 m
    assert float(noise.sigma(np.array(1.0))) == pytest.approx(0.002)
    assert float(noise.sigma(np.array(2.0))) == pytest.approx(0.0065)
    stds = {}
    for depth in (1.0, 2.0):
        along, across = _ray_residuals(depth, rng)
        # the perturbation stays on the camera ray
        assert np.abs(across).max() < 1e-9
        assert abs(along.mean()) < 0.05 * noise.sigma(depth)
        assert along.std() == pytest.approx(noise.sigma(depth), rel=0.1)
        stds[depth] = along.std()
    # sigma grows with the square of the depth
    expected = noise.sigma(2.0) / noise.sigma(1.0)
    assert stds[2.0] / stds[1.0] == pytest.approx(expected, rel=0.1)
    assert expected > 3.0


def test_depth_noise_is_sigma_along_the_optical_axis(rng):
    """Off-axis points: the depth (optical-axis) component has std sigma(z) exactly."""
    camera = Camera(eye=np.zeros(3), target=np.array([1.0, 0.0, 0.0]))
    points = _plane_at_depth(1.5, 40_000, 0.5, rng)  # a wide plane, up to 27 degrees off-axis
    noisy = add_depth_noise(points, camera, rng)
    assert (noisy[:, 0] - points[:, 0]).std() == pytest.approx(DepthNoise().sigma(1.5), rel=0.05)


def test_depth_noise_custom_model(rng):
    camera = Camera(eye=np.zeros(3), target=np.array([0.0, 0.0, -1.0]))
    points = np.c_[np.zeros((20_000, 2)), np.full(20_000, -1.0)]
    noisy = add_depth_noise(points, camera, rng, DepthNoise(base=0.01, quadratic=0.0))
    assert (noisy[:, 2] - points[:, 2]).std() == pytest.approx(0.01, rel=0.05)
    silent = add_depth_noise(points, camera, rng, DepthNoise(base=0.0, quadratic=0.0))
    np.testing.assert_allclose(silent, points)


def test_upright_pose_maps_model_up_to_world_up():
    np.testing.assert_allclose(MODEL_TO_WORLD_UP @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    rng = np.random.default_rng(0)
    yaws = []
    for _ in range(50):
        pose = random_object_pose(rng, "upright", position_range=0.5, height=0.4)
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-12)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        assert pose[2, 3] == 0.4
        assert np.abs(pose[:2, 3]).max() <= 0.5
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
        forward = rotation @ [0.0, 0.0, 1.0]  # the backrest direction stays horizontal
        assert abs(forward[2]) < 1e-12
        yaws.append(np.arctan2(forward[1], forward[0]))
    assert np.ptp(yaws) > np.pi  # the yaw varies


def test_so3_pose_is_a_valid_rotation():
    rng = np.random.default_rng(1)
    ups = []
    for _ in range(50):
        pose = random_object_pose(rng, "so3")
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        ups.append(rotation @ [0.0, 1.0, 0.0])
    # not upright: model +Y goes anywhere
    assert np.min(np.array(ups)[:, 2]) < 0.0


def test_unknown_pose_mode():
    with pytest.raises(ValueError, match="unknown pose mode"):
        random_object_pose(np.random.default_rng(0), "sideways")  # type: ignore[arg-type]


def test_fixed_viewpoints():
    target = np.array([0.5, -0.2, 0.45])
    cameras = fixed_viewpoints(target, distance=2.5)
    assert len(cameras) == 10
    eyes = np.array([c.eye for c in cameras])
    np.testing.assert_allclose(np.linalg.norm(eyes - target, axis=1), 2.5)
    pairwise = np.linalg.norm(eyes[:, None] - eyes[None], axis=2)
    assert pairwise[~np.eye(10, dtype=bool)].min() > 0.1
    for i, cam in enumerate(cameras):
        np.testing.assert_array_equal(cam.target, target)
        elevation = np.degrees(np.arcsin((cam.eye[2] - target[2]) / 2.5))
        assert elevation == pytest.approx(15.0 if i % 2 == 0 else 35.0)
        azimuth = np.degrees(np.arctan2(cam.eye[1] - target[1], cam.eye[0] - target[0])) % 360
        assert azimuth == pytest.approx(36.0 * i, abs=1e-9)


def test_random_camera_ranges():
    rng = np.random.default_rng(3)
    target = np.array([1.0, 1.0, 0.4])
    for _ in range(50):
        cam = random_camera(target, rng)
        offset = cam.eye - target
        distance = np.linalg.norm(offset)
        assert 1.2 <= distance <= 3.0
        assert 5.0 <= np.degrees(np.arcsin(offset[2] / distance)) <= 50.0


def test_render_view_is_deterministic(sphere_shape: Shape, camera: Camera):
    pose = make_pose(np.eye(3), CENTRE)
    a = render_view(sphere_shape, pose, camera, np.random.default_rng(42))
    b = render_view(sphere_shape, pose, camera, np.random.default_rng(42))
    c = render_view(sphere_shape, pose, camera, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert a.shape == c.shape  # the same pixels hit ...
    assert not np.array_equal(a, c)  # ... with different noise
    clean = render_view(sphere_shape, pose, camera, np.random.default_rng(0), noisy=False)
    # noise of a few millimetres at 1.5 m
    assert 0.001 < np.linalg.norm(a - clean, axis=1).mean() < 0.01


# --- floor kept around the chair ----------------------------------------------------------------

FLOOR_Z_TOLERANCE = 1e-4  # ray hits on the floor plane, in float32


def _upright_pose(yaw: float, xy: tuple[float, float], height: float) -> np.ndarray:
    return make_pose(upright_rotation(yaw), np.array([xy[0], xy[1], height]))


def _footprint(posed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return posed[:, :2].min(axis=0), posed[:, :2].max(axis=0)


def _on_floor_outside(points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Points on the floor plane z = 0, beyond a 2 cm band around the chair's footprint."""
    outside = ((points[:, :2] < low - 0.02) | (points[:, :2] > high + 0.02)).any(axis=1)
    return outside & (np.abs(points[:, 2]) < FLOOR_Z_TOLERANCE)


def _free_line_of_sight(vertices: np.ndarray, faces: np.ndarray, eye, points) -> np.ndarray:
    """Whether nothing of the mesh lies between ``eye`` and each point (exact ray casting)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    offsets = points - eye
    distance = np.linalg.norm(offsets, axis=1)
    rays = np.c_[np.tile(eye, (len(points), 1)), offsets / distance[:, None]]
    t_hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    return t_hit >= distance - 1e-4


@pytest.fixture(scope="module")
def procedural_chair() -> Shape:
    return procedural_shape(3)


def test_floor_view_of_a_mesh_chair(procedural_chair: Shape, rng):
    shape = procedural_chair
    pose = _upright_pose(0.7, (0.3, -0.2), shape.height / 2)
    camera = camera_at(pose[:3, 3], 2.0, 30.0, 40.0)
    plain = render_view(shape, pose, camera, rng, noisy=False)
    kept = render_view(shape, pose, camera, rng, noisy=False, floor=Floor())
    posed = transform(shape.mesh.vertices, pose)
    assert abs(posed[:, 2].min()) < 1e-3  # the procedural chair stands on z = 0
    low, high = _footprint(posed)
    # without floor nothing lies on the floor around the chair; with it, thousands of points do
    assert _on_floor_outside(plain, low, high).sum() == 0
    floor = kept[np.abs(kept[:, 2]) < FLOOR_Z_TOLERANCE]
    assert _on_floor_outside(kept, low, high).sum() > 5000
    # the disc reaches the footprint's half-diagonal plus the default 0.3 m margin, no further
    radius = 0.5 * np.hypot(*(high - low)) + 0.3
    reach = np.linalg.norm(floor[:, :2] - (low + high) / 2, axis=1).max()
    assert 0.97 * radius < reach <= radius / np.cos(np.pi / 64) + 1e-4
    # the floor changes nothing of the chair: every pixel that saw the chair still does
    np.testing.assert_array_equal(kept[kept[:, 2] > 1e-3], plain[plain[:, 2] > 1e-3])
    # and no floor point is seen through the chair
    assert _free_line_of_sight(posed, shape.mesh.faces, camera.eye, floor).all()


def test_floor_under_the_seat_is_hidden(box_chair: Shape, rng):
    # the box chair's legs stand on model y = 0, so a pose at height 0 puts them on z = 0
    pose = _upright_pose(0.3, (0.0, 0.0), 0.0)
    seat_centre = transform(np.array([[0.0, 0.45, 0.0]]), pose)[0]
    camera = camera_at(seat_centre, 2.0, 85.0, 10.0)  # nearly straight down onto the seat
    floor_margin = 0.5
    for shape in (box_chair, Shape("box-points", box_chair.points)):
        kept = render_view(shape, pose, camera, rng, noisy=False, floor=Floor(floor_margin))
        floor = kept[np.abs(kept[:, 2]) < FLOOR_Z_TOLERANCE]
        horizontal = np.linalg.norm(floor[:, :2] - seat_centre[:2], axis=1)
        assert (horizontal > 0.5).sum() > 1000, shape.shape_id  # the ring around is seen ...
        # ... the floor under the seat not (for points: no floor point leaks between splats)
        assert (horizontal < 0.15).sum() == 0, shape.shape_id


def test_point_chair_floor_keeps_the_chair_view(box_chair: Shape, rng):
    shape = Shape("box-points", box_chair.points)
    pose = _upright_pose(1.1, (-0.4, 0.5), 0.0)
    camera = camera_at(np.array([-0.4, 0.5, 0.45]), 1.8, 25.0, 200.0)
    plain = render_view(shape, pose, camera, rng, noisy=False)
    kept = render_view(shape, pose, camera, np.random.default_rng(7), noisy=False, floor=Floor())
    posed = transform(shape.points, pose)
    low, high = _footprint(posed)
    # the chair's visible points are exactly those of the view without floor
    chair = {p.tobytes() for p in plain}
    extra = np.array([p for p in kept if p.tobytes() not in chair])
    assert len(kept) - len(extra) == len(plain)
    # what was added is floor, at the chair's lowest point, and most of it beyond the chair
    np.testing.assert_array_equal(extra[:, 2], posed[:, 2].min())
    assert _on_floor_outside(plain, low, high).sum() == 0
    assert _on_floor_outside(kept, low, high).sum() > 0.6 * len(extra)
    # at the shape's own density: the camera sees the near half of the disc or more
    radius = 0.5 * np.hypot(*(high - low)) + 0.3
    disc_count = surface_density(posed) * np.pi * radius**2
    assert 0.4 * disc_count < len(extra) < disc_count


def test_a_floor_view_is_its_floor_free_twin_plus_the_floor(procedural_chair: Shape):
    # same camera, same seed: the chair's noisy points are the floor-free view's, point for
    # point, so comparing the two measures the floor alone
    pose = _upright_pose(0.4, (0.2, 0.1), procedural_chair.height / 2)
    camera = camera_at(pose[:3, 3], 2.2, 35.0, 60.0)
    points_only = Shape("procedural-points", procedural_chair.points)
    for shape in (procedural_chair, points_only):
        plain = render_view(shape, pose, camera, np.random.default_rng(11))
        kept = render_view(shape, pose, camera, np.random.default_rng(11), floor=Floor())
        np.testing.assert_array_equal(kept[: len(plain)], plain, err_msg=shape.shape_id)
        added = kept[len(plain) :]
        assert len(added) > 1000, shape.shape_id
        assert np.abs(added[:, 2]).max() < 0.05, shape.shape_id  # noisy floor at z = 0


def test_floor_points_get_depth_noise(procedural_chair: Shape):
    pose = _upright_pose(2.0, (0.0, 0.0), procedural_chair.height / 2)
    camera = camera_at(pose[:3, 3], 2.0, 30.0, 0.0)
    low, high = _footprint(transform(procedural_chair.mesh.vertices, pose))
    kept = render_view(procedural_chair, pose, camera, np.random.default_rng(0), floor=Floor())
    outside = ((kept[:, :2] < low - 0.05) | (kept[:, :2] > high + 0.05)).any(axis=1)
    floor_z = kept[outside & (np.abs(kept[:, 2]) < 0.05), 2]
    # a few millimetres of depth noise at about 2 m, seen at an angle: the floor is not flat
    assert len(floor_z) > 5000
    assert 0.001 < floor_z.std() < 0.01


def _tilt(degrees: float) -> np.ndarray:
    return axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(degrees))


def test_floor_needs_an_upright_chair(box_chair: Shape, rng):
    camera = camera_at(np.array([0.0, 0.0, 0.45]), 2.0, 30.0, 0.0)
    for shape in (box_chair, Shape("box-points", box_chair.points)):
        tilted = make_pose(_tilt(2.0) @ upright_rotation(0.0), np.zeros(3))
        with pytest.raises(ValueError, match=r"a floor needs an upright chair.*2\.0 degrees"):
            render_view(shape, tilted, camera, rng, floor=Floor())
        so3 = random_object_pose(np.random.default_rng(1), "so3", height=0.45)
        with pytest.raises(ValueError, match="a floor needs an upright chair"):
            render_view(shape, so3, camera, rng, floor=Floor())
        # half a degree of tilt is still upright enough, and so3 without floor is fine
        nearly = make_pose(_tilt(0.5) @ upright_rotation(0.0), np.zeros(3))
        assert len(render_view(shape, nearly, camera, rng, floor=Floor())) > 100
        assert len(render_view(shape, so3, camera, rng)) > 100


def test_floor_needs_the_camera_above_it(box_chair: Shape, rng):
    below = Camera(eye=np.array([2.0, 0.0, -0.5]), target=np.array([0.0, 0.0, 0.45]))
    with pytest.raises(ValueError, match="camera above the floor"):
        render_view(box_chair, _upright_pose(0.0, (0.0, 0.0), 0.0), below, rng, floor=Floor())


def test_floor_settings_are_checked():
    with pytest.raises(ValueError, match="non-negative"):
        Floor(margin=-0.1)
    with pytest.raises(ValueError, match="segments"):
        Floor(segments=3)


def test_surface_density_and_disc_points(box_chair: Shape, rng):
    # a point-only shape's density, from its spacing alone, is the sample's points per m²
    area = trimesh.Trimesh(box_chair.mesh.vertices, box_chair.mesh.faces, process=False).area
    expected = len(box_chair.points) / area
    assert surface_density(box_chair.points) == pytest.approx(expected, rel=0.1)
    centre = np.array([0.5, -1.0, 0.2])
    points = disc_points(centre, 0.8, 5000.0, rng)
    assert len(points) == round(5000.0 * np.pi * 0.8**2)
    np.testing.assert_array_equal(points[:, 2], 0.2)
    radial = np.linalg.norm(points[:, :2] - centre[:2], axis=1)
    assert radial.max() <= 0.8
    # uniform by area: a quarter of the points within half the radius
    assert (radial < 0.4).mean() == pytest.approx(0.25, abs=0.02)
    assert surface_density(points) == pytest.approx(5000.0, rel=0.05)


def test_a_table_hides_what_lies_under_its_top_beyond_its_edge(procedural_chair: Shape, rng):
    shape = procedural_chair
    pose = _upright_pose(0.4, (0.5, -0.3), shape.height / 2)
    view = render_view(shape, pose, camera_at(pose[:3, 3], 2.0, 30.0, 40.0), rng, noisy=False)
    # a table whose edge crosses the chair's centre, its top 0.7 m above the floor
    table = Table(height=(0.7, 0.7), reach=(0.0, 0.0))
    hidden = under_table(view, pose[:3, 3], np.random.default_rng(5), table)
    direction = np.random.default_rng(5).normal(size=2)
    beyond = (view[:, :2] - pose[:2, 3]) @ direction > 0
    np.testing.assert_array_equal(hidden, beyond & (view[:, 2] < 0.7))
    # about half of what lies below the top goes, nothing above it
    low = view[:, 2] < 0.7
    assert 0.2 < hidden[low].mean() < 0.8
    assert not hidden[~low].any()
