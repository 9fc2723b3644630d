from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from catalign.errors import CatalignError, ShapeReadError
from catalign.geometry.io import (
    SUPPORTED_SUFFIXES,
    MeshData,
    ShapeData,
    read_mesh,
    read_points,
    read_shape,
)


@pytest.fixture
def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.fixture
def cloud(rng) -> np.ndarray:
    return rng.uniform(-1, 1, size=(200, 3))


# ---- real shared files -----------------------------------------------------------------------


def test_reads_shared_npy_point_cloud(chairs_root):
    path = sorted((chairs_root / "pointclouds").glob("*.npy"))[0]
    shape = read_shape(path)
    assert shape.mesh is None
    assert shape.points.shape == (15000, 3)
    assert shape.points.dtype == np.float64
    assert np.isfinite(shape.points).all()
    # size-normalised: bounding-box diagonal about 1
    assert 0.5 < np.linalg.norm(np.ptp(shape.points, axis=0)) < 1.5
    np.testing.assert_array_equal(read_points(path), shape.points)


def test_reads_shared_obj_mesh(chairs_root):
    path = sorted((chairs_root / "meshes").glob("*.obj"))[0]
    mesh = read_mesh(path)
    assert isinstance(mesh, MeshData)
    assert mesh.vertices.ndim == 2 and mesh.vertices.shape[1] == 3 and len(mesh.vertices) > 1000
    assert mesh.faces.shape[1] == 3 and len(mesh.faces) > 1000
    assert mesh.faces.dtype == np.int64
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    np.testing.assert_array_equal(read_points(path), mesh.vertices)


# ---- formats written here --------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".off", ".glb", ".obj"])
def test_reads_meshes(tmp_path: Path, box: trimesh.Trimesh, suffix: str):
    path = tmp_path / f"box{suffix}"
    box.export(path)
    shape = read_shape(path)
    assert isinstance(shape, ShapeData)
    assert shape.mesh is not None
    assert len(shape.mesh.faces) == 12
    # the same surface: bounding box and area survive the round trip (STL does not share
    # vertices, so compare geometry rather than vertex counts)
    np.testing.assert_allclose(shape.points.min(axis=0), [-0.5, -1.0, -1.5], atol=1e-6)
    np.testing.assert_allclose(shape.points.max(axis=0), [0.5, 1.0, 1.5], atol=1e-6)
    reread = trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False)
    assert reread.area == pytest.approx(box.area, rel=1e-6)
    np.testing.assert_array_equal(shape.points, shape.mesh.vertices)


