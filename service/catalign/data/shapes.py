"""Shape sources: the shared ShapeNet chairs and our own procedural chairs, loaded by id.

Both give :class:`Shape` objects in the common canonical chair frame (+Y up, backrest on +Z).
The shared meshes come from another release than the point clouds and are turned a quarter
turn about +Y (backrest on -X): :data:`MESH_TO_CANONICAL` turns them into the common frame on
load (measured on all 15: ``tests/data/test_shapes.py`` checks every shared chair's backrest).
The shared chairs come size-normalised (bounding-box diagonal about 1); :func:`to_metric`
scales a shape to a realistic chair height so that sensor noise and centimetre thresholds mean
what they say. The train/validation split of the shared chairs is fixed by a hash of the id
(:func:`split_of`), so it never depends on file order or on which files are present.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np

from catalign.errors import ShapeReadError
from catalign.geometry.io import MeshData, read_shape
from catalign.geometry.sampling import sample_surface

Split = Literal["train", "val"]
TRAIN_PERCENT = 70
SURFACE_POINTS = 15_000
METRIC_HEIGHT_RANGE = (0.75, 1.05)
# The shared meshes' frame to the point clouds' (a +90 degree turn about +Y: -X goes to +Z).
MESH_TO_CANONICAL = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class Shape:
    """One chair: uniform surface points, and its mesh when the source has one."""

    shape_id: str
    points: np.ndarray
    mesh: MeshData | None = None

    def scaled(self, factor: float) -> Shape:
        """The same shape scaled about the origin."""
        mesh = None
        if self.mesh is not None:
            mesh = MeshData(vertices=self.mesh.vertices * factor, faces=self.mesh.faces)
        return replace(self, points=self.points * factor, mesh=mesh)

    @property
    def height(self) -> float:
        """Extent along the canonical up axis (+Y)."""
        return float(np.ptp(self.points[:, 1]))


def stable_fraction(key: str) -> float:
    """A number in [0, 1) fixed by ``key`` alone (independent of Python's hash seed)."""
    digest = hashlib.sha256(key.encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2**64


def split_of(shape_id: str) -> Split:
    """Train/validation split of a shared chair: about 70/30, decided by a hash of its id."""
    return "train" if stable_fraction(shape_id) * 100 < TRAIN_PERCENT else "val"


def metric_height(shape_id: str) -> float:
    """The realistic height (metres) a size-normalised shape is given, fixed by its id."""
    low, high = METRIC_HEIGHT_RANGE
    return low + (high - low) * stable_fraction("height:" + shape_id)


def to_metric(shape: Shape, height: float | None = None) -> Shape:
    """Scale a size-normalised shape so that it stands ``height`` metres tall."""
    target = metric_height(shape.shape_id) if height is None else height
    return shape.scaled(target / shape.height)


def default_chairs_root() -> Path:
    """``$CATALIGN_CHAIRS_DIR``, else ``shared/data/chairs`` beside the repository."""
    env = os.environ.get("CATALIGN_CHAIRS_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3].parent / "shared" / "data" / "chairs"


class SharedChairs:
    """The shared ShapeNet chairs: ``pointclouds/<id>.npy`` and ``meshes/<id>.obj``.

    Example::

        chairs = SharedChairs()
        val_ids = chairs.ids("val")
        shape = to_metric(chairs.load(val_ids[0]))
    """

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = Path(root) if root is not None else default_chairs_root()
        if not self.root.is_dir():
            raise ShapeReadError(
                f"shared chairs not found at {self.root}; set CATALIGN_CHAIRS_DIR to the folder "
                "that holds pointclouds/ and meshes/"
            )
        self._files = {
            p.stem: p
            for folder in ("pointclouds", "meshes")
            for p in sorted((self.root / folder).glob("*"))
            if p.suffix in (".npy", ".obj")
        }

    def ids(self, split: Split | None = None) -> list[str]:
        """Sorted ids, all of them or those of one split."""
        return sorted(i for i in self._files if split is None or split_of(i) == split)

    def has_mesh(self, shape_id: str) -> bool:
        return self._path(shape_id).suffix == ".obj"

    def load(self, shape_id: str) -> Shape:
        return _load_file(self._path(shape_id))

    def _path(self, shape_id: str) -> Path:
        try:
            return self._files[shape_id]
        except KeyError:
            raise ShapeReadError(f"no shared chair with id {shape_id!r} in {self.root}") from None


@lru_cache(maxsize=256)
def _load_file(path: Path) -> Shape:
    data = read_shape(path)
    if data.mesh is None:
        return Shape(shape_id=path.stem, points=data.points.astype(np.float64))
    mesh = MeshData(vertices=data.mesh.vertices @ MESH_TO_CANONICAL.T, faces=data.mesh.faces)
    rng = np.random.default_rng(int(stable_fraction(path.stem) * 2**32))
    points = sample_surface(mesh.vertices, mesh.faces, SURFACE_POINTS, rng)
    return Shape(shape_id=path.stem, points=points, mesh=mesh)


class ProceduralChairs:
    """Our own parametric chairs (``proc-0000`` ...), metric, one per seed."""

    def __init__(self, count: int, first_seed: int = 0) -> None:
        self.seeds = range(first_seed, first_seed + count)

    def ids(self) -> list[str]:
        return [procedural_id(s) for s in self.seeds]

    def load(self, shape_id: str) -> Shape:
        return procedural_shape(seed_of(shape_id))

    def __iter__(self) -> Iterator[Shape]:
        return (procedural_shape(s) for s in self.seeds)


def procedural_id(seed: int) -> str:
    return f"proc-{seed:04d}"


def seed_of(shape_id: str) -> int:
    prefix, _, number = shape_id.partition("-")
    if prefix != "proc" or not number.isdigit():
        raise ShapeReadError(f"{shape_id!r} is not a procedural chair id (expected proc-NNNN)")
    return int(number)


@lru_cache(maxsize=1024)
def procedural_shape(seed: int) -> Shape:
    """The procedural chair of ``seed`` with uniform surface samples."""
    from catalign.data.procedural import generate_chair

    mesh = generate_chair(seed)
    data = MeshData(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
    )
    rng = np.random.default_rng(seed)
    points = sample_surface(data.vertices, data.faces, SURFACE_POINTS, rng)
    return Shape(shape_id=procedural_id(seed), points=points, mesh=data)
