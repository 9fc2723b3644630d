"""One library entry: a shape turned into everything registration needs, computed once.

A mesh is sampled by area (:data:`SURFACE_POINTS` points, more for a model larger than a chair:
:func:`surface_count`), a point cloud is subsampled to at most as many; both with a generator
seeded from the source's sha256, so the same file always gives the same entry. Coordinates are
converted to metres (``source * unit_factor(units)``) before anything is stored, so a pose found
against an entry maps *source coordinates converted to metres* into the observation. The
points are narrowed to what their file keeps (:mod:`~catalign.library.quantise`) before
anything is computed from them. The extractor then gives key points and features,
and :class:`~catalign.geometry.distance_grid.DistanceGrid` the surface's truncated distance
field that verification reads instead of searching the points (its levels narrowed to six
bits); the entry keeps the :data:`~catalign.library.quantise.STORED_KEYPOINTS` key points
matching reads (narrowed to 16-bit steps), their features narrowed to 8 bits, and
:func:`~catalign.library.retrieval.model_descriptor` the vector used for shortlisting, from
exactly those (so that new retrieval encoders can describe a built library again from its
entries: :mod:`~catalign.library.redescribe`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from catalign.errors import DegenerateInputError, ShapeReadError
from catalign.geometry.distance_grid import CELL_VOXELS, TRUNCATION_VOXELS, DistanceGrid
from catalign.geometry.io import MeshData, ShapeData, read_shape
from catalign.geometry.sampling import sample_surface, subsample, voxel_downsample
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry, find_yaw_symmetry
from catalign.library.quantise import (
    STORED_KEYPOINTS,
    narrowed_features,
    narrowed_grid,
    narrowed_keypoints,
    narrowed_points,
    stored_rows,
    stored_surface,
)
from catalign.library.retrieval import model_descriptor
from catalign.library.sources import DEFAULT_CATEGORY, SourceFile, unit_factor
from catalign.limits import MIN_VOXELS

if TYPE_CHECKING:  # the extractor module imports torch; entries only need its interface
    from catalign.features.extractor import FeatureExtractor

SURFACE_POINTS = 10_000
# Up to this bounding-box diagonal (metres; every chair of the default library) a model gets
# SURFACE_POINTS, beyond it as many more as keep the same density, up to MAX_SURFACE_POINTS.
DENSITY_DIAGONAL = 2.0
MAX_SURFACE_POINTS = 40_000
_CHUNK = 1 << 20


@dataclass(frozen=True, eq=False)
class LibraryEntry:
    """A described library model; all coordinates in metres, arrays read-only once loaded.

    ``points`` (N,3) float32 surface samples, ``keypoints`` (M,3) float64 and ``features`` (M,D)
    float32 from the extractor (at most :data:`~catalign.library.quantise.STORED_KEYPOINTS`),
    ``descriptor`` (K,) float32 for shortlisting, and the bounding
    box of the whole source shape, ``grid`` the distance field of ``points`` over that box.
    ``source`` is the file path (or ``procedural:<seed>``), ``source_sha256`` its checksum,
    ``units`` the unit the source was declared in, ``category`` the kind of object it is and
    ``symmetry`` the turns about its up under which it looks the same (both kept in the
    manifest, not in the entry's file: :mod:`~catalign.library.sources`,
    :mod:`~catalign.geometry.symmetry`).
    """

    model_id: str
    points: np.ndarray
    keypoints: np.ndarray
    features: np.ndarray
    descriptor: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    size: np.ndarray
    grid: DistanceGrid
    source: str
    source_sha256: str
    units: str
    category: str = DEFAULT_CATEGORY
    symmetry: YawSymmetry = NO_SYMMETRY

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def centre(self) -> np.ndarray:
        """The bounding-box centre: the origin of the category-level frame."""
        return (self.bbox_min + self.bbox_max) / 2


def file_sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def mesh_sha256(mesh: MeshData) -> str:
    """Hex sha256 of a mesh's arrays (float64 vertices then int64 faces, little-endian)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    return digest.hexdigest()


def seed_from_checksum(sha256: str) -> int:
    """A 64-bit generator seed taken from a hex checksum."""
    return int(sha256[:16], 16)


def surface_count(extent_points: np.ndarray, num_points: int) -> int:
    """How many surface points sample a model whose points or vertices (metres) are
    ``extent_points``: ``num_points``, or for a model wider than :data:`DENSITY_DIAGONAL`
    across, as many more as its surface is larger (the square of its size), at most
    :data:`MAX_SURFACE_POINTS`. The fit that tells the observed instance itself (``exact_fitness``
    of the query within the ICP distance of the samples) needs a chair's density: a 2.9 m sofa's
    own views fitted 0.74 to 0.77 of their points at the true pose on 10,000 samples, 0.92 to
    0.95 on 20,000 and 0.98 on 30,000."""
    if len(extent_points) == 0:
        return num_points
    diagonal = float(np.linalg.norm(extent_points.max(axis=0) - extent_points.min(axis=0)))
    scaled = num_points * max(1.0, diagonal / DENSITY_DIAGONAL) ** 2
    return int(min(max(num_points, MAX_SURFACE_POINTS), round(scaled)))


