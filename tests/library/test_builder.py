"""Building at scale: a build killed half-way resumes without describing its finished entries
again, a journal of another build is not trusted, and worker processes build what one
process builds."""

from __future__ import annotations

import inspect
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from catalign.library import build, load
from catalign.library.builder import JOURNAL_NAME
from catalign.paths import DEFAULT_MODEL_DIR

_BUILDER = """
import sys
from collections import namedtuple

import numpy as np

from catalign.geometry.sampling import voxel_downsample
from catalign.library import build

Described = namedtuple("Described", "keypoints features")  # torch-free stand-in


{extractor}

build([sys.argv[2]], sys.argv[1], FakeExtractor(), progress=False)
"""


def _sources(folder: Path, files, count: int) -> Path:
    folder.mkdir()
    for i in range(count):
        np.save(folder / f"m{i:03d}.npy", files.random_cloud(200 + i, count=20_000))
    return folder


def _journal_lines(library: Path) -> int:
    journal = library / JOURNAL_NAME
    return len(journal.read_text().splitlines()) if journal.is_file() else 0


def test_a_killed_build_resumes_where_it_stopped(files, tmp_path, extractor, caplog) -> None:
    sources = _sources(tmp_path / "many", files, 60)
    library = tmp_path / "library"
    script = _BUILDER.format(extractor=textwrap.dedent(inspect.getsource(type(extractor))))
    builder = subprocess.Popen(
        [sys.executable, "-c", script, str(library), str(sources)], stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 60
        while _journal_lines(library) < 4 and time.monotonic() < deadline:
            assert builder.poll() is None, builder.stderr.read()
            time.sleep(0.01)
    finally:
        os.kill(builder.pid, signal.SIGKILL)
        builder.wait()
    finished = _journal_lines(library) - 1  # less the header
    assert 3 <= finished < 60, "the build was not killed half-way"

    with caplog.at_level(logging.INFO, logger="catalign.library.builder"):
        manifest = build([sources], library, extractor, progress=False)
    resumed = [r.getMessage() for r in caplog.records if "resuming" in r.getMessage()]
    assert resumed and int(resumed[0].split()[1]) >= finished - 1  # a torn last line redone
    assert not (library / JOURNAL_NAME).exists()
    fresh = build([sources], tmp_path / "fresh", extractor, progress=False)
    assert manifest.entries == fresh.entries  # same records, files and checksums
    assert load(library, extractor.fingerprint).ids == [f"m{i:03d}" for i in range(60)]


def test_a_journal_of_another_build_or_a_changed_source_is_not_trusted(
    files, tmp_path, extractor, caplog
) -> None:
    sources = _sources(tmp_path / "few", files, 3)
    library = tmp_path / "library"

    def interrupted(category: str) -> None:
        """A build of ``category`` that stops at its second entry (an unreadable file)."""
        good = (sources / "m001.npy").read_bytes()
        (sources / "m001.npy").write_bytes(b"not a numpy file")
        with pytest.raises(Exception, match="m001"):
            build([sources], library, extractor, category=category, overwrite=True, progress=False)
        (sources / "m001.npy").write_bytes(good)
        assert _journal_lines(library) == 2  # the header and m000

    interrupted("table")
    with caplog.at_level(logging.INFO, logger="catalign.library.builder"):
        manifest = build([sources], library, extractor, category="bench", progress=False)
    assert "of another build" in caplog.text and "resuming" not in caplog.text
    assert {r.category for r in manifest.entries.values()} == {"bench"}

    interrupted("bench")
    caplog.clear()
    np.save(sources / "m000.npy", files.random_cloud(7, count=20_000))  # changed meanwhile
    with caplog.at_level(logging.INFO, logger="catalign.library.builder"):
        manifest = build(
            [sources], library, extractor, category="bench", overwrite=True, progress=False
        )
    assert "resuming" not in caplog.text
    fresh = build([sources], tmp_path / "fresh", extractor, category="bench", progress=False)
    assert manifest.entries == fresh.entries


@pytest.mark.slow
def test_worker_processes_build_what_one_process_builds(
    files, tmp_path, monkeypatch, caplog
) -> None:
    if not (DEFAULT_MODEL_DIR / "model.safetensors").is_file():
        pytest.skip("model_store/ has no trained weights")
    from catalign.features.extractor import LearnedExtractor

    extractor = LearnedExtractor(threads=1)
    sources = tmp_path / "boxes"
    for i, extents in enumerate([(0.5, 0.9, 0.5), (0.6, 0.8, 0.4), (1.2, 0.7, 0.8)]):
        files.box(f"../boxes/b{i}.ply", extents)
    one = build([sources], tmp_path / "one", extractor, progress=False, workers=1)
    monkeypatch.setattr("catalign.library.builder.JOBS_PER_WORKER", 1)  # processes for 3
    with caplog.at_level(logging.INFO, logger="catalign.library.builder"):
        two = build([sources], tmp_path / "two", extractor, progress=False, workers=2)
    assert "2 worker(s)" in caplog.text
    assert one.ids == two.ids == ["b0", "b1", "b2"]
    for model_id in one.ids:
        a = load(tmp_path / "one", extractor.fingerprint)[model_id]
        b = load(tmp_path / "two", extractor.fingerprint)[model_id]
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_allclose(a.features, b.features, atol=1e-5)
        assert one.entries[model_id].symmetry == two.entries[model_id].symmetry
