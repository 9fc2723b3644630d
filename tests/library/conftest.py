"""Fixtures for the library tests: a fast deterministic extractor and real shape files."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import sqlite3
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from catalign.features.extractor import Described
from catalign.geometry.sampling import voxel_downsample
from catalign.library.entry import LibraryEntry
from catalign.library.entry_codec import entry_bytes
from catalign.library.loaded import load
from catalign.library.npz import npz_arrays
from catalign.library.quantise import point_steps
from catalign.library.records import EntryRecord, entry_file_name
from catalign.library.store import read_manifest


class FakeExtractor:
    """Voxel centroids with 4-D features (offset from the centre and its length): fast and
    deterministic, and different shapes get different descriptors."""

    voxel_size = 0.05
    fingerprint = "fake-v1"
    retrieval = None  # the pooled features shortlist

    def describe(self, points: np.ndarray) -> Described:
        centroids, _ = voxel_downsample(points, self.voxel_size)
        offsets = centroids - centroids.mean(axis=0)
        radius = np.linalg.norm(offsets, axis=1, keepdims=True)
        return Described(centroids, np.hstack([offsets, radius]).astype(np.float32))


@pytest.fixture
def extractor() -> FakeExtractor:
    return FakeExtractor()


def random_cloud(seed: int, count: int = 600, scale: float = 0.4) -> np.ndarray:
    """Points uniform in a cube of half-side ``scale`` (metres)."""
    return np.random.default_rng(seed).uniform(-scale, scale, size=(count, 3))


def write_cloud(path: Path, points: np.ndarray) -> Path:
    """Write points as .npy, .xyz, .pcd or .ply (by suffix)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npy":
        np.save(path, points)
    elif path.suffix == ".xyz":
        np.savetxt(path, points)
    else:
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        o3d.io.write_point_cloud(str(path), cloud)
    return path


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return path


class ShapeFiles:
    """Writes shape files under one folder (tests get it as the ``files`` fixture)."""

    random_cloud = staticmethod(random_cloud)

    def __init__(self, root: Path) -> None:
        self.root = root

    def cloud(self, name: str, seed: int = 0, count: int = 600, scale: float = 0.4) -> Path:
        return write_cloud(self.root / name, random_cloud(seed, count, scale))

    def points(self, name: str, points: np.ndarray) -> Path:
        return write_cloud(self.root / name, points)

    def mesh(self, name: str, mesh: trimesh.Trimesh) -> Path:
        return write_mesh(self.root / name, mesh)

    def box(self, name: str, extents: tuple[float, float, float] = (0.5, 0.9, 0.5)) -> Path:
        return self.mesh(name, trimesh.creation.box(extents=extents))


@pytest.fixture
def files(tmp_path: Path) -> ShapeFiles:
    return ShapeFiles(tmp_path / "src")


@pytest.fixture
def mixed_folder(files: ShapeFiles) -> Path:
    """A folder tree with every supported format and one file to ignore."""
    files.box("box.ply")
    files.mesh("sub/cylinder.obj", trimesh.creation.cylinder(radius=0.3, height=0.8))
    files.mesh("sub/sphere.stl", trimesh.creation.icosphere(radius=0.35))
    files.mesh("cone.off", trimesh.creation.cone(radius=0.3, height=0.7))
    files.mesh("deep/er/capsule.glb", trimesh.creation.capsule(height=0.6, radius=0.2))
    files.cloud("big.npy", seed=1, count=12_000)
    files.cloud("sub/scan.xyz", seed=2)
    files.cloud("scan2.pcd", seed=3)
    files.cloud("points.ply", seed=4)
    (files.root / "README.txt").write_text("not a shape")
    return files.root


def stored(library_dir: Path, query: str) -> list[tuple[Any, ...]]:
    """The rows ``query`` finds in the library's catalogue file, read as any SQLite client."""
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection:
        return connection.execute(query).fetchall()


def as_format_2(library_dir: Path) -> dict[str, Any]:
    """Turn a library back into format 2 (its catalogue as the ``manifest.json`` catalign
    wrote before format 3, which users still have, its entries in the full layout) and return
    that JSON."""
    manifest = read_manifest(library_dir)
    records = _full_entry_files(library_dir)
    raw = {
        "format_version": 2,
        "extractor": {"fingerprint": manifest.fingerprint, "voxel_size": manifest.voxel_size},
        "created": manifest.created,
        "updated": manifest.updated,
        "entries": {i: _without_descriptor(records[i].to_json()) for i in manifest.ids},
        "engine": manifest.engine,
        "category": manifest.category,
    }
    (library_dir / "catalogue.sqlite").unlink()
    write_format_2(library_dir, raw)
    return raw


