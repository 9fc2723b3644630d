"""The long fuzz run: every file reader and header check, 10^6 executions per format.

The fuzz tests (``tests/fuzz/``) run a few hundred Hypothesis examples per reader on every CI run;
this script runs the same property (``tests/fuzz/_kit.py``: finite (N, 3) points within the limit,
or the project's own error, with the address space capped so that a lying header cannot allocate
unnoticed) on many more inputs, made by the same mutators from a seeded RNG, so a run is
reproducible from its ``--seed``. Each execution writes its bytes to a temporary file and reads
it the way the service (or the SDK) does. Anything else raised counts as a crash; the first few
inputs of each crash type are kept under ``--crashes`` for a regression test. A reader that
crashes the process itself (a segfault in Open3D) ends the run: the input it died on is in
``--crashes``/last-input. Prints a markdown table and writes it to ``bench/results/fuzz.md``.

    .venv/bin/python bench/fuzz.py [--executions 1000000] [--formats ply pcd ...] [--seed 0]
"""

from __future__ import annotations

import argparse
import platform
import random
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from _report import load_average, publish
from tqdm import tqdm

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the mutators and targets are the fuzz tests' own module
from tests.fuzz._kit import TARGETS, Target, run_target  # noqa: E402

KEPT_PER_CRASH = 5


@dataclass
class Tally:
    """What one format's run saw."""

    executions: int = 0
    seconds: float = 0.0
    points_read: int = 0
    project_errors: int = 0
    crashes: Counter[str] = field(default_factory=Counter)


def keep(crashes: Path, target: Target, kind: str, number: int, data: Any) -> None:
    """Write a crashing input where a regression test can pick it up (bytes, or a message)."""
    folder = crashes / target.name / kind
    folder.mkdir(parents=True, exist_ok=True)
    if isinstance(data, SimpleNamespace):
        (folder / f"{number}.txt").write_text(repr(data))
    else:
        (folder / f"{number}.bin").write_bytes(data)


def fuzz(target: Target, executions: int, seed: int, crashes: Path) -> Tally:
    rng = random.Random(f"{target.name}:{seed}")
    tally = Tally()
    last_input = crashes / target.name / "last-input"
    last_input.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"fuzz-{target.name}-") as folder:
        start = time.perf_counter()
        for _ in tqdm(range(executions), desc=target.name, unit="exec", mininterval=1.0):
            data = target.generate(rng)
            if not isinstance(data, SimpleNamespace):
                last_input.write_bytes(data)
            try:
                read = run_target(target, data, Path(folder))
            except Exception as error:
                kind = type(error).__name__
                tally.crashes[kind] += 1
                if tally.crashes[kind] <= KEPT_PER_CRASH:
                    keep(crashes, target, kind, tally.crashes[kind], data)
            else:
                tally.points_read += read > 0
                tally.project_errors += read == 0
            tally.executions += 1
        tally.seconds = time.perf_counter() - start
    last_input.unlink(missing_ok=True)
    return tally


def table(tallies: dict[str, Tally], seed: int) -> str:
    lines = [
        f"Fuzzing the file readers ({platform.processor() or platform.machine()}, "
        f"load {load_average():.1f}, seed {seed}): `bench/fuzz.py`",
        "",
        "| format | executions | seconds | executions/s | crashes | project errors | points read |",
        "|---|---:|---:|---:|---|---:|---:|",
    ]
    for name, t in tallies.items():
        crashes = ", ".join(f"{k} {v}" for k, v in t.crashes.most_common()) or "0"
        lines.append(
            f"| {name} | {t.executions} | {t.seconds:.1f} | {t.executions / t.seconds:.0f} | "
            f"{crashes} | {t.project_errors} | {t.points_read} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--executions", type=int, default=1_000_000, help="per format")
    parser.add_argument("--formats", nargs="+", choices=sorted(TARGETS), default=list(TARGETS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--crashes", type=Path, default=Path(tempfile.gettempdir()) / "catalign-fuzz"
    )
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results/fuzz.md")
    args = parser.parse_args()
    tallies = {
        name: fuzz(TARGETS[name], args.executions, args.seed, args.crashes) for name in args.formats
    }
    publish(table(tallies, args.seed), args.out)
    if any(t.crashes for t in tallies.values()):
        print(f"crashing inputs kept under {args.crashes}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