def describe_shape(
    model_id: str,
    shape: ShapeData,
    extractor: FeatureExtractor,
    *,
    source: str,
    source_sha256: str,
    units: str = "m",
    num_points: int = SURFACE_POINTS,
) -> LibraryEntry:
    """Sample, convert to metres and describe ``shape`` as the entry ``model_id``."""
    factor = unit_factor(units)
    rng = np.random.default_rng(seed_from_checksum(source_sha256))
    if shape.mesh is not None:
        vertices = shape.mesh.vertices * factor
        try:
            count = surface_count(vertices, num_points)
            points = sample_surface(vertices, shape.mesh.faces, count, rng)
        except ValueError as exc:  # zero surface area
            raise ShapeReadError(f"{source}: cannot sample the mesh ({exc})") from exc
        extent_points = vertices
    else:
        extent_points = shape.points * factor
        points = subsample(extent_points, surface_count(extent_points, num_points), rng)
    bbox_min = extent_points.min(axis=0).astype(np.float64)
    bbox_max = extent_points.max(axis=0).astype(np.float64)
    points = narrowed_points(points, bbox_min, bbox_max)
    voxels = len(voxel_downsample(points, extractor.voxel_size)[0])
    if voxels < MIN_VOXELS:
        raise DegenerateInputError(
            f"{source}: model {model_id!r} occupies only {voxels} voxels of "
            f"{extractor.voxel_size:g} m, and a query needs at least {MIN_VOXELS}; a model must "
            "be at least as large as what it is matched with (is the declared unit right?)"
        )
    described = extractor.describe(points.astype(np.float64))
    if len(described.keypoints) == 0:
        raise DegenerateInputError(
            f"{source}: the extractor found no key points in model {model_id!r} "
            f"({len(points)} points, voxel size {extractor.voxel_size:g} m); "
            "is the declared unit right?"
        )
    voxel = extractor.voxel_size
    grid = DistanceGrid.around(
        points,
        cell=CELL_VOXELS * voxel,
        truncation=TRUNCATION_VOXELS * voxel,
        low=bbox_min,
        high=bbox_max,
    )
    grid = narrowed_grid(grid)
    kept = stored_rows(len(described.keypoints), STORED_KEYPOINTS)
    keypoints = narrowed_keypoints(described.keypoints[kept], *grid.box)
    features = narrowed_features(described.features[kept])
    return LibraryEntry(
        model_id=model_id,
        points=stored_surface(points, bbox_min, bbox_max),
        keypoints=keypoints,
        features=features,
        descriptor=model_descriptor(extractor, keypoints, features),
        bbox_min=bbox_min,
        bbox_max=bbox_max,
        size=bbox_max - bbox_min,
        grid=grid,
        source=source,
        source_sha256=source_sha256,
        units=units,
        symmetry=find_yaw_symmetry(points),
    )


def narrowed_entry(entry: LibraryEntry) -> LibraryEntry:
    """``entry`` as the current layout stores it, for an entry read from a file of an earlier
    one (its surface in 16-bit steps in sampling order, float32 key points, 255 grid levels):
    narrowing what is already narrowed changes nothing. The descriptor is kept: it was
    computed from key points at most a 16-bit step of the grid's box (0.01 mm for a chair)
    from the narrowed ones."""
    grid = narrowed_grid(entry.grid)
    return replace(
        entry,
        points=stored_surface(entry.points, entry.bbox_min, entry.bbox_max),
        keypoints=narrowed_keypoints(entry.keypoints, *grid.box),
        grid=grid,
    )


def describe_file(
    source: SourceFile,
    extractor: FeatureExtractor,
    units: str = "m",
    num_points: int = SURFACE_POINTS,
    source_name: str | None = None,
    max_points: int | None = None,
) -> LibraryEntry:
    """Read and describe one shape file; the source is recorded as ``source_name`` when given
    (an upload's original name), else as the file's absolute path. A file with more than
    ``max_points`` points or vertices is refused from its header."""
    shape = read_shape(source.path, max_points=max_points)
    entry = describe_shape(
        source.model_id,
        shape,
        extractor,
        source=source_name or str(source.path.resolve()),
        source_sha256=file_sha256(source.path),
        units=units,
        num_points=num_points,
    )
    return replace(entry, category=source.category)


def describe_procedural(
    seed: int, extractor: FeatureExtractor, num_points: int = SURFACE_POINTS
) -> LibraryEntry:
    """Describe the procedural chair of ``seed`` as entry ``proc-NNNN`` (metres)."""
    from catalign.data.procedural import generate_chair
    from catalign.data.shapes import procedural_id

    generated = generate_chair(seed)
    mesh = MeshData(
        vertices=np.asarray(generated.vertices, dtype=np.float64),
        faces=np.asarray(generated.faces, dtype=np.int64),
    )
    return describe_shape(
        procedural_id(seed),
        ShapeData(points=mesh.vertices, mesh=mesh),
        extractor,
        source=f"procedural:{seed}",
        source_sha256=mesh_sha256(mesh),
        units="m",
        num_points=num_points,
    )
