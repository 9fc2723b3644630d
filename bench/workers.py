"""Worker threads or worker processes: how much throughput do the server's threads lose to the GIL?

``catalign serve --workers 2`` runs registrations on 2 threads sharing one ``Engine``, each with 1
torch/BLAS thread (``limit_threads(1, 2)``). torch, numpy and Open3D release the GIL in their
kernels, but the engine's Python between them holds it. On ``--queries`` of latency.py's query
views (20k points, outside its cached 50-model library, up given), ``--requests`` requests a run,
pulled by the workers from one queue, go to: 1 thread with ``--workers`` torch threads (the
baseline: one request at a time on every core); 1 thread with 1 torch thread (a request alone on
a core); ``--workers`` threads with 1 torch thread each (the server); ``--workers`` spawned
processes with 1 torch thread each and their own engine (no shared GIL; loaded and warmed up once,
untimed, idle while the others run). Runs interleave in ``--rounds`` rounds so that the machine's
load hits all alike; thread runs get fresh threads, set up as the server's and warmed up.

Reported: median req/s over rounds and its ratio to the baseline, median request latency, the
share of request time its thread was on a CPU (``thread_time`` / wall: waiting for the GIL or a
core lowers it), resident memory after the last round. Beside a request alone, processes slow a
request only by sharing cores, caches and memory bandwidth; threads share those and the GIL, so
1 - latency(processes) / latency(threads) estimates the share of a threaded request lost to the
GIL. Prints a markdown table and writes it to ``bench/results/workers.md``.

    .venv/bin/python bench/workers.py [--requests 32] [--rounds 3] [--queries 8] [--workers 2]
        [--model-dir DIR] [--cache DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import multiprocessing
import platform
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
from _report import load_average, publish
from latency import query_cloud

from catalign.data.views import WORLD_UP
from catalign.features.extractor import LearnedExtractor
from catalign.library.index import build_procedural
from catalign.library.loaded import load
from catalign.library.store import CATALOGUE_NAME
from catalign.registration.engine import Engine
from catalign.threads import cores, limit_malloc_arenas, limit_threads

RESULTS = Path(__file__).parent / "results" / "workers.md"
LIBRARY_SIZE = 50
FIRST_QUERY_SEED = 5000  # latency.py's query: no library chair has a seed this high
TIMEOUT_S = 600  # a worker process that answers nothing for this long has died


Run = tuple[float, list[tuple[float, float]]]  # req/s, and each request's wall and on-CPU s


def engine_for(model_dir: Path | None, cache: Path) -> Engine:
    """An engine on latency.py's 50-model procedural library, built and cached when missing."""
    extractor = LearnedExtractor(model_dir)
    folder = cache / f"{extractor.fingerprint[:12]}-{LIBRARY_SIZE}"
    if not (folder / CATALOGUE_NAME).is_file():
        build_procedural(folder, extractor, LIBRARY_SIZE, first_seed=0, overwrite=True)
    return Engine(extractor, load(folder, extractor.fingerprint))


def request(engine: Engine, points: np.ndarray) -> tuple[float, float]:
    """Wall and on-CPU seconds of one registration on the calling thread."""
    wall, cpu = time.perf_counter(), time.thread_time()
    engine.register(points, up=WORLD_UP, seed=0)
    return time.perf_counter() - wall, time.thread_time() - cpu


def rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` in MiB (``VmRSS`` of /proc/<pid>/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run_threads(
    engine: Engine, queries: list[np.ndarray], workers: int, threads: int, requests: int
) -> Run:
    """``requests`` registrations on ``workers`` fresh threads sharing ``engine``, each set up as
    the server sets up its workers; timed once every thread has served a warm-up request (the
    barrier keeps one thread from taking both)."""
    barrier = threading.Barrier(workers, timeout=TIMEOUT_S)

    def warm_up() -> None:
        request(engine, queries[0])
        barrier.wait()

    setup = partial(limit_threads, threads, workers * threads)
    with ThreadPoolExecutor(workers, initializer=setup) as pool:
        for warming in [pool.submit(warm_up) for _ in range(workers)]:
            warming.result()
        started = time.perf_counter()
        jobs = [pool.submit(request, engine, queries[i % len(queries)]) for i in range(requests)]
        done = [job.result() for job in jobs]
        elapsed = time.perf_counter() - started
    return requests / elapsed, done


def serve(model_dir: Path | None, cache: Path, seeds: list[int], tasks, answers) -> None:
    """A worker process: its own engine and queries on 1 thread; after one warm-up request it
    says it is ready, then registers each query index it takes from ``tasks`` until None."""
    limit_malloc_arenas(2)  # as `catalign serve` does
    limit_threads(1, 1)
    engine = engine_for(model_dir, cache)
    queries = [query_cloud(seed) for seed in seeds]
    request(engine, queries[0])
    answers.put(None)
    while (index := tasks.get()) is not None:
        answers.put(request(engine, queries[index]))


class Processes:
    """``count`` spawned worker processes pulling requests from one queue, loaded and warmed up
    before the first run so that no run times their start."""

    def __init__(self, count: int, model_dir: Path | None, cache: Path, seeds: list[int]) -> None:
        context = multiprocessing.get_context("spawn")
        self.tasks, self.answers = context.Queue(), context.Queue()
        self.workers = [
            context.Process(
                target=serve, args=(model_dir, cache, seeds, self.tasks, self.answers), daemon=True
            )
            for _ in range(count)
        ]
        for worker in self.workers:
            worker.start()
        for _ in self.workers:
            self.answers.get(timeout=TIMEOUT_S)

    def run(self, queries: int, requests: int) -> Run:
        started = time.perf_counter()
        for i in range(requests):
            self.tasks.put(i % queries)
        done = [self.answers.get(timeout=TIMEOUT_S) for _ in range(requests)]
        elapsed = time.perf_counter() - started
        return requests / elapsed, done

    def rss_mb(self) -> float:
        return sum(rss_mb(worker.pid) for worker in self.workers)

    def close(self) -> None:
        for _ in self.workers:
            self.tasks.put(None)
        for worker in self.workers:
            worker.join(timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=32, help="timed requests per run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--queries", type=int, default=8, help="distinct query clouds")
    parser.add_argument("--workers", type=int, default=2, help="threads or processes")
    parser.add_argument("--cache", type=Path, default=Path(".cache/bench-libraries"))
    parser.add_argument("--model-dir", type=Path, default=None, help="weights (model_store/)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_malloc_arenas(2)  # as `catalign serve` does, before any worker thread starts

    n = args.workers
    seeds = list(range(FIRST_QUERY_SEED, FIRST_QUERY_SEED + args.queries))
    engine = engine_for(args.model_dir, args.cache)
    queries = [query_cloud(seed) for seed in seeds]
    processes = Processes(n, args.model_dir, args.cache, seeds)
    threaded, spawned, alone = (
        f"{n} threads (`serve --workers {n}`)",
        f"{n} processes",
        "1 thread (alone)",
    )
    configs = {  # name: (torch threads per worker, one run of it)
        "1 thread (baseline)": (n, partial(run_threads, engine, queries, 1, n)),
        alone: (1, partial(run_threads, engine, queries, 1, 1)),
        threaded: (1, partial(run_threads, engine, queries, n, 1)),
        spawned: (1, partial(processes.run, len(queries))),
    }
    runs: dict[str, list[Run]] = {name: [] for name in configs}
    try:
        for _ in range(args.rounds):
            for name, (_, run) in configs.items():
                runs[name].append(run(args.requests))
        own = rss_mb(multiprocessing.current_process().pid)
        memory = {**dict.fromkeys(configs, own), spawned: processes.rss_mb()}
    finally:
        processes.close()

    rate = {name: float(np.median([r for r, _ in rs])) for name, rs in runs.items()}
    times = {name: np.array([t for _, done in rs for t in done]) for name, rs in runs.items()}
    latency = {name: float(np.median(t[:, 0])) for name, t in times.items()}
    on_cpu = {name: t[:, 1].sum() / t[:, 0].sum() for name, t in times.items()}
    ratio = {name: rate[name] / rate["1 thread (baseline)"] for name in rate}
    lines = [
        f"# Worker threads or processes ({n} workers, 20k-point queries)",
        "",
        f"{platform.machine()}, {cores()} cores, weights {engine.extractor.fingerprint[:12]}, "
        f"{LIBRARY_SIZE}-model procedural library, {len(queries)} queries with up, "
        f"{args.requests} requests per run after warm-up, median of {args.rounds} interleaved "
        f"rounds; load average {load_average():.2f}.",
        "",
        "| configuration | torch threads per worker | req/s | vs baseline | median ms/request "
        "| on CPU | RSS MiB |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, (threads, _) in configs.items():
        lines.append(
            f"| {name} | {threads} | {rate[name]:.2f} | {ratio[name]:.2f}x "
            f"| {latency[name] * 1e3:.0f} | {on_cpu[name]:.0%} | {memory[name]:.0f} |"
        )
    lines += [
        "",
        "Beside a request alone on a core, a request took "
        f"{latency[threaded] / latency[alone]:.2f}x as long on {n} threads and "
        f"{latency[spawned] / latency[alone]:.2f}x on {n} processes; "
        "share of a threaded request lost to the GIL, 1 - processes / threads: "
        f"{1 - latency[spawned] / latency[threaded]:.0%}. RSS: this process for the thread rows "
        "(it ran them all), the sum of the worker processes for the last.",
    ]
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
