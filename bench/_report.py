"""What every benchmark script shares: the machine's load and writing the result table."""

from __future__ import annotations

import os
from pathlib import Path


def load_average() -> float:
    """The 1-minute load average: timings on a shared 2-core machine need it beside them."""
    return os.getloadavg()[0]


def publish(table: str, path: Path) -> None:
    """Print the markdown table and write it to ``path`` (under ``bench/results/``)."""
    print(table)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(table)