def as_format_3(library_dir: Path) -> None:
    """Turn a library back into format 3: its entries in the full layout, its catalogue
    without the descriptor column, as catalign wrote before format 4."""
    records = _full_entry_files(library_dir)
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection, connection:
        connection.execute("ALTER TABLE entries DROP COLUMN descriptor")
        connection.execute("UPDATE library SET format_version = 3")
        connection.executemany(
            "UPDATE entries SET file = ?, sha256 = ? WHERE model_id = ?",
            [(r.file, r.sha256, i) for i, r in records.items()],
        )


def earlier_layout_bytes(entry: LibraryEntry) -> bytes:
    """``entry``'s file in the entry layout before the current one: the surface's steps as rows
    in sampling order, float32 key points, the grid's 255 levels, deflated members."""
    arrays = npz_arrays(entry_bytes(entry))
    for name in ("surface_steps", "keypoint_steps", "grid_steps"):
        del arrays[name]
    shuffled = np.random.default_rng(0).permutation(len(entry.points))
    arrays["point_steps"] = point_steps(entry.points[shuffled], entry.bbox_min, entry.bbox_max)
    arrays["keypoints"] = entry.keypoints.astype(np.float32)
    arrays["grid"] = np.asarray(entry.grid.values)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def as_earlier_layout(library_dir: Path) -> None:
    """Rewrite every entry file of a library of the current format in the earlier entry
    layout (:func:`earlier_layout_bytes`), and point its row at it."""
    manifest, library = read_manifest(library_dir), load(library_dir, None)
    rows = []
    for model_id, record in manifest.entries.items():
        data = earlier_layout_bytes(library[model_id])
        sha256 = hashlib.sha256(data).hexdigest()
        file = entry_file_name(model_id, sha256)
        (library_dir / record.file).unlink()
        (library_dir / file).write_bytes(data)
        rows.append((file, sha256, model_id))
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection, connection:
        connection.executemany("UPDATE entries SET file = ?, sha256 = ? WHERE model_id = ?", rows)


def _without_descriptor(record: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in record.items() if k != "descriptor"}


def _full_entry_files(library_dir: Path) -> dict[str, EntryRecord]:
    """Rewrite every entry file in the layout of formats 2 and 3 (every array at full
    precision, uncompressed) holding the same values; the records that name the new files."""
    manifest, library = read_manifest(library_dir), load(library_dir, None)
    records = {}
    for model_id, record in manifest.entries.items():
        entry = library[model_id]
        buffer = io.BytesIO()
        np.savez(
            buffer,
            model_id=np.array(model_id),
            points=entry.points,
            keypoints=entry.keypoints,
            features=entry.features,
            descriptor=entry.descriptor,
            bbox_min=entry.bbox_min,
            bbox_max=entry.bbox_max,
            size=entry.size,
            grid=entry.grid.values,
            grid_origin=entry.grid.origin,
            grid_cell_step=np.array([entry.grid.cell, entry.grid.step]),
            source=np.array(entry.source),
            source_sha256=np.array(entry.source_sha256),
            units=np.array(entry.units),
        )
        data = buffer.getvalue()
        sha256 = hashlib.sha256(data).hexdigest()
        file = entry_file_name(model_id, sha256)
        (library_dir / record.file).unlink()
        (library_dir / file).write_bytes(data)
        records[model_id] = dataclasses.replace(record, file=file, sha256=sha256, descriptor=b"")
    return records


def write_format_2(library_dir: Path, raw: dict[str, Any]) -> None:
    (library_dir / "manifest.json").write_text(json.dumps(raw, indent=2) + "\n")


def _snapshot(library_dir: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(library_dir)): p.read_bytes()
        for p in sorted(library_dir.rglob("*"))
        if p.is_file() and p.name not in (".lock", ".writing")
    }


@pytest.fixture
def snapshot():
    """Function: every file of a library (the writers' lock and mark aside) and its bytes."""
    return _snapshot


def without_outlines(library_dir: Path) -> None:
    """Turn a library's catalogue back into one of format 4 written before entries had
    outlines: without their column."""
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection, connection:
        connection.execute("ALTER TABLE entries DROP COLUMN outline")
