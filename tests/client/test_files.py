"""The CLI's own point readers: .npy, .xyz and ASCII / binary .ply, without open3d."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from catalign_client import InvalidPointsError
from catalign_client._files import UnsupportedFileError, read_points

POINTS = np.array([[0.0, 0.5, -1.25], [1e-3, 2.0, 3.5], [-4.0, 5.0, 6.75]])


def write_ply(
    path: Path,
    points: np.ndarray,
    fmt: str,
    *,
    before: str = "",
    before_rows: bytes = b"",
) -> Path:
    """A PLY with x y z float, nx ny nz float and a uchar red per vertex."""
    extra = np.column_stack([points * 0 + 0.5, np.arange(len(points)) % 256])
    header = (
        f"ply\nformat {fmt} 1.0\ncomment made by a test\n{before}"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    if fmt == "ascii":
        rows = "".join(
            " ".join(f"{v:g}" for v in [*p, *e]) + "\n" for p, e in zip(points, extra, strict=True)
        )
        body = rows.encode()
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype(
            [(n, endian + "f4") for n in ("x", "y", "z", "nx", "ny", "nz")] + [("red", "u1")]
        )
        rows = np.zeros(len(points), dtype=dtype)
        for i, name in enumerate("xyz"):
            rows[name] = points[:, i]
        body = rows.tobytes()
    path.write_bytes(header.encode() + before_rows + body)
    return path


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_vertices(tmp_path: Path, fmt: str):
    points = read_points(write_ply(tmp_path / "cloud.ply", POINTS, fmt))
    assert points.dtype == np.float64
    np.testing.assert_allclose(points, POINTS.astype(np.float32))


def test_binary_ply_skips_a_scalar_element_before_the_vertices(tmp_path: Path):
    before = "element camera 2\nproperty double fx\nproperty int id\n"
    path = write_ply(
        tmp_path / "c.ply", POINTS, "binary_little_endian", before=before, before_rows=bytes(24)
    )
    np.testing.assert_allclose(read_points(path), POINTS.astype(np.float32))


def test_ascii_ply_skips_rows_of_an_element_before_the_vertices(tmp_path: Path):
    before = "element camera 2\nproperty double fx\n"
    path = write_ply(tmp_path / "c.ply", POINTS, "ascii", before=before, before_rows=b"1\n2\n")
    np.testing.assert_allclose(read_points(path), POINTS.astype(np.float32))


def test_ply_written_by_trimesh(tmp_path: Path):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "trimesh.ply"
    path.write_bytes(trimesh.PointCloud(POINTS).export(file_type="ply"))
    np.testing.assert_allclose(read_points(path), POINTS)


def test_binary_ply_with_a_list_before_the_vertices_is_left_to_the_server(tmp_path: Path):
    before = "element meta 1\nproperty list uchar int ids\n"
    path = write_ply(tmp_path / "c.ply", POINTS, "binary_little_endian", before=before)
    with pytest.raises(UnsupportedFileError):
        read_points(path)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"solid stl\n", "not a PLY"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n", "x, y"),
        (b"ply\nformat exotic 1.0\nend_header\n", "format"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex"),
    ],
)
def test_bad_ply_files(tmp_path: Path, content: bytes, message: str):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(InvalidPointsError, match=message):
        read_points(path)


def test_truncated_binary_ply(tmp_path: Path):
    path = write_ply(tmp_path / "c.ply", POINTS, "binary_little_endian")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(InvalidPointsError, match="truncated"):
        read_points(path)


def test_npy_keeps_the_first_three_columns(tmp_path: Path):
    np.save(tmp_path / "a.npy", np.column_stack([POINTS, np.ones(3)]).astype(np.float32))
    np.testing.assert_allclose(read_points(tmp_path / "a.npy"), POINTS.astype(np.float32))
    np.save(tmp_path / "flat.npy", np.zeros(9))
    with pytest.raises(InvalidPointsError, match="shape"):
        read_points(tmp_path / "flat.npy")


def test_xyz_text_with_comments_commas_and_extra_columns(tmp_path: Path):
    path = tmp_path / "a.xyz"
    path.write_text("# x y z r g b\n0 0.5 -1.25 1 2 3\n0.001,2,3.5\n-4 5 6.75\n")
    np.testing.assert_allclose(read_points(path), POINTS)
    path.write_text("0 1\n")
    with pytest.raises(InvalidPointsError):
        read_points(path)


def test_other_suffixes_are_unsupported(tmp_path: Path):
    with pytest.raises(UnsupportedFileError, match=r"\.pcd"):
        read_points(tmp_path / "scan.pcd")