def test_reads_ply_point_cloud(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(cloud).export(path)
    shape = read_shape(path)
    assert shape.mesh is None
    np.testing.assert_allclose(shape.points, cloud, atol=1e-6)
    with pytest.raises(ShapeReadError, match="no triangles"):
        read_mesh(path)


def test_reads_pcd(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "cloud.pcd"
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    assert o3d.io.write_point_cloud(str(path), pcd)
    shape = read_shape(path)
    assert shape.mesh is None
    np.testing.assert_allclose(shape.points, cloud, atol=1e-6)


def test_reads_xyz_text(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "cloud.xyz"
    np.savetxt(path, cloud, header="x y z")
    np.testing.assert_allclose(read_points(path), cloud)


def test_xyz_extra_columns_are_dropped(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "with_normals.xyz"
    np.savetxt(path, np.c_[cloud, -cloud])
    np.testing.assert_allclose(read_points(path), cloud)


def test_xyz_single_line(tmp_path: Path):
    path = tmp_path / "one.xyz"
    path.write_text("1 2 3\n")
    np.testing.assert_array_equal(read_points(path), [[1.0, 2.0, 3.0]])


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32])
def test_reads_npy(tmp_path: Path, cloud: np.ndarray, dtype):
    path = tmp_path / "cloud.npy"
    np.save(path, cloud.astype(dtype))
    points = read_points(path)
    assert points.dtype == np.float64
    np.testing.assert_array_equal(points, cloud.astype(dtype).astype(np.float64))
    assert read_shape(path).mesh is None


def test_suffix_is_case_insensitive(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "CLOUD.NPY"
    with path.open("wb") as handle:
        np.save(handle, cloud)
    np.testing.assert_array_equal(read_points(path), cloud)


# ---- errors ----------------------------------------------------------------------------------

# what a message says about a file that exists but cannot be understood
UNREADABLE = r"not a readable|holds no triangle mesh|no points could be read|holds no points"


def test_missing_file(tmp_path: Path):
    path = tmp_path / "absent.ply"
    with pytest.raises(ShapeReadError, match="no such file") as info:
        read_shape(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("suffix", sorted(SUPPORTED_SUFFIXES))
def test_empty_file(tmp_path: Path, suffix: str):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(ShapeReadError, match="empty") as info:
        read_shape(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("suffix", sorted(SUPPORTED_SUFFIXES))
def test_corrupt_file(tmp_path: Path, suffix: str):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ShapeReadError, match=UNREADABLE) as info:
        read_shape(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".npy", ".xyz", ".off"])
def test_text_garbage(tmp_path: Path, suffix: str):
    path = tmp_path / f"prose{suffix}"
    path.write_text("this is not a shape file\n" * 20)
    with pytest.raises(ShapeReadError, match=UNREADABLE) as info:
        read_shape(path)
    assert str(path) in str(info.value)


def test_truncated_npy(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "cut.npy"
    np.save(path, cloud)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(ShapeReadError, match=r"not a readable \.npy"):
        read_points(path)


def test_npy_with_nan(tmp_path: Path, cloud: np.ndarray):
    cloud[[3, 10], 1] = np.nan
    cloud[20, 0] = np.inf
    path = tmp_path / "nan.npy"
    np.save(path, cloud)
    with pytest.raises(ShapeReadError, match="3 of 200 points have NaN or infinite"):
        read_points(path)


def test_obj_with_nan_vertex(tmp_path: Path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ShapeReadError, match="NaN"):
        read_shape(path)


@pytest.mark.parametrize(
    "array",
    [np.zeros((10, 2)), np.zeros((10, 4)), np.zeros(3), np.zeros((2, 3, 3)), np.float64(1.0)],
    ids=["N2", "N4", "1d", "3d", "scalar"],
)
def test_wrong_shaped_npy(tmp_path: Path, array: np.ndarray):
    path = tmp_path / "wrong.npy"
    np.save(path, array)
    with pytest.raises(ShapeReadError, match=r"expected an \(N, 3\) array of points, got shape"):
        read_points(path)


def test_npy_without_points(tmp_path: Path):
    path = tmp_path / "none.npy"
    np.save(path, np.zeros((0, 3)))
    with pytest.raises(ShapeReadError, match="holds no points"):
        read_points(path)


def test_npy_of_strings(tmp_path: Path):
    path = tmp_path / "words.npy"
    np.save(path, np.array([["a", "b", "c"]]))
    with pytest.raises(ShapeReadError, match="numeric"):
        read_points(path)


def test_xyz_with_two_columns(tmp_path: Path):
    path = tmp_path / "flat.xyz"
    path.write_text("1 2\n3 4\n")
    with pytest.raises(ShapeReadError, match=r"got shape \(2, 2\)"):
        read_points(path)


def test_xyz_with_only_comments(tmp_path: Path):
    path = tmp_path / "comments.xyz"
    path.write_text("# nothing here\n")
    with pytest.warns(UserWarning), pytest.raises(ShapeReadError, match="holds no points"):
        read_points(path)


@pytest.mark.parametrize("name", ["shape.txt", "shape.vtk", "shape"])
def test_unsupported_suffix(tmp_path: Path, name: str):
    path = tmp_path / name
    path.write_text("1 2 3\n")
    with pytest.raises(ShapeReadError, match="unsupported file type") as info:
        read_shape(path)
    message = str(info.value)
    for suffix in (".obj", ".ply", ".npy", ".pcd"):
        assert suffix in message


def test_read_mesh_on_point_cloud(tmp_path: Path, cloud: np.ndarray):
    path = tmp_path / "cloud.npy"
    np.save(path, cloud)
    with pytest.raises(ShapeReadError, match="holds points but no triangles"):
        read_mesh(path)


def test_read_mesh_on_vertex_only_obj(tmp_path: Path):
    path = tmp_path / "vertices.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    np.testing.assert_array_equal(read_points(path), [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(ShapeReadError, match="no triangles"):
        read_mesh(path)


def test_shape_read_error_is_a_catalign_error():
    assert issubclass(ShapeReadError, CatalignError)


def test_a_file_trimesh_reads_anyway_leaves_no_traceback_in_the_log(
    tmp_path: Path, box: trimesh.Trimesh, caplog: pytest.LogCaptureFixture
):
    """An ASCII STL with a garbled normal is read (normals are not used), and trimesh's warning
    about it, which carries a traceback, stays out of the service's log."""
    text = box.export(file_type="stl_ascii").replace("facet normal", "facet normal 1e", 1)
    path = tmp_path / "garbled_normal.stl"
    path.write_text(text)
    with caplog.at_level(logging.WARNING):
        shape = read_shape(path)
    assert shape.mesh is not None and len(shape.mesh.faces) == len(box.faces)
    assert not [r for r in caplog.records if r.name.startswith("trimesh")], caplog.text
