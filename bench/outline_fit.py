"""What the shortlist's outline fit costs a query: two engines on one library, timed in turn.

One engine re-ranks the shortlist by outlines (the defaults), the other shortlists by the
descriptors alone (``shortlist.fit_candidates`` None); both serve the same loaded library in
one warm process, and each view is registered by both, in alternating order, so that the
page cache, the entries each process keeps and the machine's load weigh on both alike. The
views are those of ``bench/retrieval.py`` (the validation chairs, ``up`` given, the category
sent), registered against a library it built (``--library``, e.g. its 1,158 or 10,158 models).
Prints a markdown table and writes it to ``bench/results/outline_fit.md``.

    .venv/bin/python bench/outline_fit.py --library DIR [--views 30] [--seed 1] [--out FILE]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from time import perf_counter

import numpy as np
from _report import load_average, publish
from retrieval import shared_cases

from catalign.data.views import WORLD_UP
from catalign.features.extractor import LearnedExtractor
from catalign.library.loaded import load
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine
from catalign.threads import limit_threads

RESULTS = Path(__file__).parent / "results" / "outline_fit.md"
WARM_UP = 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--library", type=Path, required=True)
    parser.add_argument("--views", type=int, default=30)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)
    library = load(args.library, None)
    extractor = LearnedExtractor(None)
    engines = {
        "outline fit": Engine(extractor, library),
        "descriptors alone": Engine(
            extractor, library, config=EngineConfig().replaced(shortlist={"fit_candidates": None})
        ),
    }
    _, cases, _, _ = shared_cases(2, args.seed)
    views = cases["chair"][: args.views]
    seconds: dict[str, list[float]] = {name: [] for name in engines}
    for number, case in enumerate(views):
        order = list(engines) if number % 2 else list(reversed(engines))
        for name in order:
            started = perf_counter()
            engines[name].register(case.points, up=WORLD_UP, seed=0, category="chair")
            if number >= WARM_UP:
                seconds[name].append(perf_counter() - started)
    baseline = float(np.median(seconds["descriptors alone"]))
    lines = [
        "# The outline fit's cost",
        "",
        f"{library!r}; {len(views) - WARM_UP} views of the validation chairs (seed {args.seed}, "
        f"after {WARM_UP} to warm up), each registered by both engines in alternating order; "
        f"{args.threads} threads, load average {load_average():.2f}.",
        "",
        "| shortlist | median s | p95 s | ratio of medians |",
        "|---|---:|---:|---:|",
    ]
    for name, times in seconds.items():
        median = float(np.median(times))
        lines.append(
            f"| {name} | {median:.3f} | {np.percentile(times, 95):.3f} | {median / baseline:.2f} |"
        )
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
