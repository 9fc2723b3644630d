"""Shape sources: the shared ShapeNet chairs and tables and our own procedural chairs, by id.

All give :class:`Shape` objects in the common canonical frame (+Y up, a chair's backrest on +Z).
The shared meshes come from another release than the point clouds and are turned a quarter
turn about +Y (backrest on -X): :data:`MESH_TO_CANONICAL` turns them into the common frame on
load (measured on all 15: ``tests/data/test_shapes.py`` checks every shared chair's backrest).
The shared shapes come size-normalised (bounding-box diagonal about 1); :func:`to_metric`
scales a shape to a realistic height for its category (chairs 0.75-1.05 m, tables 0.45-0.8 m)
so that sensor noise and centimetre thresholds mean what they say. The train/validation split
of the shared shapes is fixed by a hash of the id
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
# Realistic heights (metres) a size-normalised shape of each category is given.
METRIC_HEIGHT_RANGES = {"chair": (0.75, 1.05), "table": (0.45, 0.8)}
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


def metric_height(shape_id: str, category: str = "chair") -> float:
    """The realistic height (metres) a size-normalised shape of ``category`` is given, fixed by
    its id."""
    low, high = METRIC_HEIGHT_RANGES[category]
    return low + (high - low) * stable_fraction("height:" + shape_id)


def to_metric(shape: Shape, height: float | None = None, category: str = "chair") -> Shape:
    """Scale a size-normalised shape so that it stands ``height`` metres tall (by default, a
    height fixed by its id in its ``category``'s range)."""
    target = metric_height(shape.shape_id, category) if height is None else height
    return shape.scaled(target / shape.height)


def default_chairs_root() -> Path:
    """``$CATALIGN_CHAIRS_DIR``, else ``shared/data/chairs`` beside the repository."""
    env = os.environ.get("CATALIGN_CHAIRS_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3].parent / "shared" / "data" / "chairs"


def default_tables_root() -> Path:
    """``$CATALIGN_TABLES_DIR``, else ``shared/data/tables`` beside the repository."""
    env = os.environ.get("CATALIGN_TABLES_DIR")
    if env:
        return Path(env)
    return default_chairs_root().parent / "tables"


class SharedChairs:
    """The shared ShapeNet chairs: ``pointclouds/<id>.npy`` and ``meshes/<id>.obj``.

    Example::

        chairs = SharedChairs()
        val_ids = chairs.ids("val")
        shape = to_metric(chairs.load(val_ids[0]))
    """

    category = "chair"
    variable = "CATALIGN_CHAIRS_DIR"

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = Path(root) if root is not None else self.default_root()
        if not self.root.is_dir():
            raise ShapeReadError(
                f"shared {self.category}s not found at {self.root}; set {self.variable} to the "
                "folder that holds pointclouds/"
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
            raise ShapeReadError(
                f"no shared {self.category} with id {shape_id!r} in {self.root}"
            ) from None

    @staticmethod
    def default_root() -> Path:
        return default_chairs_root()

    def metric(self, shape_id: str) -> Shape:
        """A shape scaled to a realistic height of its category."""
        return to_metric(self.load(shape_id), category=self.category)


class SharedTables(SharedChairs):
    """The shared ShapeNet tables (``pointclouds/<id>.npy``), in the chairs' frame."""

    category = "table"
    variable = "CATALIGN_TABLES_DIR"

    @staticmethod
    def default_root() -> Path:
        return default_tables_root()


def shared_shapes(category: str, root: str | Path | None = None) -> SharedChairs:
    """The shared shapes of ``category`` (chair or table)."""
    sources = {"chair": SharedChairs, "table": SharedTables}
    if category not in sources:
        raise ShapeReadError(f"no shared shapes of category {category!r}; use chair or table")
    return sources[category](root)


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
