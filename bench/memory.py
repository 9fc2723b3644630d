"""Memory, start-up and latency of ``catalign serve`` with worker processes, by library size.

Every worker process loads the library's catalogue (each model's record and shortlisting
descriptor) and reads an entry's file only when a query shortlists it, keeping the last 128
(``catalign.library.loaded``), so what a process holds grows with the catalogue and its
caches, not with the entries' arrays.

For each ``--library`` (default: latency.py's cached procedural library of ``--size`` models,
built when missing), this starts ``catalign serve`` with ``--workers`` worker processes and
times it to ready, sends ``--queries`` different queries (views of procedural chairs outside
the library, ``up`` given) through the SDK one at a time after one to warm up, and reads
``/proc/PID/smaps`` of the server and of each worker: resident memory (RSS) and its
proportional share (PSS: a page shared by n processes counts 1/n in each). The per-model caches
the engine builds for the models a query touches (KD-trees, normals, matching subsets) are
private to each worker and grow with the models queried, up to the engine's ``model_cache``
models: ``--caches`` also measures, in a spawned process per setting, how much resident memory
one engine gains when every model of the library is asked for once, with the default bound and
without one (``model_cache=none``).

    .venv/bin/python bench/memory.py [--library DIR ...] [--size 1000] [--workers 2]
        [--queries 16] [--caches] [--cache .cache/bench-libraries] [--out bench/results/memory.md]
"""

from __future__ import annotations

import argparse
import multiprocessing
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil
from _report import load_average, publish
from serve import MODEL_DIR, REQUEST_TIMEOUT_S, UP, ServerProcess, query_cloud

from catalign.features.extractor import LearnedExtractor
from catalign.library.index import build_procedural
from catalign.library.loaded import load
from catalign.library.store import CATALOGUE_NAME
from catalign.registration.config import EngineConfig
from catalign_client import Client

RESULTS = Path(__file__).parent / "results" / "memory.md"
MIB = 2**20


@dataclass(frozen=True)
class Usage:
    """One process's memory, in bytes."""

    rss: int
    pss: int


@dataclass(frozen=True)
class Served:
    """One library served: its size, the server's start-up, the queries' latencies and each
    process's memory after them."""

    library: Path
    models: int
    disk: int
    median_entry: float
    ready_s: float
    latencies_s: list[float]
    processes: list[tuple[str, Usage]]


def usage(pid: int) -> Usage:
    """Sum the ``Rss`` and ``Pss`` lines of ``/proc/PID/smaps``."""
    totals = {"rss": 0, "pss": 0}
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        field, _, rest = line.partition(" ")
        if field in ("Rss:", "Pss:"):
            totals[field[:-1].lower()] += int(rest.split()[0]) * 1024
    return Usage(**totals)


def measure(library_dir: Path, workers: int, queries: int) -> Served:
    """Serve ``library_dir``, time it to ready, send the queries, read each process's memory."""
    sizes = [p.stat().st_size for p in (library_dir / "entries").iterdir()]
    server = ServerProcess(
        workers, queue=4 * workers, mode="processes", threads_per_worker=1, library=library_dir
    )
    try:
        ready_s = server.wait_ready()
        clouds = [query_cloud(seed=5000 + i) for i in range(queries + 1)]
        latencies = []
        with Client(server.url, timeout=REQUEST_TIMEOUT_S, retries=0) as client:
            client.align(clouds[0], up=UP)  # every worker warmed up at start; this one's caches
            for cloud in clouds[1:]:
                started = time.perf_counter()
                client.align(cloud, up=UP)
                latencies.append(time.perf_counter() - started)
        main = psutil.Process(server.pid)
        # the worker processes, not multiprocessing's resource tracker
        children = [
            c
            for c in main.children(recursive=True)
            if "resource_tracker" not in " ".join(c.cmdline())
        ]
        rows = [("server", usage(main.pid))]
        rows += [(f"worker {i + 1}", usage(c.pid)) for i, c in enumerate(children)]
    finally:
        server.stop()
    return Served(library_dir, len(sizes), sum(sizes), float(np.median(sizes)), ready_s,
                  latencies, rows)  # fmt: skip


