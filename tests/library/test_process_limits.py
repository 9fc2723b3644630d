"""A served library keeps each entry's file open and mapped: loading one raises the process's
open-files limit to match, and says in a sentence when the hard limit is too low."""

from __future__ import annotations

import resource
import subprocess
import sys

import pytest

from catalign.paths import DEFAULT_MODEL_DIR

LIBRARY = DEFAULT_MODEL_DIR / "library"
_LOAD = """
import resource
from catalign.errors import LibraryError
from catalign.library.loaded import load
try:
    library = load({library!r}, None)
except LibraryError as error:
    print("refused:", error)
else:
    print("loaded", len(library), resource.getrlimit(resource.RLIMIT_NOFILE)[0])
"""


def _load_with_limits(soft: int, hard: int) -> str:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))

    done = subprocess.run(
        [sys.executable, "-c", _LOAD.format(library=str(LIBRARY))],
        preexec_fn=limit,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


@pytest.mark.skipif(not (LIBRARY / "catalogue.sqlite").is_file(), reason="no shipped library")
def test_the_open_files_limit_is_raised_or_the_library_refused_in_a_sentence() -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 4096:
        pytest.skip(f"this machine's hard limit on open files is {hard}")
    loaded = _load_with_limits(200, 4096).split()
    assert loaded[0] == "loaded" and int(loaded[2]) > 200  # the soft limit was raised
    refused = _load_with_limits(200, 200)
    assert refused.startswith("refused:") and "ulimit -n" in refused and "split" in refused
