"""Query latency of the engine against procedural libraries of growing size, FPFH alongside.

20k-point partial views of procedural chairs that are not in the library (``--queries`` of them:
a query whose heading proposal is confident and whose answer is sure is described at one
heading, others at two, so one view is not typical) are registered against libraries of 10, 50,
200 and 1000 procedural chairs (built once with the shipped weights and cached under
``--cache``), with the engine's defaults: with ``up``, with ``up`` at both proposed headings
always (``orient.heading_mass=none``), with ``up`` and ICP on one thread (``icp.threads=1``: what
the worker's second thread buys), with ``up`` and no sweep (``sweep.models=0``: the
sweep's cost), with and without ``up`` with every exact fit taken as sure
(``decision.sure_fitness=0.9``: the cost of refining swept poses when a fit is exact but not
sure), with ``up`` at every heading (no heading proposals: the baseline of the features stage),
without ``up`` (searched under the confident proposed ups first, ``orient.up_mass``) and
without ``up`` under every proposed up always (``orient.up_mass=none``). The FPFH baseline
(Open3D's recipe, every model tried) runs in the same process on the small libraries, where it
finishes. Prints a markdown table and writes it to
``bench/results/latency.md``.

    .venv/bin/python bench/latency.py [--sizes 10 50 200 1000] [--runs 5] [--queries 8]
        [--top-k 10] [--model-dir DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch
from _report import load_average, publish

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import WORLD_UP, random_object_pose, render_view
from catalign.features.extractor import LearnedExtractor
from catalign.geometry.sampling import subsample
from catalign.library.index import build_procedural
from catalign.library.loaded import load
from catalign.library.store import CATALOGUE_NAME
from catalign.registration.config import EngineConfig
from catalign.registration.engine import STAGES, Engine
from catalign.registration.methods import build_registrar
from catalign.registration.results import LibraryShape
from catalign.threads import limit_threads

RESULTS = Path(__file__).parent / "results" / "latency.md"
# The first query view's seed (its chair's and its camera's); the others follow it.
QUERY_SEED = 5000
# How each row of the table calls the engine: its configuration and the up it is given.
MODES = {
    "learned engine, up": ({}, WORLD_UP),
    "learned engine, up, both proposed headings": ({"orient": {"heading_mass": None}}, WORLD_UP),
    "learned engine, up, ICP on one thread": ({"icp": {"threads": 1}}, WORLD_UP),
    "learned engine, up, no sweep": ({"sweep": {"models": 0}}, WORLD_UP),
    "learned engine, up, every exact fit sure": ({"decision": {"sure_fitness": 0.9}}, WORLD_UP),
    "learned engine, up, every heading": ({"orient": {"heading_proposals": None}}, WORLD_UP),
    "learned engine, no up": ({}, None),
    "learned engine, no up, every proposed up": ({"orient": {"up_mass": None}}, None),
    "learned engine, no up, every exact fit sure": ({"decision": {"sure_fitness": 0.9}}, None),
}


def query_cloud(seed: int = QUERY_SEED, count: int = 20_000) -> np.ndarray:
    """A noisy 640x480 view of a chair outside every library, cut to ``count`` points."""
    rng = np.random.default_rng(seed)
    shape = procedural_shape(seed)
    pose = random_object_pose(rng, "upright", height=shape.height / 2)
    camera = camera_at(pose[:3, 3], 1.6, 25.0, 40.0, width=640, height=480)
    return subsample(render_view(shape, pose, camera, rng), count, rng)


def timed(
    register, queries: list[np.ndarray], runs: int, warm_ups: int
) -> tuple[list[float], list]:
    """Wall milliseconds of each ``register(query)`` over ``runs`` passes through the
    ``queries``, after registering the first ``warm_ups`` of them once (per-model caches,
    allocator, lazy imports), and what each call returned."""
    for query in queries[:warm_ups]:
        register(query)
    times, answers = [], []
    for _ in range(runs):
        for query in queries:
            started = time.perf_counter()
            answers.append(register(query))
            times.append((time.perf_counter() - started) * 1e3)
    return times, answers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 50, 200, 1000])
    parser.add_argument("--fpfh-sizes", type=int, nargs="+", default=[10, 50])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--queries", type=int, default=8, help="distinct query views")
    parser.add_argument("--top-k", type=int, default=EngineConfig().top_k)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=Path(".cache/bench-libraries"))
    parser.add_argument("--model-dir", type=Path, default=None, help="weights (model_store/)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)  # as the server's workers run

    extractor = LearnedExtractor(args.model_dir)
    queries = [query_cloud(seed) for seed in range(QUERY_SEED, QUERY_SEED + args.queries)]
    rows, stages = [], []
    for size in args.sizes:
        folder = args.cache / f"{extractor.fingerprint[:12]}-{size}"
        if not (folder / CATALOGUE_NAME).is_file():
            build_procedural(folder, extractor, size, first_seed=0, overwrite=True)
        library = load(folder, extractor.fingerprint)
        for mode, (options, up) in MODES.items():
            config = EngineConfig(top_k=args.top_k, **options)
            engine = Engine(extractor, library, config=config)
            ms, answers = timed(
                lambda q, e=engine, u=up: e.register(q, up=u, seed=0),
                queries,
                args.runs,
                warm_ups=len(queries),
            )
            rows.append((mode, size, ms))
            medians = {k: np.median([a.timings_ms[k] for a in answers]) for k in STAGES}
            stages.append((mode, size, medians))
        if size in args.fpfh_sizes:
            fpfh = build_registrar("fpfh")
            fpfh.prepare([LibraryShape(e.model_id, e.points) for e in library])
            ms, _ = timed(lambda q, f=fpfh: f.register(q, seed=0), queries, 1, warm_ups=1)
            rows.append(("FPFH baseline", size, ms))

    lines = [
        "# Query latency (20k-point query)",
        "",
        f"{platform.machine()}, {torch.get_num_threads()} torch threads (BLAS 1), "
        f"top_k={args.top_k}, weights {extractor.fingerprint[:12]}, headings={extractor.headings}, "
        f"{args.queries} query views, each timed {args.runs} times after one warm-up "
        f"(FPFH: once, after one query); load average {load_average():.2f}.",
        "",
        "| method | library size | median ms | p95 ms |",
        "|---|---|---|---|",
    ]
    for method, size, ms in rows:
        lines.append(f"| {method} | {size} | {np.median(ms):.0f} | {np.percentile(ms, 95):.0f} |")
    lines += [
        "",
        "Engine stages, median ms of the same runs:",
        "",
        "| method | library size | " + " | ".join(STAGES) + " |",
        "|---|---|" + "---|" * len(STAGES),
    ]
    for mode, size, medians in stages:
        cells = " | ".join(f"{medians[k]:.0f}" for k in STAGES)
        lines.append(f"| {mode} | {size} | {cells} |")
    table = "\n".join(lines) + "\n"
    publish(table, args.out)


if __name__ == "__main__":
    main()