def cache_growth(library_dir: Path, model_cache: int | None) -> tuple[int, int]:
    """Resident bytes an engine gains when every model's matching subset and ICP surface is
    asked for once (run in a spawned process: a fresh heap), and the models it keeps."""
    from catalign.registration.engine import Engine

    extractor = LearnedExtractor(MODEL_DIR)
    engine = Engine(
        extractor,
        load(library_dir, extractor.fingerprint),
        config=EngineConfig(model_cache=model_cache),
    )
    before = psutil.Process().memory_info().rss
    for model_id in engine.library.ids:
        engine.searcher.matcher.matchable(model_id)
        engine.refiner.surface(model_id)
    return psutil.Process().memory_info().rss - before, len(engine.refiner._surfaces)


def cache_table(library_dir: Path) -> str:
    lines = [
        "",
        f"One engine on {library_dir.name}, every model asked for once (matching subset, ICP "
        "surface), in a spawned process per setting:",
        "",
        "| model_cache | models kept | resident memory gained MiB |",
        "|---|---|---|",
    ]
    context = multiprocessing.get_context("spawn")
    for capacity in (EngineConfig().model_cache, None):
        with context.Pool(1) as pool:
            gained, kept = pool.apply(cache_growth, (library_dir, capacity))
        name = "none" if capacity is None else f"{capacity} (default)"
        lines.append(f"| {name} | {kept} | {gained / MIB:.0f} |")
    return "\n".join(lines) + "\n"


def table(results: list[Served], args: argparse.Namespace) -> str:
    lines = [
        f"# catalign serve by library size: {args.workers} worker processes, {args.queries} "
        "queries",
        "",
        f"{platform.machine()}, load average {load_average():.1f}. Latency through the SDK, one "
        "query at a time, `up` given; RSS counts a shared page in every process, PSS divides it "
        "among them. Command: `python bench/memory.py "
        + " ".join(f"--library {r.library}" for r in results)
        + f" --workers {args.workers} --queries {args.queries}"
        + (" --caches" if args.caches else "")
        + "`.",
        "",
        "| library | models | entry files | median entry | ready s | median latency s "
        "| p95 latency s | process | RSS MiB | PSS MiB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for served in results:
        total = Usage(*(sum(getattr(u, f) for _, u in served.processes) for f in ("rss", "pss")))
        head = (
            f"| {served.library.name} | {served.models:,} | {served.disk / 2**30:.2f} GiB "
            f"| {served.median_entry / 1024:.0f} KiB | {served.ready_s:.1f} "
            f"| {np.median(served.latencies_s):.3f} | {np.percentile(served.latencies_s, 95):.3f}"
        )
        for name, u in [*served.processes, ("**all**", total)]:
            lines.append(f"{head} | {name} | {u.rss / MIB:.0f} | {u.pss / MIB:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--library", type=Path, action="append", default=[])
    parser.add_argument("--size", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--queries", type=int, default=16)
    parser.add_argument("--caches", action="store_true", help="Also measure the model caches.")
    parser.add_argument("--cache", type=Path, default=Path(".cache/bench-libraries"))
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    fingerprint = LearnedExtractor(MODEL_DIR).fingerprint
    libraries = args.library
    if not libraries:
        folder = args.cache / f"{fingerprint[:12]}-{args.size}"
        if not (folder / CATALOGUE_NAME).is_file():
            build_procedural(
                folder, LearnedExtractor(MODEL_DIR), args.size, first_seed=0, overwrite=True
            )
        libraries = [folder]
    results = [measure(library_dir, args.workers, args.queries) for library_dir in libraries]
    text = table(results, args)
    if args.caches:
        text += cache_table(libraries[-1])
    publish(text, args.out)


if __name__ == "__main__":
    main()
