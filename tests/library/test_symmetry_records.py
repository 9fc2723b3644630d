"""Every entry's symmetry about its up is found when it is described, kept in the catalogue and
read back; a library written before symmetries gets them found when it is converted. A new
entry without a category gets the library's default category."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from catalign.geometry.symmetry import YawSymmetry
from catalign.library.index import add, build, info
from catalign.library.legacy import migrate
from catalign.library.loaded import load
from tests.library.conftest import (
    as_format_2,
    random_cloud,
    stored,
    write_cloud,
    write_format_2,
)


def _table_cloud(path: Path, length: float, width: float) -> Path:
    """Surface samples of a table with a ``length`` x ``width`` top on four corner legs."""
    parts = [trimesh.creation.box((length, 0.04, width))]
    parts[0].apply_translation((0.0, 0.72, 0.0))
    for sx in (-1, 1):
        for sz in (-1, 1):
            leg = trimesh.creation.box((0.05, 0.7, 0.05))
            leg.apply_translation((sx * (length / 2 - 0.1), 0.35, sz * (width / 2 - 0.1)))
            parts.append(leg)
    points, _ = trimesh.sample.sample_surface(trimesh.util.concatenate(parts), 4000, seed=0)
    return write_cloud(path, np.asarray(points))


def test_symmetries_are_found_stored_and_read_back(tmp_path: Path, extractor) -> None:
    src = tmp_path / "src"
    _table_cloud(src / "table" / "long.npy", 1.4, 0.8)
    _table_cloud(src / "table" / "square.npy", 0.9, 0.9)
    write_cloud(src / "chair" / "lumpy.npy", random_cloud(1) * np.array([1.0, 1.0, 0.3]))
    out = tmp_path / "lib"
    build([src], out, extractor, progress=False)
    orders = dict(stored(out, "SELECT model_id, symmetry FROM entries"))
    assert (orders["long"], orders["square"]) == (2, 4)
    library = load(out, extractor.fingerprint)
    assert library.symmetry("long") == YawSymmetry(2)
    assert library["square"].symmetry == YawSymmetry(4)


def test_a_library_written_before_symmetries_finds_them_when_converted(
    tmp_path: Path, extractor
) -> None:
    out = tmp_path / "lib"
    build([_table_cloud(tmp_path / "long.npy", 1.4, 0.8)], out, extractor, progress=False)
    raw = as_format_2(out)
    del raw["entries"]["long"]["symmetry"]
    write_format_2(out, raw)
    migrate(out)  # the conversion reads every entry, so it finds what was not recorded
    assert info(out).entries["long"].symmetry == 2
    assert load(out, extractor.fingerprint).symmetry("long") == YawSymmetry(2)


def test_an_entry_added_without_a_category_gets_the_librarys(tmp_path: Path, extractor) -> None:
    out = tmp_path / "lib"
    first = write_cloud(tmp_path / "t1.npy", random_cloud(1))
    manifest = build([first], out, extractor, category="table", progress=False)
    assert manifest.category == "table"
    assert stored(out, "SELECT category FROM library") == [("table",)]
    src = tmp_path / "more"
    write_cloud(src / "t2.npy", random_cloud(2))
    write_cloud(src / "bench" / "b1.npy", random_cloud(3))
    add(out, [src], extractor, progress=False)
    added = info(out)
    assert added.categories() == {"bench": 1, "table": 2}  # the sub-folder still names its own
    assert added.category == "table"
