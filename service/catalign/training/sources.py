"""The shapes a training command learns from: a user's CAD folder, or the shared chairs and
tables (by category)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from catalign.errors import ConfigError
from catalign.training.loop import ShapeSource


def one_category(
    category: str,
    data: Path | None,
    units: str,
    chairs_dir: Path | None,
    tables_dir: Path | None,
) -> ShapeSource:
    """The shapes of ``category`` that ``train-orientation`` and ``calibrate`` learn from: the
    shared chairs or tables, or all of a user's folder ``data`` taken as that category."""
    sources = training_sources([category], data, units, chairs_dir, tables_dir)
    return sources[category]


def training_sources(
    category: list[str] | None,
    data: Path | None,
    units: str,
    chairs_dir: Path | None,
    tables_dir: Path | None,
) -> Mapping[str, ShapeSource]:
    """The shapes ``catalign train`` learns from, by category: a user's folder, or else the
    shared chairs and tables."""
    from catalign.data.shapes import shared_shapes
    from catalign.training.cad_folder import cad_folders

    if data is not None:
        if category and len(category) > 1:
            raise ConfigError(
                "--data holds one category (--category NAME) or one sub-folder per category "
                f"(no --category); got {len(category)} categories"
            )
        return cad_folders(data, category[0] if category else None, units)
    roots = {"chair": chairs_dir, "table": tables_dir}
    for name in category or ():
        if name not in roots:
            raise ConfigError(
                f"no shared shapes of category {name!r} (there are chair and table); train on "
                "your own CAD files with --data DIR --category NAME"
            )
    return {name: shared_shapes(name, roots[name]) for name in category or ("chair",)}
