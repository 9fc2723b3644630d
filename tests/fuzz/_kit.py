"""What the fuzz tests and ``bench/fuzz.py`` share: valid inputs, their mutators, the targets.

A fuzzer that only throws random bytes at a reader stops at its first check (the magic word), so
every target here starts from valid inputs of its format (50 points, or a small mesh) and mutates
them the way a broken writer or a hostile client would: truncation, flipped bytes, header numbers
made huge, negative or not numbers at all, header words swapped for other words of the grammar,
header lines duplicated, dropped or reordered, non-UTF-8 bytes, other line endings, binary words
overwritten, and (for GLB) the JSON chunk edited and the file rebuilt with consistent lengths.
Pure random bytes, with and without the format's magic, come in too.

The property every target checks (:func:`run_target`): the reader returns a finite (N, 3) float64
array (meshes: faces that index existing vertices) within the point limit, or raises the
project's own error; any other exception propagates. Each read runs with the process's address
space capped a little above what it already uses, so a header that makes a reader allocate far
more than the file justifies fails with MemoryError instead of passing unnoticed.

Mutators take a :class:`random.Random`; the tests hand them Hypothesis' ``st.randoms()`` (so
failures shrink), the benchmark a seeded one.
"""

from __future__ import annotations

import array
import copy
import io
import json
import random
import re
import struct
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import open3d as o3d
import trimesh

from catalign.api.inputs import decode_binary
from catalign.api.schemas import RegisterOptions
from catalign.errors import CatalignError
from catalign.geometry.io import read_shape
from catalign_client._exceptions import CatalignError as ClientError
from catalign_client._files import UnsupportedFileError
from catalign_client._files import read_points as client_read_points
from catalign_client._pointcloud2 import pointcloud2_points
from catalign_client._points import as_points
from tests._memory import address_space_capped

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # refusals are expected

MAX_POINTS = 10_000
MAX_FACES = 20_000

SEED_POINTS = 50

INTERESTING_NUMBERS = (
    "0", "1", "-1", "2", "3", "7", "255", "256", "65535", "2147483647", "2147483648",
    "-2147483648", "4294967295", "4294967296", "9223372036854775807", "18446744073709551616",
    "1000000000000", "1" + "0" * 40, "1" * 31, "-0", "+3", "nan", "NaN", "inf", "-inf", "1e9",
    "1e400", "1.5", "-2.5", "0x10", "", "٣", "²", "3 3", "1_000",
)  # fmt: skip
INTERESTING_WORDS = (
    b"\x00\x00\x00\x00", b"\xff\xff\xff\xff", b"\xff\xff\xff\x7f", b"\x00\x00\xc0\x7f",
    b"\x00\x00\x80\x7f", b"\x00\x00\x80\xff", b"\x01\x00\x00\x00", b"\x00\x00\x00\x80",
    b"\x00\x00\x00\x01", b"\xff" * 8,
)  # fmt: skip
NON_UTF8 = (b"\xff", b"\xfe\xff", b"\xc3(", b"\x80\x80", b"\xed\xa0\x80", b"\x00")


@dataclass(frozen=True)
class Grammar:
    """What the mutators know of a format: where its header ends, the words it is made of."""

    header_end: bytes | None
    words: tuple[bytes, ...]
    magic: bytes = b""


@dataclass(frozen=True)
class Target:
    """One reader under fuzzing: how to make an input and how to read it into points."""

    name: str
    generate: Callable[[random.Random], Any]
    read: Callable[[Any, Path], np.ndarray]
    errors: tuple[type[BaseException], ...]
    max_points: int | None


# --- valid inputs --------------------------------------------------------------------------


def seed_points() -> np.ndarray:
    """50 float32-exact points, so every encoding reads them back exactly."""
    rng = np.random.default_rng(7)
    return rng.uniform(-1.0, 1.0, size=(SEED_POINTS, 3)).astype(np.float32).astype(np.float64)


def _sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=1)  # 42 vertices, 80 faces


