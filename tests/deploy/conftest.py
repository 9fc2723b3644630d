"""What the replica tests share: the extractor of the weights they serve (``model_dir``, from
tests/conftest.py) and the 3-chair procedural library the API tests use, built once (copy it
before changing it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from catalign.features.extractor import LearnedExtractor
from tests.deploy._replicas import LIBRARY_SEEDS


@pytest.fixture(scope="session")
def extractor(model_dir: Path) -> LearnedExtractor:
    return LearnedExtractor(model_dir, threads=1)


@pytest.fixture(scope="session")
def procedural_library(
    extractor: LearnedExtractor, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """The 3-chair library, built once for the session; tests copy it before changing it."""
    from catalign.library.index import build_procedural

    out = tmp_path_factory.mktemp("deploy") / "library"
    build_procedural(out, extractor, LIBRARY_SEEDS, progress=False)
    return out
