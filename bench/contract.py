"""The contract at volume: schemathesis against one real server until it has answered
``--requests`` requests, with every check and every phase, stateful included.

Starts ``catalign serve`` (``bench/serve.py``'s ``ServerProcess``: shipped weights, 2 worker
processes, a deadline as long as the client's timeout so that a slow registration on a busy
machine is not turned into a 503) on a copy of the default library, with an API key (sent
both as X-API-Key and as a Bearer token, so that no request is refused for a made-up
credential; the ``ignored_auth`` check still sends each operation without). Then runs
``schemathesis run openapi.yaml --checks all`` through its four phases (examples, coverage,
fuzzing, stateful: the stateful phase chains ``POST /models``, ``GET``, ``DELETE`` and the
listing on the ids they return), ``--examples`` per operation and phase, seed after seed
(``--seed``, ``--seed`` + 1, ...) on the same server, until the server's own count of answered
requests (``catalign_http_requests_total`` on ``/metrics``, less this script's reads of it)
reaches ``--requests``. ``bench/contract.toml`` lists, per operation, the answers a
schema-valid request may get beyond schemathesis's defaults, with the reason the schema cannot
rule that request out. The library copy is changed (the stateful phase adds and removes
models, and may empty it); the original never is.

Prints a row per run and writes the markdown report to ``--out`` (default
``bench/results/contract.md``) and the raw rows to ``--rows`` (JSON).

    .venv/bin/python bench/contract.py [--requests 20000] [--examples 1000] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import httpx
from _report import load_average, publish
from prometheus_client.parser import text_string_to_metric_families
from serve import LIBRARY, ROOT, ServerProcess

API_KEY = "contract-key-0123"
CONFIG = Path(__file__).with_name("contract.toml")
PHASES = "examples,coverage,fuzzing,stateful"


def answered(url: str) -> Counter[tuple[str, str, str]]:
    """The server's count of answered requests by (method, route, status)."""
    text = httpx.get(f"{url}/metrics", headers={"X-API-Key": API_KEY}, timeout=60).text
    counts: Counter[tuple[str, str, str]] = Counter()
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name == "catalign_http_requests_total":
                labels = sample.labels
                counts[labels["method"], labels["route"], labels["status"]] += int(sample.value)
    return counts


def schemathesis_run(url: str, seed: int, examples: int, report: Path) -> dict:
    """One ``schemathesis run`` against ``url``; its JSON report."""
    exe = shutil.which("schemathesis", path=str(Path(sys.executable).parent)) or "schemathesis"
    command = [
        *(exe, "--config-file", str(CONFIG), "run", str(ROOT / "openapi.yaml")),
        *("--url", url, "--header", f"X-API-Key: {API_KEY}", "--checks", "all"),
        # The key in both places: else schemathesis makes up an Authorization header, and a
        # wrong key there is refused even beside the right X-API-Key (both are checked).
        *("--header", f"Authorization: Bearer {API_KEY}"),
        *("--phases", PHASES, "--max-examples", str(examples), "--seed", str(seed)),
        *("--continue-on-failure", "--request-timeout", "600", "--workers", "1"),
        *("--report", "json", "--report-json-path", str(report)),
    ]
    # In the scratch folder: schemathesis leaves its cache (.schemathesis/) where it runs.
    finished = subprocess.run(command, capture_output=True, text=True, cwd=report.parent)
    if not report.exists():
        raise RuntimeError(f"schemathesis wrote no report:\n{finished.stdout[-4000:]}")
    if finished.returncode != 0:
        print(finished.stdout[-6000:])  # the failures, with the requests that reproduce them
    return json.loads(report.read_text())


