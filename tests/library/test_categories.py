"""Every library entry has a category: given, taken from its sub-folder, or a chair by default;
libraries written before categories keep working once converted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from catalign.cli import app
from catalign.errors import InvalidInputError
from catalign.library.index import add, build, info
from catalign.library.legacy import migrate
from catalign.library.loaded import load
from catalign.library.sources import collect_sources, validate_category
from tests.library.conftest import (
    as_format_2,
    random_cloud,
    stored,
    write_cloud,
    write_format_2,
)

runner = CliRunner()


def _tree(root: Path, files: dict[str, int]) -> Path:
    """Clouds at the relative paths of ``files`` (each with its seed) under ``root``."""
    for relative, seed in files.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        write_cloud(path, random_cloud(seed))
    return root


def test_sub_folders_name_categories_and_a_given_category_wins(tmp_path: Path) -> None:
    src = _tree(tmp_path / "src", {"table/t1.npy": 1, "table/ikea/t2.npy": 2, "loose.npy": 3})
    found = {s.model_id: s.category for s in collect_sources([src])}
    assert found == {"t1": "table", "t2": "table", "loose": "chair"}
    given = {s.model_id: s.category for s in collect_sources([src], category="bench")}
    assert set(given.values()) == {"bench"}
    single = collect_sources([src / "table" / "t1.npy"])
    assert single[0].category == "chair"  # a file named alone: no folder to name it


@pytest.mark.parametrize("bad", ["", "Table", "big table", "1table", "t" * 33, "../x"])
def test_a_bad_category_is_refused_naming_it(bad: str) -> None:
    with pytest.raises(InvalidInputError, match="not a valid category"):
        validate_category(bad)


def test_a_sub_folder_that_cannot_be_a_category_says_so(tmp_path: Path) -> None:
    src = _tree(tmp_path / "src", {"Dining Tables/t1.npy": 1})
    with pytest.raises(InvalidInputError, match=r"Dining Tables.*--category"):
        collect_sources([src])
    assert collect_sources([src], category="table")[0].category == "table"


def test_categories_are_stored_loaded_and_counted(tmp_path: Path, extractor) -> None:
    src = _tree(tmp_path / "src", {"table/t1.npy": 1, "table/t2.npy": 2, "chair/c1.npy": 3})
    out = tmp_path / "lib"
    manifest = build([src], out, extractor, progress=False)
    assert manifest.categories() == {"chair": 1, "table": 2}
    add(
        out,
        [write_cloud(tmp_path / "b1.npy", random_cloud(4))],
        extractor,
        category="bench",
        progress=False,
    )
    library = load(out, extractor.fingerprint)
    assert library.category_counts() == {"bench": 1, "chair": 1, "table": 2}
    assert library["t2"].category == "table" and library["b1"].category == "bench"
    assert library.of_category("table").tolist() == [False, False, True, True]  # sorted ids
    assert library.of_category(None) is None
    with pytest.raises(InvalidInputError, match=r"'sofa'.*bench \(1\), chair \(1\), table \(2\)"):
        library.of_category("sofa")
    assert stored(out, "SELECT category FROM entries WHERE model_id = 't1'") == [("table",)]


def test_a_library_written_before_categories_is_of_chairs_or_its_manifests(
    tmp_path: Path, extractor
) -> None:
    out = tmp_path / "lib"
    build([write_cloud(tmp_path / "a.npy", random_cloud(1))], out, extractor, progress=False)
    raw = as_format_2(out)
    del raw["entries"]["a"]["category"]
    write_format_2(out, raw)
    migrate(out)
    assert load(out, extractor.fingerprint)["a"].category == "chair"
    as_format_2(out)
    raw["category"] = "table"  # an older library may name its one category
    write_format_2(out, raw)
    migrate(out)
    assert info(out).categories() == {"table": 1}
    assert load(out, extractor.fingerprint)["a"].category == "table"


def test_the_cli_builds_adds_and_counts_by_category(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    src = _tree(tmp_path / "src", {"table/t1.npy": 1, "chair/c1.npy": 2})
    for path in src.rglob("*.npy"):  # chair-sized clouds the shipped extractor can describe
        np.save(path, (rng.uniform(-0.3, 0.3, (3000, 3))).astype(np.float32))
    library = tmp_path / "lib"
    built = runner.invoke(app, ["library", "build", str(src), "--out", str(library)])
    assert built.exit_code == 0, built.output
    assert "2 models (chair 1, table 1)" in built.output
    extra = tmp_path / "b1.npy"
    np.save(extra, rng.uniform(-0.3, 0.3, (3000, 3)).astype(np.float32))
    added = runner.invoke(app, ["library", "add", str(library), str(extra), "--category", "bench"])
    assert added.exit_code == 0 and "(bench 1, chair 1, table 1)" in added.output
    shown = runner.invoke(app, ["library", "info", str(library)])
    assert "categories: bench 1, chair 1, table 1" in shown.output
    refused = runner.invoke(
        app, ["library", "add", str(library), str(extra), "--category", "Big Bench"]
    )
    assert refused.exit_code == 2 and "not a valid category" in refused.stderr
    assert "Traceback" not in refused.output
