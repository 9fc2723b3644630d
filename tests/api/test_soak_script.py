"""``bench/soak.py`` on a tiny count: it runs a real server, changes the library, writes rows.

The full soak (20,000 registrations) takes half an hour on 2 cores; this runs 40 small ones on one
worker process with 2 library changes, so that the script itself stays working.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests._bench import run_bench

pytestmark = pytest.mark.slow


def test_a_tiny_soak_writes_its_rows_report_and_figure(model_dir: Path, tmp_path: Path) -> None:
    out, rows, figure = tmp_path / "soak.md", tmp_path / "soak.json", tmp_path / "soak.png"
    done = run_bench(
        "soak.py",
        *("--requests", "40", "--block", "20", "--change-every", "20"),
        *("--points", "2000", "--views", "2", "--workers", "1"),
        *("--out", str(out), "--rows", str(rows), "--figure", str(figure)),
        timeout=180,
    )
    assert done.returncode == 0, done.stderr[-3000:]

    written = json.loads(rows.read_text())
    assert [row["requests"] for row in written["rows"]] == [20, 40]
    for row in written["rows"]:
        assert row["errors"] == 0
        assert row["rss_mib"] > row["server_rss_mib"] > 0  # the worker process is counted
        assert row["processes"] >= 2 and row["fds"] > 0 and row["p99_ms"] >= row["p50_ms"] > 0
    changes = written["changes"]
    assert [c["model_id"] for c in changes] == ["soak-0000", "soak-0001"]
    assert all("error" not in c for c in changes)
    assert changes[1]["models"] == 61  # the default library's 60, one soak chair at a time
    assert written["verdict"]["errors"] == 0
    assert "| 40 |" in out.read_text()
    assert figure.read_bytes().startswith(b"\x89PNG")