def table(
    rows: list[dict], statuses: Counter[tuple[str, str, str]], args: argparse.Namespace
) -> str:
    total = sum(statuses.values())
    server_errors = sum(n for (_, _, status), n in statuses.items() if status.startswith("5"))
    failures = sum(row["failures"] for row in rows)
    lines = [
        f"Contract at volume ({platform.machine()}, {os.cpu_count()} CPUs): `bench/contract.py "
        f"--requests {args.requests} --examples {args.examples} --seed {args.seed}`; "
        f"schemathesis {rows[0]['version']}, `--checks all`, phases {PHASES}, one `catalign "
        "serve` with 2 worker processes and an API key on a copy of the default library.",
        "",
        "| run | seed | test cases | requests answered | 5xx | contract failures | s | load |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, row in enumerate(rows):
        lines.append(
            f"| {i + 1} | {row['seed']} | {row['test_cases']} | {row['requests']} | "
            f"{row['server_errors']} | {row['failures']} | {row['seconds']:.0f} | "
            f"{row['load']:.1f} |"
        )
    lines += [
        "",
        f"In all: {total} requests answered, {server_errors} with a 5xx, {failures} contract "
        "failures.",
        "",
        "| route | answers by status |",
        "|---|---|",
    ]
    by_route: dict[str, Counter[str]] = {}
    for (_, route, status), n in statuses.items():
        by_route.setdefault(route, Counter())[status] += n
    for route in sorted(by_route):
        shown = ", ".join(f"{status}: {n}" for status, n in sorted(by_route[route].items()))
        lines.append(f"| `{route}` | {shown} |")
    failed = sorted({f"{f['code']} {f['title']}" for row in rows for f in row["failure_kinds"]})
    if failed:
        lines += ["", "Failures found: " + "; ".join(failed) + "."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=20_000, help="answered requests to reach")
    parser.add_argument("--examples", type=int, default=1000, help="per operation and phase")
    parser.add_argument("--seed", type=int, default=0, help="of the first run")
    parser.add_argument("--max-runs", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results/contract.md")
    parser.add_argument(
        "--rows", type=Path, default=Path(__file__).parent / "results/contract.json"
    )
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="catalign-contract-") as scratch:
        library = Path(scratch) / "library"
        shutil.copytree(LIBRARY, library)
        server = ServerProcess(2, 8, "processes", 1, library=library, api_key=API_KEY)
        try:
            server.wait_ready()
            start = answered(server.url)
            reads = 1
            rows: list[dict] = []
            statuses: Counter[tuple[str, str, str]] = Counter()
            while sum(statuses.values()) < args.requests and len(rows) < args.max_runs:
                seed = args.seed + len(rows)
                began = time.monotonic()
                report = schemathesis_run(
                    server.url, seed, args.examples, Path(scratch) / f"{seed}.json"
                )
                seconds = time.monotonic() - began
                now = answered(server.url)
                before = statuses
                statuses = now - start
                statuses["GET", "/metrics", "200"] -= reads  # this script's own reads
                reads += 1
                run = statuses - before
                rows.append(
                    {
                        "seed": seed,
                        "version": report["schemathesis_version"],
                        "test_cases": report["test_cases"]["generated"],
                        "requests": sum(run.values()),
                        "server_errors": sum(n for (_, _, s), n in run.items() if s[0] == "5"),
                        "failures": sum(f["count"] for f in report["failures"]),
                        "failure_kinds": report["failures"],
                        "errors": report["errors"],
                        "phases": report["phases"],
                        "seconds": seconds,
                        "load": load_average(),
                    }
                )
                row = rows[-1]
                print(
                    f"run {len(rows)} seed {seed}: {row['test_cases']} test cases, "
                    f"{row['requests']} requests, {row['server_errors']} 5xx, "
                    f"{row['failures']} failures, {seconds:.0f} s",
                    flush=True,
                )
        finally:
            server.stop()
    publish(table(rows, statuses, args), args.out)
    args.rows.write_text(
        json.dumps(
            {"rows": rows, "statuses": [[*key, n] for key, n in sorted(statuses.items())]},
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
