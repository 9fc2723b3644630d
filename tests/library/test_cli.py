"""``catalign library ...`` as a user runs it: real files, the shipped weights, exit codes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.shapes import procedural_shape
from catalign.library.store import FORMAT_VERSION

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

    removed = runner.invoke(app, ["library", "remove", str(library), "alpha"])
    assert removed.exit_code == 0 and "1 models" in removed.output


def test_errors_are_one_sentence_and_exit_code_2(tmp_path: Path) -> None:
    missing = runner.invoke(app, ["library", "info", str(tmp_path / "nothing")])
    assert missing.exit_code == 2
    assert "no library" in missing.stderr and "Traceback" not in missing.output

    library = tmp_path / "lib"
    runner.invoke(app, ["library", "procedural", "--out", str(library), "--count", "1"])
    unknown = runner.invoke(app, ["library", "remove", str(library), "ghost"])
    assert unknown.exit_code == 2 and "ghost" in unknown.stderr
