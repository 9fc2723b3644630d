"""How fast ``catalign library build`` describes models, on one core and on every core, and what
resuming a killed build saves.

Builds a library of ``--count`` procedural chairs (``catalign library procedural``, the shipped
library's kind of entry) with one worker process and with ``--workers`` (default: one per core),
in the same run, so that the ratio holds on a shared machine; then kills a build of the same
chairs after about half of them (SIGKILL, as a crash or an out-of-memory kill would) and runs it
again, timing how long the second run takes and how many entries it reused.

    .venv/bin/python bench/build.py [--count 40] [--workers N] [--out bench/results/build.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _report import load_average, publish

from catalign.library.builder import JOURNAL_NAME

CLI = [str(Path(sys.executable).with_name("catalign")), "library", "procedural"]


def timed_build(out: Path, count: int, workers: int) -> float:
    """Seconds ``catalign library procedural`` takes to build ``count`` chairs in ``out``."""
    started = time.perf_counter()
    subprocess.run(
        [*CLI, "--out", str(out), "--count", str(count), "--workers", str(workers)],
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - started


def killed_half_way(out: Path, count: int, workers: int) -> int:
    """Start a build and SIGKILL it (with its workers) once half its entries are journalled;
    how many entries it had finished."""
    args = [*CLI, "--out", str(out), "--count", str(count), "--workers", str(workers)]
    build = subprocess.Popen(
        args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    journal = out / JOURNAL_NAME
    while build.poll() is None:
        done = len(journal.read_text().splitlines()) - 1 if journal.is_file() else 0
        if done >= count // 2:
            break
        time.sleep(0.05)
    os.killpg(build.pid, signal.SIGKILL)  # the build and its worker processes
    build.wait()
    return len(journal.read_text().splitlines()) - 1 if journal.is_file() else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=Path("bench/results/build.md"))
    args = parser.parse_args()

    root = Path(tempfile.mkdtemp(prefix="bench-build-"))
    try:
        load_before = load_average()
        one = timed_build(root / "one", args.count, 1)
        many = timed_build(root / "many", args.count, args.workers)
        finished = killed_half_way(root / "resumed", args.count, args.workers)
        resumed = timed_build(root / "resumed", args.count, args.workers)
        load_after = load_average()
    finally:
        shutil.rmtree(root, ignore_errors=True)

    rows = [
        ("1 worker", one, args.count),
        (f"{args.workers} workers", many, args.count),
        (f"{args.workers} workers, resumed after a kill", resumed, args.count - finished),
    ]
    lines = [
        f"# Library build: {args.count} procedural chairs",
        "",
        f"{platform.node()}, {os.cpu_count()} cores, load average {load_before:.1f} before, "
        f"{load_after:.1f} after; each build is a `catalign library procedural` process "
        "(start-up and model loading included).",
        "",
        "| build | seconds | models described | models per second |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, seconds, described in rows:
        lines.append(f"| {name} | {seconds:.1f} | {described} | {args.count / seconds:.2f} |")
    lines += [
        "",
        f"{args.workers} workers: {one / many:.2f}x the rate of 1. The killed build had "
        f"journalled {finished} of {args.count} models; run again, it described only the "
        f"other {args.count - finished} ({resumed / many:.2f}x the time of a whole build).",
        "",
    ]
    publish("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
