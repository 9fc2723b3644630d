"""``catalign library ...`` as a user runs it: real files, the shipped weights, exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.shapes import procedural_shape
from catalign.library.store import FORMAT_VERSION, manifest_stamp
from tests.library.conftest import (
    as_earlier_layout,
    as_format_2,
    stored,
    without_outlines,
    write_format_2,
)

runner = CliRunner()


def test_build_list_info_add_remove(tmp_path: Path) -> None:
    sources = tmp_path / "cad"
    sources.mkdir()
    np.save(sources / "alpha.npy", procedural_shape(1).points.astype(np.float32))
    library = tmp_path / "lib"

    built = runner.invoke(app, ["library", "build", str(sources), "--out", str(library)])
    assert built.exit_code == 0, built.output
    assert "1 models" in built.output

    np.save(tmp_path / "beta.npy", procedural_shape(2).points.astype(np.float32))
    added = runner.invoke(app, ["library", "add", str(library), str(tmp_path / "beta.npy")])
    assert added.exit_code == 0, added.output
    listed = runner.invoke(app, ["library", "list", str(library)])
    assert listed.output.split() == ["alpha", "beta"]

    info = runner.invoke(app, ["library", "info", str(library)])
    assert "models: 2" in info.output and f"format: {FORMAT_VERSION}" in info.output
    # the build indexed alpha; beta, added since, is scored exactly until the index is written
    assert "shortlist index: 1 of 2 entries; 1 scored exactly until" in info.output

    before = manifest_stamp(library)
    indexed = runner.invoke(app, ["library", "index", str(library)])
    assert indexed.exit_code == 0, indexed.output
    assert manifest_stamp(library) != before  # serving processes load it again, indexed
    assert "shortlist index of 2 models (chair 2)" in indexed.output
    info = runner.invoke(app, ["library", "info", str(library)])
    assert "shortlist index: 2 of 2 entries\n" in info.output

    removed = runner.invoke(app, ["library", "remove", str(library), "alpha"])
    assert removed.exit_code == 0 and "1 models" in removed.output
    info = runner.invoke(app, ["library", "info", str(library)])
    assert "shortlist index: 1 of 1 entries\n" in info.output  # alpha's key is dropped


def test_errors_are_one_sentence_and_exit_code_2(tmp_path: Path) -> None:
    missing = runner.invoke(app, ["library", "info", str(tmp_path / "nothing")])
    assert missing.exit_code == 2
    assert "no library" in missing.stderr and "Traceback" not in missing.output
    not_one = runner.invoke(app, ["library", "index", str(tmp_path / "nothing")])
    assert not_one.exit_code == 2 and "no library" in not_one.stderr

    library = tmp_path / "lib"
    runner.invoke(app, ["library", "procedural", "--out", str(library), "--count", "1"])
    unknown = runner.invoke(app, ["library", "remove", str(library), "ghost"])
    assert unknown.exit_code == 2 and "ghost" in unknown.stderr


def test_configure_sets_the_engine_options_the_library_is_served_with(tmp_path: Path) -> None:
    library = tmp_path / "lib"
    runner.invoke(app, ["library", "procedural", "--out", str(library), "--count", "1"])
    catalogue = library / "catalogue.sqlite"

    def engine() -> dict:
        return json.loads(stored(library, "SELECT engine FROM library")[0][0])

    set_ = runner.invoke(
        app, ["library", "configure", str(library), "--engine", "top_k=5", "--engine", "refine=2"]
    )
    assert set_.exit_code == 0, set_.output
    # stored as a tree, the flat name of earlier releases in its place
    assert engine() == {"top_k": 5, "icp": {"poses": 2}}
    # a group is merged option by option, not replaced
    more = ("--engine", "icp.iterations=20", "--engine", "sweep.models=0")
    added = runner.invoke(app, ["library", "configure", str(library), *more])
    assert added.exit_code == 0, added.output
    options = {"top_k": 5, "icp": {"poses": 2, "iterations": 20}, "sweep": {"models": 0}}
    assert engine() == options
    # a bad option is refused in one sentence and changes nothing
    before = catalogue.read_bytes()
    refusals = (
        ("bogus=1", "unknown engine option 'bogus'"),
        ("top_k=0", "top_k"),
        ("sweep.model=1", "unknown engine option 'sweep.model'"),
    )
    for bad, said in refusals:
        refused = runner.invoke(app, ["library", "configure", str(library), "--engine", bad])
        assert refused.exit_code == 2 and said in refused.stderr, refused.output
    assert catalogue.read_bytes() == before
    # writers keep the options; info shows them; --clear drops them
    np.save(tmp_path / "beta.npy", procedural_shape(2).points.astype(np.float32))
    runner.invoke(app, ["library", "add", str(library), str(tmp_path / "beta.npy")])
    info = runner.invoke(app, ["library", "info", str(library)])
    assert (
        "models: 2" in info.output
        and "engine options: icp.iterations=20 icp.poses=2 sweep.models=0 top_k=5" in info.output
    )
    cleared = runner.invoke(app, ["library", "configure", str(library), "--clear"])
    assert cleared.exit_code == 0 and "(the defaults)" in cleared.output
    assert engine() == {}


def test_a_library_of_the_older_format_is_refused_until_migrated(tmp_path: Path) -> None:
    """Format 2 (manifest.json) is never misread: every command names the conversion, which
    keeps the entry files byte for byte; one written before libraries carried engine options
    converts with none."""
    library = tmp_path / "lib"
    runner.invoke(app, ["library", "procedural", "--out", str(library), "--count", "2"])
    entries = {p.name: p.read_bytes() for p in (library / "entries").iterdir()}
    raw = as_format_2(library)
    del raw["engine"]  # as written before libraries carried options
    write_format_2(library, raw)
    for command in (["info", str(library)], ["remove", str(library), "proc-0000"]):
        refused = runner.invoke(app, ["library", *command])
        assert refused.exit_code == 2, refused.output
        said = " ".join(refused.stderr.split())  # one sentence, however the terminal wraps it
        assert "holds a library of an older format (manifest.json)" in said
        assert f"catalign library migrate {library}" in said and "Traceback" not in said
    migrated = runner.invoke(app, ["library", "migrate", str(library)])
    assert migrated.exit_code == 0
    assert "converted from format 2 to format 4, 2 models" in migrated.output
    assert not (library / "manifest.json").exists()
    assert {p.name: p.read_bytes() for p in (library / "entries").iterdir()} == entries
    again = runner.invoke(app, ["library", "migrate", str(library)])
    assert again.exit_code == 0 and "already of format 4, 2 models" in again.output
    as_earlier_layout(library)  # entry files of the layout before, in a library of format 4
    compacted = runner.invoke(app, ["library", "migrate", str(library)])
    assert compacted.exit_code == 0, compacted.output
    assert "2 entries of the earlier layout rewritten" in compacted.output
    assert "outlines added" not in compacted.output  # rewritten entries get theirs anyway
    without_outlines(library)
    outlined = runner.invoke(app, ["library", "migrate", str(library)])
    assert outlined.exit_code == 0, outlined.output
    assert "already of format 4, 2 outlines added, 2 models" in outlined.output
    assert {p.name: p.read_bytes() for p in (library / "entries").iterdir()} == entries
    info = runner.invoke(app, ["library", "info", str(library)])
    assert info.exit_code == 0 and "engine options: (the defaults)" in info.output
    assert "models: 2" in info.output
