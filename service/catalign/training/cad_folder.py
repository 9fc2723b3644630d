"""A user's own CAD folder as training shapes: ``catalign train --data DIR --category NAME``.

The files are those a library is built from (:mod:`catalign.library.sources`): any supported
mesh or point cloud, canonically aligned (+Y up, one front for the category), in ``units``.
A folder holds one category (named by the caller) or one sub-folder per category
(``DIR/bench/*.ply``), as ``catalign library build`` reads it, so that the shapes trained on are
the shapes served. Each file keeps its metric size; the train/validation split is fixed by a
hash of its id, like the shared shapes'.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cached_property
from pathlib import Path

import numpy as np

from catalign.data.shapes import SURFACE_POINTS, Shape, Split, split_of, stable_fraction
from catalign.errors import InvalidInputError
from catalign.geometry.io import MeshData, read_shape
from catalign.geometry.sampling import sample_surface
from catalign.library.sources import SourceFile, collect_sources, unit_factor

# Fewer training shapes than this per category leave no room for a validation split.
MIN_SHAPES = 3


class CadFolder:
    """The shapes of one category found in a user's folder, metric, by model id."""

    def __init__(self, category: str, files: list[SourceFile], units: str = "m") -> None:
        self.category = category
        self.factor = unit_factor(units)
        self._files = {f.model_id: f.path for f in files}
        if len(self._files) < MIN_SHAPES:
            raise InvalidInputError(
                f"category {category!r} has {len(self._files)} shape file(s); training needs at "
                f"least {MIN_SHAPES} (some are kept apart for validation)"
            )

    def ids(self, split: Split | None = None) -> list[str]:
        """Sorted ids, all of them or those of one split (at least one of each)."""
        return sorted(i for i in self._files if split is None or self._split[i] == split)

    def metric(self, shape_id: str) -> Shape:
        """The shape in metres, with uniform surface points (a mesh's) or its own points."""
        data = read_shape(self._files[shape_id])
        if data.mesh is None:
            return Shape(shape_id=shape_id, points=data.points.astype(np.float64) * self.factor)
        mesh = MeshData(vertices=data.mesh.vertices * self.factor, faces=data.mesh.faces)
        rng = np.random.default_rng(int(stable_fraction(shape_id) * 2**32))
        points = sample_surface(mesh.vertices, mesh.faces, SURFACE_POINTS, rng)
        return Shape(shape_id=shape_id, points=points, mesh=mesh)

    @cached_property
    def _split(self) -> dict[str, Split]:
        """The hashed split, moved where needed so that both splits hold a shape."""
        split = {i: split_of(i) for i in self._files}
        for wanted in ("val", "train"):
            if wanted not in split.values():
                ordered = sorted(split, key=lambda i: stable_fraction("split:" + i))
                split[ordered[0]] = wanted  # type: ignore[assignment]
        return split


def cad_folders(data: Path, category: str | None, units: str = "m") -> Mapping[str, CadFolder]:
    """The categories of ``data``: all of it as ``category`` when one is named, else one per
    sub-folder. Files directly in ``data`` need a named category."""
    files = collect_sources([data], category=category, default="")
    loose = [f.path.name for f in files if not f.category]
    if loose:
        raise InvalidInputError(
            f"{data} holds shape files outside a category sub-folder ({', '.join(loose[:3])}"
            f"{', ...' if len(loose) > 3 else ''}); name their category with --category NAME"
        )
    names = sorted({f.category for f in files})
    return {
        name: CadFolder(name, [f for f in files if f.category == name], units) for name in names
    }
