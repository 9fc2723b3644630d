"""Running a ``bench/`` script from a test, as a user would: its own process, with the
repository's packages on the path and none of the caller's ``CATALIGN_`` settings."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_bench(script: str, *arguments: str, timeout: float) -> subprocess.CompletedProcess[str]:
    """``python bench/<script> <arguments>``, its output captured; the caller checks the code."""
    environment = {k: v for k, v in os.environ.items() if not k.startswith("CATALIGN_")}
    environment["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "service"), str(ROOT / "client"), environment.get("PYTHONPATH", "")]
    )
    command = [sys.executable, str(ROOT / "bench" / script), *arguments]
    return subprocess.run(
        command, env=environment, capture_output=True, text=True, timeout=timeout, check=False
    )
