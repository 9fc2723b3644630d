"""``catalign library redescribe``: new retrieval encoders' descriptors for a built library,
from its own entries, the same as a fresh build with those encoders gives."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.shapes import procedural_shape
from catalign.errors import LibraryMismatchError
from catalign.features.extractor import LearnedExtractor
from catalign.features.retrieval import CARD_FILE, RETRIEVAL_DIR, WEIGHTS_FILE
from catalign.library.loaded import load
from catalign.library.redescribe import redescribe
from catalign.library.store import read_entry, read_manifest
from tests.library.conftest import FakeExtractor

runner = CliRunner()
pytestmark = pytest.mark.slow


def _other_encoders(model_dir: Path, folder: Path) -> Path:
    """A weights folder with the shipped network and retrieval encoders nudged off the shipped
    ones: the same features, other descriptors, another fingerprint."""
    folder.mkdir()
    for name in ("model.safetensors", "model_card.json"):
        (folder / name).symlink_to(model_dir / name)
    shipped = model_dir / RETRIEVAL_DIR
    (folder / RETRIEVAL_DIR).mkdir()
    generator = torch.Generator().manual_seed(0)
    weights = {
        name: tensor + 0.05 * torch.randn(tensor.shape, generator=generator)
        for name, tensor in load_file(str(shipped / WEIGHTS_FILE)).items()
    }
    save_file(weights, str(folder / RETRIEVAL_DIR / WEIGHTS_FILE))
    card = json.loads((shipped / CARD_FILE).read_text())
    written = (folder / RETRIEVAL_DIR / WEIGHTS_FILE).read_bytes()
    card["sha256"] = hashlib.sha256(written).hexdigest()
    (folder / RETRIEVAL_DIR / CARD_FILE).write_text(json.dumps(card))
    return folder


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("cad")
    for seed in (1, 2):
        np.save(folder / f"proc-{seed}.npy", procedural_shape(seed).points.astype(np.float32))
    return folder


def _build(sources: Path, out: Path, *flags: str) -> None:
    built = runner.invoke(app, ["library", "build", str(sources), "--out", str(out), *flags])
    assert built.exit_code == 0, built.output


def test_a_redescribed_library_equals_a_fresh_build_with_the_new_encoders(
    model_dir: Path, sources: Path, tmp_path: Path
) -> None:
    other = _other_encoders(model_dir, tmp_path / "other")
    library, fresh = tmp_path / "library", tmp_path / "fresh"
    _build(sources, library)
    _build(sources, fresh, "--model-dir", str(other))
    before = read_manifest(library)

    done = runner.invoke(app, ["library", "redescribe", str(library), "--model-dir", str(other)])
    assert done.exit_code == 0, done.output
    fingerprint = LearnedExtractor(other).fingerprint
    assert f"2 models now described by {fingerprint}" in done.output
    after, expected = read_manifest(library), read_manifest(fresh)
    assert after.fingerprint == expected.fingerprint == fingerprint != before.fingerprint
    for model_id in after.ids:
        assert after.entries[model_id].descriptor == expected.entries[model_id].descriptor
        assert after.entries[model_id].descriptor != before.entries[model_id].descriptor
        ours = read_entry(library, model_id, after.entries[model_id])
        theirs = read_entry(fresh, model_id, expected.entries[model_id])
        np.testing.assert_array_equal(ours.points, theirs.points)
        np.testing.assert_array_equal(ours.features, theirs.features)
    # only the new files are left, and the library serves under the new fingerprint only
    names = {f"entries/{p.name}" for p in (library / "entries").iterdir()}
    assert names == {record.file for record in after.entries.values()}
    assert len(load(library, fingerprint)) == 2
    with pytest.raises(LibraryMismatchError, match="catalign library redescribe"):
        load(library, before.fingerprint)

    again = runner.invoke(app, ["library", "redescribe", str(library), "--model-dir", str(other)])
    assert again.exit_code == 0 and "already described by" in again.output


def test_a_library_of_other_features_is_refused_untouched(
    model_dir: Path, sources: Path, tmp_path: Path, snapshot
) -> None:
    library = tmp_path / "library"
    _build(sources, library)
    taken = snapshot(library)
    with pytest.raises(LibraryMismatchError, match="rebuild it with `catalign library build"):
        redescribe(library, FakeExtractor())
    assert snapshot(library) == taken