def _ply(encoding: str, *, faces: bool) -> bytes:
    points = seed_points()
    mesh = _sphere()
    vertices = np.asarray(mesh.vertices) if faces else points
    header = [b"ply", f"format {encoding} 1.0".encode(), b"comment fuzz seed"]
    header += [f"element vertex {len(vertices)}".encode()]
    header += [b"property float x", b"property float y", b"property float z", b"property uchar red"]
    if faces:
        header += [f"element face {len(mesh.faces)}".encode()]
        header += [b"property list uchar int vertex_indices"]
    header += [b"end_header"]
    head = b"\n".join(header) + b"\n"
    red = np.arange(len(vertices)) % 256
    if encoding == "ascii":
        rows = [f"{x:.9g} {y:.9g} {z:.9g} {r}" for (x, y, z), r in zip(vertices, red, strict=True)]
        if faces:
            rows += [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
        return head + ("\n".join(rows) + "\n").encode()
    endian = "<" if encoding == "binary_little_endian" else ">"
    vertex = np.dtype(
        [("x", f"{endian}f4"), ("y", f"{endian}f4"), ("z", f"{endian}f4"), ("r", "u1")]
    )
    rows_v = np.zeros(len(vertices), dtype=vertex)
    for i, axis in enumerate("xyz"):
        rows_v[axis] = vertices[:, i]
    rows_v["r"] = red
    body = rows_v.tobytes()
    if faces:
        face = np.dtype([("n", "u1"), ("i", f"{endian}i4", 3)])
        rows_f = np.zeros(len(mesh.faces), dtype=face)
        rows_f["n"] = 3
        rows_f["i"] = mesh.faces
        body += rows_f.tobytes()
    return head + body


@cache
def ply_seeds() -> tuple[bytes, ...]:
    encodings = ("ascii", "binary_little_endian", "binary_big_endian")
    return tuple(_ply(e, faces=f) for e in encodings for f in (False, True))


@cache
def pcd_seeds() -> tuple[bytes, ...]:
    """ASCII and binary written here, binary_compressed (LZF) by Open3D's own writer."""
    points = seed_points()
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
        f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(points)}\n"
    )
    rows = "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in points)
    ascii_pcd = (head + "DATA ascii\n" + rows).encode()
    binary_pcd = (head + "DATA binary\n").encode() + points.astype("<f4").tobytes()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "seed.pcd"
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        o3d.io.write_point_cloud(str(path), cloud, write_ascii=False, compressed=True)
        compressed_pcd = path.read_bytes()
    return ascii_pcd, binary_pcd, compressed_pcd


