"""A served library holds no entry file open: a process whose open-files limit is below the
library's size loads it and reads every entry (each file is read whole and closed)."""

from __future__ import annotations

import resource
import subprocess
import sys

import pytest

from catalign.paths import DEFAULT_MODEL_DIR

LIBRARY = DEFAULT_MODEL_DIR / "library"
_LOAD = """
from catalign.library.loaded import load
library = load({library!r}, None)
library.verify()  # every entry read and checked
print(len(library), sum(len(entry.points) > 0 for entry in library))
"""
SOFT_LIMIT = 40  # files; the shipped library holds 60 entries


@pytest.mark.skipif(not (LIBRARY / "catalogue.sqlite").is_file(), reason="no shipped library")
def test_a_library_larger_than_the_open_files_limit_is_served() -> None:
    def limit() -> None:
        _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (SOFT_LIMIT, hard))

    done = subprocess.run(
        [sys.executable, "-c", _LOAD.format(library=str(LIBRARY))],
        preexec_fn=limit,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    count, read = map(int, done.stdout.split())
    assert count == read and count > SOFT_LIMIT
