"""Memory of ``catalign serve`` with worker processes: is the library shared between them?

Every worker process loads the library (and the server process too, for listings and uploads).
Entry files are read as views of a read-only memory map (``catalign.library.npz``), so the
processes read one copy of the library's pages from the page cache instead of holding one copy
each; arrays of files written before their members were aligned are copied instead.

For each ``--library`` (default: latency.py's cached procedural library of ``--size`` models,
built when missing), this starts ``catalign serve`` with ``--workers`` worker processes, sends
``--queries`` different queries (views of procedural chairs outside the library, ``up`` given)
through the SDK, two at a time so every worker runs, and reads ``/proc/PID/smaps`` of the server
and of each worker: resident memory (RSS), its proportional share (PSS: a page shared by n
processes counts 1/n in each), and the part of both in maps of the library's entry files. RSS
counts a shared page in every process that reads it (what private copies would cost), PSS once
over all. The per-model caches the engine builds for the models a query touches (KD-trees,
normals, matching subsets) are private to each worker and grow with the models queried, up to
the engine's ``model_cache`` models: ``--caches`` also measures, in a spawned process per
setting, how much resident memory one engine gains when every model of the library is asked
for once, with the default bound and without one (``model_cache=none``).

    .venv/bin/python bench/memory.py [--library DIR ...] [--size 1000] [--workers 2]
        [--queries 16] [--caches] [--cache .cache/bench-libraries] [--out bench/results/memory.md]
"""

from __future__ import annotations

import argparse
import multiprocessing
import platform
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

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
    """One process's memory, in bytes: all of it and the part in maps of library files."""

    rss: int
    pss: int
    library_rss: int
    library_pss: int


def usage(pid: int, entries: Path) -> Usage:
    """Sum the ``Rss`` and ``Pss`` lines of ``/proc/PID/smaps``, in all and over the maps of
    files under ``entries``."""
    totals = {"rss": 0, "pss": 0, "library_rss": 0, "library_pss": 0}
    in_library = False
    prefix = str(entries.resolve()) + "/"
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        field, _, rest = line.partition(" ")
        if not field.endswith(":"):  # a map's header: address, perms, offset, dev, inode, path
            in_library = line.split(maxsplit=5)[-1].startswith(prefix)
        elif field in ("Rss:", "Pss:"):
            size = int(rest.split()[0]) * 1024
            key = field[:-1].lower()
            totals[key] += size
            if in_library:
                totals[f"library_{key}"] += size
    return Usage(**totals)


def viewed_share(library_dir: Path, fingerprint: str) -> tuple[float, int]:
    """The share of the library's array bytes that a load views in place (not copied), and the
    entry files' size on disk."""
    library = load(library_dir, fingerprint)
    viewed = total = 0
    for entry in library:
        for array in (entry.points, entry.keypoints, entry.features, entry.grid.values):
            total += array.nbytes
            viewed += 0 if array.flags.owndata else array.nbytes
    disk = sum(p.stat().st_size for p in (library_dir / "entries").iterdir())
    return viewed / total, disk


def measure(library_dir: Path, workers: int, queries: int) -> list[tuple[str, Usage]]:
    """Serve ``library_dir``, send the queries, return each process's usage."""
    server = ServerProcess(
        workers, queue=4 * workers, mode="processes", threads_per_worker=1, library=library_dir
    )
    try:
        server.wait_ready()
        clouds = [query_cloud(seed=5000 + i) for i in range(queries)]
        with (
            Client(server.url, timeout=REQUEST_TIMEOUT_S, retries=0) as client,
            ThreadPoolExecutor(max_workers=workers) as pool,
        ):
            list(pool.map(lambda c: client.align(c, up=UP), clouds))
        main = psutil.Process(server.pid)
        # the worker processes, not multiprocessing's resource tracker
        children = [
            c
            for c in main.children(recursive=True)
            if "resource_tracker" not in " ".join(c.cmdline())
        ]
        entries = library_dir / "entries"
        rows = [("server", usage(main.pid, entries))]
        rows += [(f"worker {i + 1}", usage(c.pid, entries)) for i, c in enumerate(children)]
        return rows
    finally:
        server.stop()


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


def table(
    results: list[tuple[Path, float, int, list[tuple[str, Usage]]]], args: argparse.Namespace
) -> str:
    lines = [
        f"# catalign serve memory: {args.workers} worker processes, {args.queries} queries",
        "",
        f"{platform.machine()}, load average {load_average():.1f}. RSS counts a shared page in "
        "every process, PSS divides it among them; *library* is the part in maps of the "
        "library's entry files. Command: `python bench/memory.py "
        + " ".join(f"--library {p}" for p, *_ in results)
        + f" --workers {args.workers} --queries {args.queries}"
        + (" --caches" if args.caches else "")
        + "`.",
        "",
        "| library | arrays viewed in place | entry files | process | RSS MiB | PSS MiB "
        "| library RSS MiB | library PSS MiB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for path, share, disk, rows in results:
        total = Usage(*(sum(getattr(u, f) for _, u in rows) for f in Usage.__dataclass_fields__))
        for name, u in [*rows, ("**all**", total)]:
            lines.append(
                f"| {path.name} | {share:.0%} | {disk / MIB:.0f} MiB | {name} | {u.rss / MIB:.0f} "
                f"| {u.pss / MIB:.0f} | {u.library_rss / MIB:.0f} | {u.library_pss / MIB:.0f} |"
            )
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
    results = []
    for library_dir in libraries:
        share, disk = viewed_share(library_dir, fingerprint)
        results.append((library_dir, share, disk, measure(library_dir, args.workers, args.queries)))
    text = table(results, args)
    if args.caches:
        text += cache_table(libraries[-1])
    publish(text, args.out)


if __name__ == "__main__":
    main()