@cache
def obj_seeds() -> tuple[bytes, ...]:
    mesh = _sphere()
    rows = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.vertices]
    triangles = [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    negative = [f"f {a - 42}/1 {b - 42}/1 {c - 42}/1" for a, b, c in mesh.faces]
    plain = "\n".join(["# fuzz seed", "o sphere", *rows, *triangles]) + "\n"
    relative = "\n".join([*rows, "vt 0 0", *negative]) + "\n"
    return plain.encode(), relative.encode()


@cache
def stl_seeds() -> tuple[bytes, ...]:
    mesh = _sphere()
    return mesh.export(file_type="stl"), mesh.export(file_type="stl_ascii").encode()


@cache
def off_seeds() -> tuple[bytes, ...]:
    mesh = _sphere()
    rows = [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.vertices]
    faces = [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    counts = f"{len(rows)} {len(faces)} 0"
    return (
        "\n".join(["OFF", counts, *rows, *faces]).encode() + b"\n",
        "\n".join([f"OFF {counts}", "# comment", *rows, *faces]).encode() + b"\n",
    )


@cache
def glb_seeds() -> tuple[bytes, ...]:
    return (_sphere().export(file_type="glb"),)


@cache
def npy_seeds() -> tuple[bytes, ...]:
    points = seed_points()
    seeds = []
    for arr, version in (
        (points, (1, 0)),
        (points.astype("<f4"), (2, 0)),
        (points.astype(">f8"), (1, 0)),
    ):
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, arr, version=version)
        seeds.append(buffer.getvalue())
    return tuple(seeds)


@cache
def xyz_seeds() -> tuple[bytes, ...]:
    points = seed_points()
    plain = "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in points)
    normals = "# x y z nx ny nz\n" + "".join(
        f"{x:.9g}\t{y:.9g}\t{z:.9g} 0 0 1\n" for x, y, z in points
    )
    return plain.encode(), normals.encode()


@cache
def float32_seeds() -> tuple[bytes, ...]:
    return (seed_points().astype("<f4").tobytes(), np.zeros((1, 3), "<f4").tobytes())


# --- mutators ------------------------------------------------------------------------------

Mutator = Callable[[bytes, random.Random, Grammar], bytes]


def _header(data: bytes, grammar: Grammar) -> int:
    """Where the header ends (a text format without one: its first 4 KB are all header)."""
    if grammar.header_end is not None:
        at = data.find(grammar.header_end)
        if at >= 0:
            return at + len(grammar.header_end)
    return min(len(data), 4096)


def _random_bytes(rng: random.Random, most: int) -> bytes:
    return rng.randbytes(rng.randint(0, most))


def truncate(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    return data[: rng.randint(0, len(data))]


def flip_bytes(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    if not data:
        return data
    out = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
    return bytes(out)


def splice_random(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    """Random bytes over, into or instead of a span of the file."""
    start = rng.randint(0, len(data))
    end = min(len(data), start + rng.choice((0, 1, 4, 16, 256)))
    return data[:start] + _random_bytes(rng, 32) + data[end:]


def repeat_span(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    """More rows (or junk) than the header declares."""
    start = rng.randint(0, len(data))
    span = data[start : start + rng.randint(1, 512)]
    return data[:start] + span * rng.randint(2, 8) + data[start:]


def header_number(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    end = _header(data, grammar)
    numbers = list(re.finditer(rb"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?", data[:end]))
    if not numbers:
        return flip_bytes(data, rng, grammar)
    number = rng.choice(numbers)
    if rng.random() < 0.8:
        new = rng.choice(INTERESTING_NUMBERS).encode()
    else:
        whole_part = re.match(rb"[-+]?\d+", number.group())
        new = str(int(whole_part.group()) + rng.randint(-3, 3)).encode()
    return data[: number.start()] + new + data[number.end() :]


def header_word(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    end = _header(data, grammar)
    words = list(re.finditer(rb"[A-Za-z_][A-Za-z0-9_]*", data[:end]))
    if not words or not grammar.words:
        return flip_bytes(data, rng, grammar)
    word = rng.choice(words)
    return data[: word.start()] + rng.choice(grammar.words) + data[word.end() :]


def header_line(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    """A header line duplicated, dropped, moved, or a grammar line added."""
    end = _header(data, grammar)
    lines = data[:end].split(b"\n")
    if len(lines) < 2:
        return flip_bytes(data, rng, grammar)
    i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
    action = rng.randrange(4)
    if action == 0:
        lines.insert(j, lines[i])
    elif action == 1:
        del lines[i]
    elif action == 2:
        lines[i], lines[j] = lines[j], lines[i]
    else:
        lines.insert(j, b" ".join(rng.choice(grammar.words or (b"x",)) for _ in range(3)))
    return b"\n".join(lines) + data[end:]


def non_utf8(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    at = rng.randint(0, _header(data, grammar))
    return data[:at] + rng.choice(NON_UTF8) + data[at:]


def line_endings(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    return data.replace(b"\n", rng.choice((b"\r\n", b"\r", b"\n\n", b" \n", b"\x0b")))


def binary_word(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    """An aligned 4- or 8-byte word set to 0, -1, NaN, inf or a huge count, either byte order."""
    if len(data) < 8:
        return flip_bytes(data, rng, grammar)
    word = rng.choice(INTERESTING_WORDS)
    if rng.random() < 0.5:
        word = word[::-1]
    at = rng.randrange(0, len(data) - len(word) + 1, 4)
    return data[:at] + word + data[at + len(word) :]


TEXT_MUTATORS: tuple[Mutator, ...] = (
    truncate, flip_bytes, splice_random, repeat_span, header_number, header_number, header_word,
    header_word, header_line, header_line, non_utf8, line_endings,
)  # fmt: skip
BINARY_MUTATORS: tuple[Mutator, ...] = (
    truncate, flip_bytes, splice_random, repeat_span, binary_word, binary_word, header_number,
    header_word, non_utf8,
)  # fmt: skip


def mutate(
    seeds: tuple[bytes, ...], rng: random.Random, grammar: Grammar, mutators: tuple[Mutator, ...]
) -> bytes:
    """A valid seed put through one to three mutators; now and then random bytes instead."""
    roll = rng.random()
    if roll < 0.05:
        return _random_bytes(rng, 1024)
    if roll < 0.10:
        return grammar.magic + _random_bytes(rng, 1024)
    data = rng.choice(seeds)
    for _ in range(rng.randint(1, 3)):
        data = rng.choice(mutators)(data, rng, grammar)
    return data


# --- GLB: edit the JSON chunk and rebuild the container ------------------------------------

GLTF_VALUES: tuple[Any, ...] = (
    0, 1, -1, 2, 3, 4, 5, 6, 7, 2**31, 2**32, 2**53, 10**30, 1.5, float("nan"), True, None, "x",
    "data:application/octet-stream;base64,AAAA", "../../etc/passwd", [], {}, [0], [0, 0], {"x": 1},
    5120, 5123, 5125, 5126, "SCALAR", "VEC3", "MAT4", "POSITION",
)  # fmt: skip


def _gltf_slots(node: Any) -> list[tuple[Any, Any]]:
    """Every (container, key) in a parsed JSON tree, so that any value can be replaced."""
    slots = []
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, value in items:
        slots.append((node, key))
        slots.extend(_gltf_slots(value))
    return slots


def glb_json(data: bytes, rng: random.Random, grammar: Grammar) -> bytes:
    """One JSON value replaced, deleted or duplicated; every length in the container kept true."""
    if len(data) < 20 or data[:4] != b"glTF":
        return flip_bytes(data, rng, grammar)
    json_bytes = struct.unpack("<I", data[12:16])[0]
    try:
        gltf = json.loads(data[20 : 20 + json_bytes])
    except ValueError:
        return flip_bytes(data, rng, grammar)
    slots = _gltf_slots(gltf)
    for _ in range(rng.randint(1, 3)):
        if not slots:
            break
        container, key = rng.choice(slots)
        action = rng.random()
        if action < 0.7:
            container[key] = copy.deepcopy(rng.choice(GLTF_VALUES))
        elif action < 0.85 and isinstance(container, list):
            container.append(copy.deepcopy(container[key]))
        else:
            del container[key]
        slots = _gltf_slots(gltf)
    chunk = json.dumps(gltf).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = data[20 + json_bytes :]
    body = struct.pack("<I4s", len(chunk), b"JSON") + chunk + rest
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


# --- PointCloud2 messages ------------------------------------------------------------------

UINT32_EDGES = (0, 1, 3, 4, 8, 12, 16, 255, 2**16, 2**31 - 1, 2**31, 2**32 - 1)


def pointcloud2_message(*, big_endian: bool = False) -> SimpleNamespace:
    """A valid organized cloud: x, y, z float32, an intensity and padding; NaN marks no return."""
    width, height, point_step, row_step = 10, 5, 20, 10 * 20 + 8
    endian = ">" if big_endian else "<"
    record = np.dtype(
        {
            "names": ["x", "y", "z", "intensity"],
            "formats": [f"{endian}f4"] * 4,
            "offsets": [0, 4, 8, 12],
            "itemsize": point_step,
        }
    )
    rows = np.zeros((height, row_step), dtype=np.uint8)
    points = seed_points()
    view = rows[:, : width * point_step].copy().view(record).reshape(height, width)
    for i, axis in enumerate("xyz"):
        view[axis] = points[: width * height, i].reshape(height, width)
    view["x"][0, 0] = np.nan
    rows[:, : width * point_step] = view.view(np.uint8).reshape(height, -1)
    fields = [
        SimpleNamespace(name=name, offset=offset, datatype=7, count=1)
        for name, offset in (("x", 0), ("y", 4), ("z", 8), ("intensity", 12))
    ]
    return SimpleNamespace(
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=point_step,
        row_step=row_step,
        data=rows.tobytes(),
        is_dense=False,
    )


def _message_number(rng: random.Random, value: int) -> Any:
    """A message's integer edited: a uint32 edge, a neighbour, or a type a ROS field can hold."""
    roll = rng.random()
    if roll < 0.6:
        return rng.choice(UINT32_EDGES)
    if roll < 0.85:
        return max(0, value + rng.randint(-4, 4)) if isinstance(value, int) else 0
    return rng.choice((-1, np.uint32(12), np.int64(-3), True, 1.5, None, "12"))


def _message_data(rng: random.Random, data: bytes) -> Any:
    """The data edited, or the same bytes in another container a ROS binding may give."""
    kind = rng.randrange(7)
    if kind == 0:
        return data[: rng.randint(0, len(data))]
    if kind == 1:
        return flip_bytes(data, rng, Grammar(None, ()))
    if kind == 2:
        return list(data) + rng.choice(([], [256], [-1]))
    if kind == 3:
        return bytearray(data)
    if kind == 4:
        return array.array("B", data)
    if kind == 5:
        return memoryview(data)[:: rng.choice((1, 2))]
    return np.frombuffer(data[: len(data) // 4 * 4], dtype=np.float32)


def mutate_message(rng: random.Random) -> SimpleNamespace:
    """A valid message with one to three of its parts edited."""
    msg = pointcloud2_message(big_endian=rng.random() < 0.3)
    for _ in range(rng.randint(1, 3)):
        part = rng.choice(
            ("height", "width", "point_step", "row_step", "bigendian", "data", "field", "fields")
        )
        if part in ("height", "width", "point_step", "row_step"):
            setattr(msg, part, _message_number(rng, getattr(msg, part)))
        elif part == "bigendian":
            msg.is_bigendian = not msg.is_bigendian
        elif part == "data":
            msg.data = _message_data(rng, bytes(msg.data) if isinstance(msg.data, bytes) else b"")
        elif part == "field":
            field = rng.choice(msg.fields)
            attribute = rng.choice(("name", "offset", "datatype", "count"))
            if attribute == "name":
                field.name = rng.choice(("x", "y", "z", "", "X", None))
            else:
                setattr(field, attribute, _message_number(rng, getattr(field, attribute)))
        else:
            action = rng.randrange(3)
            if action == 0 and msg.fields:
                msg.fields.pop(rng.randrange(len(msg.fields)))
            elif action == 1:
                msg.fields.append(
                    SimpleNamespace(**vars(rng.choice(msg.fields or [SimpleNamespace()])))
                )
            else:
                rng.shuffle(msg.fields)
    return msg


# --- the property --------------------------------------------------------------------------


def assert_points(points: object, max_points: int | None) -> int:
    """The property's success half: finite (N, 3) float64 points within the limit; returns N."""
    assert isinstance(points, np.ndarray), f"read {type(points).__name__}, not an array"
    assert points.dtype == np.float64, f"read dtype {points.dtype}"
    assert points.ndim == 2 and points.shape[1] == 3 and len(points) > 0, f"shape {points.shape}"
    assert np.isfinite(points).all(), "read non-finite coordinates"
    assert max_points is None or len(points) <= max_points, f"{len(points)} > {max_points}"
    return len(points)


def run_target(target: Target, data: Any, folder: Path) -> int:
    """Read ``data``: the number of points read, or 0 when the project's error refused it.

    Any other exception, and any violation of the property, propagates.
    """
    try:
        with address_space_capped():
            points = target.read(data, folder)
    except target.errors:
        return 0
    return assert_points(points, target.max_points)


# --- the targets ---------------------------------------------------------------------------


def _write(data: bytes, folder: Path, suffix: str) -> Path:
    path = folder / f"fuzz{suffix}"
    path.write_bytes(data)
    return path


def _service_reader(suffix: str) -> Callable[[bytes, Path], np.ndarray]:
    """How the API reads an upload: every header check, the limits, then the format's reader."""

    def read(data: bytes, folder: Path) -> np.ndarray:
        shape = read_shape(_write(data, folder, suffix), max_points=MAX_POINTS, max_faces=MAX_FACES)
        if shape.mesh is not None:
            faces = shape.mesh.faces
            assert faces.ndim == 2 and faces.shape[1] == 3, f"faces of shape {faces.shape}"
            assert len(faces) <= MAX_FACES, f"{len(faces)} faces > {MAX_FACES}"
            assert faces.size == 0 or (
                faces.min() >= 0 and faces.max() < len(shape.mesh.vertices)
            ), f"faces index vertices outside 0..{len(shape.mesh.vertices) - 1}"
        return shape.points

    return read


def _client_reader(suffix: str) -> Callable[[bytes, Path], np.ndarray]:
    """How the CLI reads a local file: the SDK's reader, then the SDK's point check."""

    def read(data: bytes, folder: Path) -> np.ndarray:
        points = client_read_points(_write(data, folder, suffix))
        assert isinstance(points, np.ndarray) and points.ndim == 2 and points.shape[1] == 3, (
            f"the SDK reader returned {type(points).__name__} {getattr(points, 'shape', '')}"
        )
        return as_points(points)

    return read


def _read_raw_float32(data: bytes, folder: Path) -> np.ndarray:
    query = decode_binary(data, RegisterOptions(), MAX_POINTS)
    assert query.points is not None
    return query.points


def _read_message(msg: SimpleNamespace, folder: Path) -> np.ndarray:
    return pointcloud2_points(msg)


PLY = Grammar(
    b"end_header\n",
    (b"ply", b"format", b"ascii", b"binary_little_endian", b"binary_big_endian", b"element",
     b"vertex", b"face", b"property", b"list", b"float", b"double", b"uchar", b"int", b"int64",
     b"uint", b"char", b"x", b"y", b"z", b"end_header", b"comment", b"obj_info"),
    b"ply\nformat binary_little_endian 1.0\n",
)  # fmt: skip
PCD = Grammar(
    b"\nDATA ",
    (b"FIELDS", b"SIZE", b"TYPE", b"COUNT", b"WIDTH", b"HEIGHT", b"POINTS", b"DATA", b"VIEWPOINT",
     b"ascii", b"binary", b"binary_compressed", b"x", b"y", b"z", b"rgb", b"F", b"U", b"I",
     b"COLUMNS"),
    b"VERSION 0.7\nFIELDS x y z\nPOINTS 1\nDATA binary\n",
)  # fmt: skip
OBJ = Grammar(
    None, (b"v", b"vn", b"vt", b"f", b"l", b"o", b"g", b"usemtl", b"mtllib", b"s"), b"v 0 0 0\n"
)
STL = Grammar(
    None,
    (b"solid", b"facet", b"normal", b"outer", b"loop", b"vertex", b"endloop", b"endfacet",
     b"endsolid"),
    b"solid fuzz\n",
)  # fmt: skip
OFF = Grammar(None, (b"OFF", b"COFF", b"NOFF", b"STOFF", b"nOFF"), b"OFF\n")
GLB = Grammar(None, (b"JSON", b"BIN"), b"glTF\x02\x00\x00\x00")
NPY = Grammar(
    b"\n",
    (b"descr", b"fortran_order", b"shape", b"True", b"False", b"f8", b"f4", b"i8", b"O", b"U3",
     b"V12", b"c16", b"S8", b"b1", b"M8"),
    b"\x93NUMPY\x01\x00",
)  # fmt: skip
XYZ = Grammar(None, (b"nan", b"inf", b"e", b"x"), b"")
RAW = Grammar(None, (), b"")

_TEXT, _BINARY = TEXT_MUTATORS, BINARY_MUTATORS


NPY_MUTATORS = (*_BINARY, header_number, header_word)
GLB_MUTATORS = (*_BINARY, *(glb_json,) * 6)
SERVICE_ERRORS = (CatalignError,)
CLIENT_ERRORS = (ClientError, UnsupportedFileError)
Seeds = Callable[[], tuple[bytes, ...]]


def _files(seeds: Seeds, grammar: Grammar, mutators: tuple[Mutator, ...]) -> Callable[..., bytes]:
    return lambda rng: mutate(seeds(), rng, grammar, mutators)


def _service(suffix: str, seeds: Seeds, grammar: Grammar, mutators: tuple[Mutator, ...]) -> Target:
    generate = _files(seeds, grammar, mutators)
    return Target(suffix[1:], generate, _service_reader(suffix), SERVICE_ERRORS, MAX_POINTS)


def _sdk(suffix: str, seeds: Seeds, grammar: Grammar, mutators: tuple[Mutator, ...]) -> Target:
    generate = _files(seeds, grammar, mutators)
    return Target(f"sdk-{suffix[1:]}", generate, _client_reader(suffix), CLIENT_ERRORS, None)


TARGETS: dict[str, Target] = {
    target.name: target
    for target in (
        _service(".ply", ply_seeds, PLY, _TEXT + _BINARY),
        _service(".pcd", pcd_seeds, PCD, _TEXT + _BINARY),
        _service(".obj", obj_seeds, OBJ, _TEXT),
        _service(".stl", stl_seeds, STL, _TEXT + _BINARY),
        _service(".off", off_seeds, OFF, _TEXT),
        _service(".glb", glb_seeds, GLB, GLB_MUTATORS),
        _service(".npy", npy_seeds, NPY, NPY_MUTATORS),
        _service(".xyz", xyz_seeds, XYZ, _TEXT),
        Target(
            "raw-float32",
            _files(float32_seeds, RAW, _BINARY),
            _read_raw_float32,
            SERVICE_ERRORS,
            MAX_POINTS,
        ),
        _sdk(".ply", ply_seeds, PLY, _TEXT + _BINARY),
        _sdk(".pcd", pcd_seeds, PCD, _TEXT + _BINARY),
        _sdk(".npy", npy_seeds, NPY, NPY_MUTATORS),
        _sdk(".xyz", xyz_seeds, XYZ, _TEXT),
        Target("sdk-pointcloud2", mutate_message, _read_message, CLIENT_ERRORS, None),
    )
}
