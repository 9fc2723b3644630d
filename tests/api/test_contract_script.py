"""``bench/contract.py`` on a tiny volume: a real server, one schemathesis run of every phase.

The full run (20,000 requests) takes a quarter of an hour on 2 cores; this asks for a few
examples per operation so that the script itself stays working.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests._bench import run_bench

pytestmark = pytest.mark.slow


def test_a_tiny_contract_run_counts_the_servers_answers(model_dir: Path, tmp_path: Path) -> None:
    out, rows = tmp_path / "contract.md", tmp_path / "contract.json"
    done = run_bench(
        "contract.py",
        *("--requests", "50", "--examples", "2", "--max-runs", "1"),
        *("--out", str(out), "--rows", str(rows)),
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]

    written = json.loads(rows.read_text())
    (row,) = written["rows"]
    assert set(row["phases"]) == {"examples", "coverage", "fuzzing", "stateful"}
    assert row["test_cases"] > 0 and row["requests"] >= 50
    assert row["server_errors"] == 0, out.read_text()
    routes = {route for _, route, _, _ in written["statuses"]}
    assert {"/register", "/models", "/models/{model_id:path}"} <= routes
    assert f"In all: {row['requests']} requests answered" in out.read_text()
