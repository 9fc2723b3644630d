"""Header checks: lying files are refused before a reader allocates, limits are kept.

Valid files come from the real writers (trimesh, numpy, Open3D); the lying ones are the same
files with their declared counts edited. Every lying read runs with the process's address space
capped a little above what it already uses, so a check that let a file through would fail with
MemoryError here instead of asking for gigabytes.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from catalign.errors import ShapeReadError
from catalign.geometry.headers import Declared, check_header
from catalign.geometry.io import read_mesh, read_points, read_shape
from tests._memory import HEADROOM, address_space_capped

HUGE = 10**12


@pytest.fixture
def cloud(rng) -> np.ndarray:
    return rng.uniform(-1, 1, size=(200, 3))


@pytest.fixture
def mesh() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=2)  # 162 vertices, 320 faces


def test_the_address_space_cap_works():
    """The harness itself: under the cap, asking for more than HEADROOM is a MemoryError."""
    with address_space_capped(), pytest.raises(MemoryError):
        np.ones(2 * HEADROOM // 8)


def _refused(path: Path, match: str = "declares", **limits: int) -> str:
    """Read ``path`` under a capped address space; it must be refused, quickly, by name."""
    started = time.perf_counter()
    with address_space_capped(), pytest.raises(ShapeReadError, match=match) as info:
        read_shape(path, **limits)
    assert time.perf_counter() - started < 5.0
    message = str(info.value)
    assert str(path) in message
    return message


def _edit(source: Path, name: str, *replacements: tuple[bytes, bytes]) -> Path:
    """A copy of ``source`` with header bytes replaced (each must occur)."""
    data = source.read_bytes()
    for old, new in replacements:
        assert old in data, old
        data = data.replace(old, new, 1)
    target = source.with_name(name)
    target.write_bytes(data)
    return target


# ---- the real writers ------------------------------------------------------------------------

Writer = Callable[[Path, np.ndarray, trimesh.Trimesh], tuple[Path, np.ndarray]]


def _pcd(kind: str) -> Writer:
    def write(tmp: Path, cloud: np.ndarray, mesh: trimesh.Trimesh) -> tuple[Path, np.ndarray]:
        path = tmp / f"cloud_{kind}.pcd"
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        assert o3d.io.write_point_cloud(
            str(path), pcd, write_ascii=kind == "ascii", compressed=kind == "binary_compressed"
        )
        assert f"DATA {kind}\n".encode() in path.read_bytes()[:400]
        return path, cloud

    return write


def _trimesh(suffix: str, **options: str) -> Writer:
    def write(tmp: Path, cloud: np.ndarray, mesh: trimesh.Trimesh) -> tuple[Path, np.ndarray]:
        path = tmp / f"mesh_{options.get('encoding', options.get('file_type', 'binary'))}{suffix}"
        mesh.export(path, **options)
        corners = suffix == ".stl"  # STL stores every corner of every triangle
        return path, mesh.vertices[mesh.faces].reshape(-1, 3) if corners else mesh.vertices

    return write


def _ply_cloud(encoding: str) -> Writer:
    def write(tmp: Path, cloud: np.ndarray, mesh: trimesh.Trimesh) -> tuple[Path, np.ndarray]:
        path = tmp / f"cloud_{encoding}.ply"
        trimesh.PointCloud(cloud).export(path, encoding=encoding)
        return path, cloud

    return write


def _npy(tmp: Path, cloud: np.ndarray, mesh: trimesh.Trimesh) -> tuple[Path, np.ndarray]:
    path = tmp / "cloud.npy"
    np.save(path, cloud)
    return path, cloud


def _xyz(tmp: Path, cloud: np.ndarray, mesh: trimesh.Trimesh) -> tuple[Path, np.ndarray]:
    path = tmp / "cloud.xyz"
    np.savetxt(path, cloud, header="x y z")
    return path, cloud


WRITERS: dict[str, Writer] = {
    "pcd-ascii": _pcd("ascii"),
    "pcd-binary": _pcd("binary"),
    "pcd-compressed": _pcd("binary_compressed"),
    "ply-ascii": _trimesh(".ply", encoding="ascii"),
    "ply-binary": _trimesh(".ply", encoding="binary"),
    "ply-cloud-ascii": _ply_cloud("ascii"),
    "ply-cloud-binary": _ply_cloud("binary"),
    "obj": _trimesh(".obj"),
    "stl-binary": _trimesh(".stl"),
    "stl-ascii": _trimesh(".stl", file_type="stl_ascii"),
    "off": _trimesh(".off"),
    "glb": _trimesh(".glb"),
    "npy": _npy,
    "xyz": _xyz,
}
MESHES = ("ply-ascii", "ply-binary", "obj", "stl-binary", "stl-ascii", "off", "glb")


# ---- valid files: read as before, limits kept --------------------------------------------------


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_valid_file_reads_its_points(tmp_path: Path, cloud, mesh, kind: str):
    path, expected = WRITERS[kind](tmp_path, cloud, mesh)
    points = read_points(path)
    np.testing.assert_allclose(points, expected, atol=1e-6)
    # a limit the file keeps changes nothing
    limited = read_points(path, max_points=len(expected), max_faces=len(mesh.faces))
    np.testing.assert_array_equal(limited, points)


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_valid_file_over_max_points(tmp_path: Path, cloud, mesh, kind: str):
    path, expected = WRITERS[kind](tmp_path, cloud, mesh)
    limit = len(expected) - 1
    message = _refused(path, match=f"more than the limit of {limit} points", max_points=limit)
    assert str(len(expected)) in message


@pytest.mark.parametrize("kind", MESHES)
def test_valid_mesh_over_max_faces(tmp_path: Path, cloud, mesh, kind: str):
    path, _ = WRITERS[kind](tmp_path, cloud, mesh)
    with pytest.raises(ShapeReadError, match="more than the limit of 100 faces") as info:
        read_mesh(path, max_faces=100)
    assert str(path) in str(info.value)


def test_check_header_returns_declared_counts(tmp_path: Path, cloud, mesh):
    ply, _ = WRITERS["ply-binary"](tmp_path, cloud, mesh)
    assert check_header(ply) == Declared(points=162, faces=320)
    stl, _ = WRITERS["stl-binary"](tmp_path, cloud, mesh)
    assert check_header(stl) == Declared(points=960, faces=320)
    glb, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    assert check_header(glb) == Declared(points=162, faces=320)
    pcd, _ = WRITERS["pcd-compressed"](tmp_path, cloud, mesh)
    assert check_header(pcd) == Declared(points=200, faces=None)
    obj, _ = WRITERS["obj"](tmp_path, cloud, mesh)
    assert check_header(obj) == Declared(points=None, faces=None)  # nothing declared, no limit
    assert check_header(obj, max_points=10**6) == Declared(points=162, faces=320)


def test_limits_must_be_positive(tmp_path: Path, cloud, mesh):
    path, _ = _npy(tmp_path, cloud, mesh)
    with pytest.raises(ValueError, match="max_points"):
        read_shape(path, max_points=0)


# ---- PCD ---------------------------------------------------------------------------------


def test_evil_pcd_is_refused(tmp_path: Path):
    path = tmp_path / "evil.pcd"
    path.write_bytes(b"VERSION .7\nFIELDS x y z\nPOINTS 1000000000\nDATA ascii\n1 2 3\n")
    assert path.stat().st_size == 59
    message = _refused(path)
    assert message == (
        f"{path}: not a readable .pcd file: the header declares 1000000000 points, "
        "but the file's 59 bytes (6 after the header) can hold at most 1"
    )


@pytest.mark.parametrize("kind", ["pcd-ascii", "pcd-binary", "pcd-compressed"])
def test_pcd_lying_about_points(tmp_path: Path, cloud, mesh, kind: str):
    path, _ = WRITERS[kind](tmp_path, cloud, mesh)
    liar = _edit(
        path,
        "liar.pcd",
        (b"WIDTH 200\n", b"WIDTH 1000000000\n"),
        (b"POINTS 200\n", b"POINTS 1000000000\n"),
    )
    assert "1000000000 points" in _refused(liar)


def test_pcd_lying_width_alone(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["pcd-binary"](tmp_path, cloud, mesh)
    liar = _edit(path, "wide.pcd", (b"WIDTH 200\n", b"WIDTH 1000000000\n"))
    assert "1000000000 points" in _refused(liar)


def test_pcd_compressed_sizes_that_lie(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["pcd-compressed"](tmp_path, cloud, mesh)
    data = path.read_bytes()
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, uncompressed = struct.unpack_from("<II", data, start)
    assert uncompressed == 200 * 12
    # the uncompressed size alone: Open3D would allocate it
    huge = bytearray(data)
    struct.pack_into("<II", huge, start, compressed, 0xFFFFFFF0)
    (tmp_path / "expand.pcd").write_bytes(bytes(huge))
    assert "would expand to 4294967280 bytes" in _refused(tmp_path / "expand.pcd")
    # a compressed size past the end of the file
    past = bytearray(data)
    struct.pack_into("<II", past, start, 0xFFFFFFF0, uncompressed)
    (tmp_path / "past.pcd").write_bytes(bytes(past))
    assert "4294967280 bytes of compressed data" in _refused(tmp_path / "past.pcd")
    # consistent counts that LZF cannot produce from so few bytes
    points = 0xFFFFFFF0 // 12
    consistent = _edit(
        path,
        "dense.pcd",
        (b"WIDTH 200\n", f"WIDTH {points}\n".encode()),
        (b"POINTS 200\n", f"POINTS {points}\n".encode()),
    )
    dense = bytearray(consistent.read_bytes())
    start = dense.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    struct.pack_into("<II", dense, start, compressed, points * 12)
    consistent.write_bytes(bytes(dense))
    assert f"{compressed} compressed bytes can hold at most" in _refused(consistent)


@pytest.mark.parametrize(
    ("header", "why"),
    [
        (b"VERSION .7\nPOINTS 1\nDATA ascii\n", "no FIELDS line"),
        (b"FIELDS a b c\nPOINTS 1\nDATA ascii\n", "do not name x, y and z"),
        (b"FIELDS x y z\nPOINTS many\nDATA ascii\n", "'many' is not a whole number"),
        (b"FIELDS x y z\nPOINTS 1.5\nDATA ascii\n", "'1.5' is not a whole number"),
        (b"FIELDS x y z\nPOINTS -5\nDATA ascii\n", r"negative POINTS value \(-5\)"),
        (b"FIELDS x y z\nWIDTH 1\nHEIGHT -1\nDATA ascii\n", "negative HEIGHT"),
        (b"FIELDS x y z\nDATA ascii\n", "neither POINTS nor WIDTH"),
        (b"FIELDS x y z\nSIZE 4 4\nPOINTS 1\nDATA binary\n", "SIZE line has 2 values for 3"),
        (b"FIELDS x y z\nSIZE 4 4 3\nPOINTS 1\nDATA binary\n", "not 1, 2, 4 or 8 bytes"),
        (b"FIELDS x y z\nPOINTS 1\nDATA zipped\n", "unknown encoding 'zipped'"),
        (b"FIELDS x y z\nPOINTS 1\n", "no DATA line"),
    ],
)
def test_pcd_malformed_header(tmp_path: Path, header: bytes, why: str):
    path = tmp_path / "bad.pcd"
    path.write_bytes(header + b"1 2 3\n")
    _refused(path, match=f"not a readable .pcd file: .*{why}")


def test_pcd_header_without_end(tmp_path: Path):
    path = tmp_path / "endless.pcd"
    path.write_bytes(b"FIELDS x y z\n" + b"# padding\n" * 20_000)
    _refused(path, match="does not end within its first 65536 bytes")


# ---- PLY ---------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["ply-ascii", "ply-binary"])
@pytest.mark.parametrize("element", [b"vertex", b"face"])
def test_ply_lying_about_an_element(tmp_path: Path, cloud, mesh, kind: str, element: bytes):
    path, _ = WRITERS[kind](tmp_path, cloud, mesh)
    count = {b"vertex": 162, b"face": 320}[element]
    old = b"element %s %d\n" % (element, count)
    liar = _edit(path, "liar.ply", (old, b"element %s %d\n" % (element, HUGE)))
    noun = {b"vertex": "vertices", b"face": "faces"}[element]
    assert f"declares {HUGE} {noun}" in _refused(liar)


def test_ply_lying_about_an_unknown_element(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["ply-binary"](tmp_path, cloud, mesh)
    extra = b"element edge %d\nproperty int vertex1\nproperty int vertex2\nend_header\n" % HUGE
    liar = _edit(path, "edges.ply", (b"end_header\n", extra))
    assert f"declares {HUGE} 'edge' elements" in _refused(liar)


def test_ply_cloud_lying_about_vertices(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["ply-cloud-binary"](tmp_path, cloud, mesh)
    liar = _edit(path, "liar.ply", (b"element vertex 200\n", b"element vertex 100000000\n"))
    _refused(liar, match="declares 100000000 vertices, but the file's")


@pytest.mark.parametrize(
    ("header", "why"),
    [
        (b"plx\nformat ascii 1.0\nend_header\n", "does not start with the line 'ply'"),
        (b"ply\nformat zip 1.0\nend_header\n", "unknown format 'zip'"),
        (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", "negative vertex count"),
        (b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n", "'x' is not a whole number"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "property before any"),
        (b"ply\nformat ascii 1.0\nelement v 1\nproperty quad x\nend_header\n", "type 'quad'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\n", "no end_header line"),
    ],
)
def test_ply_malformed_header(tmp_path: Path, header: bytes, why: str):
    path = tmp_path / "bad.ply"
    path.write_bytes(header + b"1 2 3\n")
    _refused(path, match=f"not a readable .ply file: .*{why}")


# ---- STL ---------------------------------------------------------------------------------


def test_stl_binary_lying_about_triangles(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["stl-binary"](tmp_path, cloud, mesh)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 80, 0xFFFFFFFF)
    path.write_bytes(bytes(data))
    message = _refused(path)
    assert "declares 4294967295 triangles" in message
    assert f"can hold at most {(len(data) - 84) // 50}" in message


def test_stl_binary_with_too_few_triangles(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["stl-binary"](tmp_path, cloud, mesh)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 80, 3)
    path.write_bytes(bytes(data))
    _refused(
        path, match=f"declares 3 triangles, which take 234 bytes, but the file has {len(data)}"
    )


def test_stl_ascii_is_counted_not_read(tmp_path: Path, monkeypatch):
    """ASCII STL declares nothing: facets are counted by streaming, and the reader never runs."""
    path = tmp_path / "many.stl"
    facet = b"facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
    path.write_bytes(b"solid many\n" + (facet + b"endloop\nendfacet\n") * 200_000 + b"endsolid\n")
    monkeypatch.setattr(trimesh, "load", _never_called)
    message = _refused(path, match="more than the limit of 300 points", max_points=300)
    assert "triangles" in message
    _refused(path, match="more than the limit of 100 faces", max_faces=100)


# ---- OBJ and XYZ: counted, not declared --------------------------------------------------


def _never_called(*args, **kwargs):
    raise AssertionError("the reader ran although the header check should have refused")


def test_obj_is_counted_not_read(tmp_path: Path, monkeypatch):
    """OBJ declares nothing: 'v' and 'f' lines are streamed and counted against the limits."""
    path = tmp_path / "many.obj"
    path.write_bytes(b"# a comment\n" + b"v 0 0 0\nvn 0 0 1\n" * 1_000_000 + b"f 1 2 3\n" * 10)
    monkeypatch.setattr(trimesh, "load", _never_called)
    message = _refused(path, match="more than the limit of 1000 points", max_points=1000)
    assert "the file holds at least" in message
    _refused(path, match="more than the limit of 5 faces", max_faces=5)


def test_obj_counting_survives_a_very_long_line(tmp_path: Path):
    path = tmp_path / "long.obj"
    path.write_bytes(b"v 0 0 0\n# " + b"x" * (3 << 20) + b"\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert check_header(path, max_points=3) == Declared(points=3, faces=1)
    _refused(path, match="holds at least 3 points", max_points=2)


def test_xyz_is_counted_not_read(tmp_path: Path, monkeypatch):
    path = tmp_path / "many.xyz"
    path.write_bytes(b"# x y z\n\n" + b"0 0 0\n" * 2_000_000)
    monkeypatch.setattr(np, "loadtxt", _never_called)
    _refused(path, match="more than the limit of 1000 points", max_points=1000)


def test_xyz_comments_and_blank_lines_are_not_points(tmp_path: Path):
    path = tmp_path / "three.xyz"
    path.write_bytes(b"# header\n\n1 2 3\n  # indented comment\n4 5 6\n\t7 8 9")
    assert check_header(path, max_points=3) == Declared(points=3, faces=None)
    np.testing.assert_array_equal(
        read_points(path, max_points=3), [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    )


# ---- OFF ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("counts", "noun"), [(b"%d 320 0" % HUGE, "vertices"), (b"162 %d 0" % HUGE, "faces")]
)
def test_off_lying_about_counts(tmp_path: Path, cloud, mesh, counts: bytes, noun: str):
    path, _ = WRITERS["off"](tmp_path, cloud, mesh)
    liar = _edit(path, "liar.off", (b"162 320 0\n", counts + b"\n"))
    assert f"declares {HUGE} {noun}" in _refused(liar)


def test_off_counts_on_the_off_line_and_comments(tmp_path: Path):
    path = tmp_path / "inline.off"
    path.write_bytes(b"# made by hand\nOFF 3 1 0 # counts here\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert check_header(path) == Declared(points=3, faces=1)
    assert len(read_mesh(path).faces) == 1
    path.write_bytes(b"OFF 3000 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    _refused(path, match="declares 3000 vertices")


@pytest.mark.parametrize(
    ("text", "why"),
    [
        (b"ON\n3 1 0\n", "first line is not 'OFF'"),
        (b"OFF\n", "no vertex and face counts"),
        (b"OFF\n3\n", "does not hold vertices and faces"),
        (b"OFF\n3 x 0\n", "'x' is not a whole number"),
        (b"OFF\n-3 1 0\n", "negative vertex count"),
    ],
)
def test_off_malformed_header(tmp_path: Path, text: bytes, why: str):
    path = tmp_path / "bad.off"
    path.write_bytes(text)
    _refused(path, match=f"not a readable .off file: .*{why}")


# ---- GLB ---------------------------------------------------------------------------------


def _glb_split(path: Path) -> tuple[dict, bytes]:
    """The JSON of a GLB and everything after its JSON chunk (the BIN chunk, with its header)."""
    data = path.read_bytes()
    (json_bytes,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[20 : 20 + json_bytes]), data[20 + json_bytes :]


def _glb_write(path: Path, gltf: dict, rest: bytes, length: int | None = None) -> Path:
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + rest
    total = 12 + len(body) if length is None else length
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, total) + body)
    return path


def _position(gltf: dict) -> dict:
    return gltf["accessors"][gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]


def test_glb_roundtrip_of_the_test_writer(tmp_path: Path, cloud, mesh):
    path, expected = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    again = _glb_write(tmp_path / "again.glb", gltf, rest)
    np.testing.assert_allclose(read_points(again), expected, atol=1e-6)


def test_glb_lying_accessor_count(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    _position(gltf)["count"] = HUGE
    liar = _glb_write(tmp_path / "liar.glb", gltf, rest)
    assert f"of {HUGE} values of 12 bytes" in _refused(liar)


def test_glb_accessor_without_data(tmp_path: Path, cloud, mesh):
    """trimesh fills an accessor without a bufferView with zeros: count * 12 bytes of them."""
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    position = _position(gltf)
    del position["bufferView"]
    position["count"] = HUGE
    liar = _glb_write(tmp_path / "zeros.glb", gltf, rest)
    assert "without data" in _refused(liar)


def test_glb_lying_buffer_and_view(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    gltf["buffers"][0]["byteLength"] = HUGE
    _refused(_glb_write(tmp_path / "buffer.glb", gltf, rest), match="but the BIN chunk holds")
    gltf, rest = _glb_split(path)
    gltf["bufferViews"][0]["byteLength"] = HUGE
    _refused(_glb_write(tmp_path / "view.glb", gltf, rest), match="bufferView 0 of")


def test_glb_lying_lengths(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    _refused(_glb_write(tmp_path / "length.glb", gltf, rest, length=2**32 - 1), match="4294967295")
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 12, 2**32 - 4)
    (tmp_path / "json.glb").write_bytes(bytes(data))
    _refused(tmp_path / "json.glb", match="JSON chunk of 4294967292 bytes")
    bin_at = 20 + struct.unpack_from("<I", path.read_bytes(), 12)[0]
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, bin_at, 2**32 - 4)
    (tmp_path / "bin.glb").write_bytes(bytes(data))
    _refused(tmp_path / "bin.glb", match="chunk of 4294967292 bytes")


def test_glb_outside_files_are_refused(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    gltf["buffers"].append({"uri": "../../dev/zero", "byteLength": 12})
    _refused(_glb_write(tmp_path / "outside.glb", gltf, rest), match="refers to an outside file")


def test_glb_instances_count_towards_the_limit(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    mesh_node = next(n for n in gltf["nodes"] if "mesh" in n)
    start = len(gltf["nodes"])
    gltf["nodes"].extend({"mesh": mesh_node["mesh"]} for _ in range(9))
    gltf["scenes"][gltf.get("scene", 0)]["nodes"].extend(range(start, start + 9))
    copies = _glb_write(tmp_path / "copies.glb", gltf, rest)
    assert check_header(copies) == Declared(points=1620, faces=3200)
    _refused(copies, match="declares 1620 points, more than the limit of 1000", max_points=1000)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"glTX" + bytes(16), "does not start with the GLB magic"),
        (b"glTF" + struct.pack("<II", 1, 20) + bytes(8), "glTF version 1"),
        (b"glTF" + struct.pack("<II", 2, 20) + struct.pack("<I4s", 0, b"BIN\0"), "not JSON"),
        (b"glTF" + struct.pack("<II", 2, 24) + struct.pack("<I4s", 4, b"JSON") + b"[1, ", "parse"),
    ],
)
def test_glb_malformed_header(tmp_path: Path, data: bytes, why: str):
    path = tmp_path / "bad.glb"
    path.write_bytes(data)
    _refused(path, match=f"not a readable .glb file: .*{why}")


# ---- NPY ---------------------------------------------------------------------------------


def _npy_header(path: Path, shape: tuple[int, ...], descr: str, body: bytes) -> Path:
    with path.open("wb") as handle:
        header = {"descr": descr, "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(handle, header)
        handle.write(body)
    return path


def test_npy_lying_about_its_shape(tmp_path: Path, cloud):
    path = _npy_header(tmp_path / "liar.npy", (HUGE, 3), "<f8", cloud.tobytes())
    message = _refused(path)
    assert f"shape ({HUGE}, 3)" in message
    assert f"({HUGE * 24} bytes)" in message


def test_npy_with_bytes_to_spare(tmp_path: Path, cloud):
    path = _npy_header(tmp_path / "spare.npy", (10, 3), "<f8", cloud.tobytes())
    _refused(path, match="are more")


def test_npy_of_objects_is_refused(tmp_path: Path):
    path = tmp_path / "objects.npy"
    np.save(path, np.array([[1, "a", None]], dtype=object), allow_pickle=True)
    _refused(path, match="Python objects")


def test_npy_wrong_shape_is_refused_before_reading(tmp_path: Path, monkeypatch):
    path = tmp_path / "flat.npy"
    np.save(path, np.zeros((10, 2)))
    monkeypatch.setattr(np, "load", _never_called)
    _refused(path, match=r"expected an \(N, 3\) array of points, got shape \(10, 2\)")


def test_npy_version_2_header(tmp_path: Path, cloud):
    path = tmp_path / "v2.npy"
    with path.open("wb") as handle:
        np.lib.format.write_array(handle, cloud, version=(2, 0))
    np.testing.assert_array_equal(read_points(path, max_points=200), cloud)
    _refused(path, match="limit of 199 points", max_points=199)


def test_glb_json_of_the_wrong_types(tmp_path: Path, cloud, mesh):
    path, _ = WRITERS["glb"](tmp_path, cloud, mesh)
    gltf, rest = _glb_split(path)
    _position(gltf)["componentType"] = [5126]
    _refused(_glb_write(tmp_path / "list.glb", gltf, rest), match="unknown componentType")
    gltf, rest = _glb_split(path)
    _position(gltf)["count"] = True
    _refused(_glb_write(tmp_path / "bool.glb", gltf, rest), match="no whole, non-negative count")
    gltf, rest = _glb_split(path)
    gltf["scenes"][0]["nodes"] = [99]
    _refused(_glb_write(tmp_path / "node.glb", gltf, rest), match="node 99, which does not exist")


# ---- every cut of every valid file -----------------------------------------------------------


@pytest.mark.filterwarnings("ignore:loadtxt. input contained no data:UserWarning")
@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_truncated_files_are_refused_or_read(tmp_path: Path, cloud, mesh, kind: str):
    """A file cut anywhere is read (a shorter text file may still be whole) or refused."""
    path, _ = WRITERS[kind](tmp_path, cloud, mesh)
    data = path.read_bytes()
    cut = path.with_name(f"cut{path.suffix}")
    for end in sorted({1, 7, 30, 90, 200, len(data) // 2, len(data) - 1}):
        cut.write_bytes(data[:end])
        with address_space_capped():
            try:
                read_shape(cut)
            except ShapeReadError as exc:
                assert str(cut) in str(exc)
