"""Soak: tens of thousands of registrations on one server, library changes interleaved.

Starts one real ``catalign serve`` on free 127.0.0.1 ports (``bench/serve.py``'s
``ServerProcess``: shipped weights ``model_store/``, ``--workers`` worker processes of one
thread each, the server's default queue of 8 and deadline of 10 s) on a copy of ``--library``
(default ``model_store/library``; the copy is changed, the original never). ``--concurrency``
client threads share one ``catalign_client.Client`` (binary encoding, no retries: every failure
counts) and register ``--requests`` partial views in turn: 20k-point views (``--points``) of
procedural chairs, half of them in the default library and half not, each with ``up`` and a
fixed seed, so every pass over the views asks the server for the same work. A further thread
changes the library every ``--change-every`` answered registrations (the first after half as
many) through the SDK: it uploads a procedural chair as a PLY mesh (``Client.add_model``,
``POST /models``) and removes the one it added before (``DELETE /models/{id}``), so the
library's version changes twice and every worker process loads it again on its next request,
while the registrations go on.

Every ``--block`` answered registrations (1,000 by default) a row records, over the server and
every process below it (its worker processes and multiprocessing's resource tracker, from
``/proc``): resident memory (RSS, in all, of the server and of the others), open file
descriptors and threads; the library's entry files on disk; and the end-to-end latency (from
before encoding to the parsed answer) median, p95, p99 and maximum of the block's registrations,
its failures and its rate, and the load average (the machine is shared: a p99 means little when
other work ran). Verdict against three targets: RSS of the last block within 5 % of the first
block's, no more descriptors in the last block than in the first, p99 of the last block within
1.2x of the second's (the first holds the start-up's first-call costs).

Prints a table per block as it goes and a markdown report at the end, written to ``--out``
(default ``bench/results/soak.md``); the raw rows, the library changes and the verdict go to
``--rows`` (JSON, default ``bench/results/soak.json``) and a figure of RSS, descriptors and
p50/p99 per block to ``--figure`` (default ``docs/soak.png``).

    .venv/bin/python bench/soak.py [--requests 20000] [--concurrency 4] [--block 1000]
        [--change-every 500] [--points 20000] [--views 8] [--workers 2] [--library DIR]
        [--out bench/results/soak.md] [--rows bench/results/soak.json] [--figure docs/soak.png]
    .venv/bin/python bench/soak.py --redraw [--rows bench/results/soak.json] [--figure FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx
import numpy as np
import trimesh
from _report import load_average, publish
from serve import KEEPALIVE_S, LIBRARY, UP, ServerProcess, _cpu_model, _process_tree, query_cloud

from catalign.data.shapes import procedural_shape
from catalign.library.store import count_entries
from catalign_client import Client

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "soak.md"
ROWS = Path(__file__).parent / "results" / "soak.json"
FIGURE = ROOT / "docs" / "soak.png"
# Views: chairs of the default library (proc-0000 to proc-0059) and chairs outside it.
VIEW_SEEDS = (0, 5000, 7, 5001, 19, 5002, 33, 5003, 41, 5004, 52, 5005)
UPLOAD_SEEDS = (9000, 9001, 9002, 9003)  # chairs uploaded by the library changes, in turn
DEADLINE_S = 10.0  # the server's default
QUEUE = 8  # the server's default
CLIENT_TIMEOUT_S = 120.0
TARGETS = {"rss": 0.05, "p99": 1.2}  # RSS growth after the first block; p99 last / second
MIB = 2**20
PAGE = os.sysconf("SC_PAGE_SIZE")


@dataclass(frozen=True)
class Row:
    """One block of answered registrations: where it ends, what it measured."""

    requests: int  # answered registrations so far
    seconds: float  # the block's wall time
    rate: float  # its registrations a second
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    errors: int  # the block's failed registrations
    changes: int  # library changes done so far
    rss_mib: float  # the server and every process below it
    server_rss_mib: float
    workers_rss_mib: float
    fds: int
    threads: int
    processes: int
    entry_files: int  # files under the library's entries/
    load: float


@dataclass(frozen=True)
class Usage:
    rss: int
    server_rss: int
    fds: int
    threads: int
    processes: int


def usage(pid: int) -> Usage:
    """Resident memory, descriptors and threads of ``pid`` and every process below it, from
    ``/proc`` (a process that exits meanwhile is left out)."""
    rss = server_rss = fds = threads = processes = 0
    for member in _process_tree(pid):
        try:
            resident = int(Path(f"/proc/{member}/statm").read_text().split()[1]) * PAGE
            count = len(os.listdir(f"/proc/{member}/fd"))
            stat = Path(f"/proc/{member}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, ValueError, IndexError):
            continue
        rss += resident
        server_rss += resident if member == pid else 0
        fds += count
        threads += int(stat[17])  # num_threads, field 20
        processes += 1
    return Usage(rss, server_rss, fds, threads, processes)


class Soak:
    """The registrations' bookkeeping, shared by the client threads and the change thread."""

    def __init__(self, args: argparse.Namespace, server: ServerProcess, library: Path) -> None:
        self.total, self.block = args.requests, args.block
        self.server, self.entries = server, library / "entries"
        self.issued = self.answered = self.changes = 0
        self.latencies: list[float] = []
        self.errors = 0
        self.messages: list[str] = []
        self.rows: list[Row] = []
        self.started = time.perf_counter()
        self.condition = threading.Condition()

    def next_request(self) -> int | None:
        with self.condition:
            if self.issued >= self.total:
                return None
            self.issued += 1
            return self.issued - 1

    def done(self, ms: float | None, error: str | None = None) -> None:
        """One registration answered (``ms``) or failed (``error``); a row every block."""
        with self.condition:
            self.answered += 1
            if error is None:
                self.latencies.append(ms)
            else:
                self.errors += 1
                if len(self.messages) < 10:
                    self.messages.append(error)
            if self.answered % self.block == 0 or self.answered == self.total:
                self._row()
            self.condition.notify_all()

    def _row(self) -> None:
        now = time.perf_counter()
        ms = np.array(self.latencies or [np.nan])
        p50, p95, p99, top = (float(np.percentile(ms, q)) for q in (50, 95, 99, 100))
        used = usage(self.server.pid)
        count = len(self.latencies) + self.errors
        row = Row(
            self.answered,
            now - self.started,
            count / (now - self.started),
            p50,
            p95,
            p99,
            top,
            self.errors,
            self.changes,
            used.rss / MIB,
            used.server_rss / MIB,
            (used.rss - used.server_rss) / MIB,
            used.fds,
            used.threads,
            used.processes,
            sum(1 for _ in self.entries.iterdir()),
            load_average(),
        )
        self.rows.append(row)
        print(format_row(row), file=sys.stderr, flush=True)
        self.latencies, self.errors, self.started = [], 0, now

    def wait_for(self, answered: int) -> None:
        with self.condition:
            self.condition.wait_for(lambda: self.answered >= answered)


def register(soak: Soak, client: Client, views: list[np.ndarray]) -> None:
    """A client thread: registrations until the run's count is issued."""
    while (index := soak.next_request()) is not None:
        started = time.perf_counter()
        try:
            client.align(views[index % len(views)], up=UP, seed=0)
        except Exception as error:  # every failure counts, none stops the run
            soak.done(None, f"request {index}: {type(error).__name__}: {error}")
        else:
            soak.done((time.perf_counter() - started) * 1e3)


def change(soak: Soak, url: str, meshes: list[Path], every: int) -> list[dict]:
    """The change thread: every ``every`` answered registrations (the first after half of it,
    so that no change starts as a block ends), add a chair and remove the one added before;
    what each change took."""
    done: list[dict] = []
    with Client(url, timeout=CLIENT_TIMEOUT_S, retries=0) as admin:
        for number, threshold in enumerate(range(max(1, every // 2), soak.total, every)):
            soak.wait_for(threshold)
            record: dict = {"after": soak.answered, "model_id": f"soak-{number:04d}"}
            try:
                started = time.perf_counter()
                admin.add_model(meshes[number % len(meshes)], model_id=record["model_id"])
                record["add_ms"] = (time.perf_counter() - started) * 1e3
                if number > 0:
                    started = time.perf_counter()
                    record["models"] = admin.remove_model(f"soak-{number - 1:04d}")
                    record["remove_ms"] = (time.perf_counter() - started) * 1e3
            except Exception as error:  # recorded; the soak goes on
                record["error"] = f"{type(error).__name__}: {error}"
            done.append(record)
            with soak.condition:
                soak.changes += 1
    return done


def upload_meshes(folder: Path) -> list[Path]:
    """The chairs the changes upload, as PLY meshes (as a CAD library would hold them)."""
    paths = []
    for seed in UPLOAD_SEEDS:
        mesh = procedural_shape(seed).mesh
        assert mesh is not None
        path = folder / f"chair-{seed}.ply"
        path.write_bytes(
            trimesh.exchange.ply.export_ply(trimesh.Trimesh(mesh.vertices, mesh.faces))
        )
        paths.append(path)
    return paths


def format_row(row: Row) -> str:
    return (
        f"| {row.requests} | {row.seconds:.0f} | {row.rate:.2f} | {row.p50_ms:.0f} | "
        f"{row.p95_ms:.0f} | {row.p99_ms:.0f} | {row.max_ms:.0f} | {row.errors} | {row.changes} | "
        f"{row.rss_mib:.0f} | {row.server_rss_mib:.0f} | {row.workers_rss_mib:.0f} | {row.fds} | "
        f"{row.threads} | {row.processes} | {row.entry_files} | {row.load:.2f} |"
    )


HEADER = (
    "| requests | s | req/s | p50 ms | p95 ms | p99 ms | max ms | errors | changes | RSS MiB | "
    "server MiB | workers MiB | fds | threads | processes | entry files | load |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def verdict(rows: list[Row]) -> dict:
    """The three targets, measured: RSS growth from the first block to the last (and to the
    highest after it), descriptors of the last block against the first, p99 last / second."""
    first, last = rows[0], rows[-1]
    growth = last.rss_mib / first.rss_mib - 1
    peak = max(r.rss_mib for r in rows[1:]) / first.rss_mib - 1 if len(rows) > 1 else growth
    ratio = last.p99_ms / rows[1].p99_ms if len(rows) > 2 else float("nan")
    return {
        "rss_first_mib": first.rss_mib,
        "rss_last_mib": last.rss_mib,
        "rss_growth": growth,
        "rss_peak_growth": peak,
        "rss_ok": growth <= TARGETS["rss"],
        "fds_first": first.fds,
        "fds_last": last.fds,
        "fds_max": max(r.fds for r in rows),
        "fds_ok": last.fds <= first.fds,
        "p99_second_ms": rows[1].p99_ms if len(rows) > 1 else float("nan"),
        "p99_last_ms": last.p99_ms,
        "p99_ratio": ratio,
        "p99_ok": bool(ratio <= TARGETS["p99"]),
        "errors": sum(r.errors for r in rows),
    }


def draw(rows: list[Row], path: Path, title: str) -> None:
    """RSS, descriptors and p50/p99 latency per block, one panel each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([r.requests for r in rows]) / 1000
    figure, (memory, fds, latency) = plt.subplots(3, 1, figsize=(7, 7), dpi=120, sharex=True)
    memory.plot(x, [r.rss_mib for r in rows], marker="o", label="server + workers")
    memory.plot(x, [r.server_rss_mib for r in rows], marker=".", label="server")
    memory.plot(x, [r.workers_rss_mib for r in rows], marker=".", label="workers")
    band = rows[0].rss_mib * (1 + TARGETS["rss"])
    memory.axhline(band, color="grey", linestyle="--", linewidth=1, label="first block + 5 %")
    memory.set_ylabel("resident MiB")
    memory.set_ylim(0, max(band, *(r.rss_mib for r in rows)) * 1.1)
    memory.legend(fontsize=8, loc="lower center", ncol=4)
    fds.plot(x, [r.fds for r in rows], marker="o", label="open descriptors")
    fds.plot(x, [r.threads for r in rows], marker=".", label="threads")
    fds.set_ylabel("count")
    fds.set_ylim(0, max(r.fds for r in rows) * 1.3)
    fds.legend(fontsize=8, loc="center right")
    latency.plot(x, [r.p50_ms for r in rows], marker="o", label="p50")
    latency.plot(x, [r.p99_ms for r in rows], marker="o", label="p99")
    limit = rows[1].p99_ms * TARGETS["p99"] if len(rows) > 1 else 0.0
    if limit:
        latency.axhline(limit, color="grey", linestyle="--", linewidth=1, label="1.2x second p99")
    latency.set_ylabel("end-to-end ms")
    latency.set_xlabel("registrations answered (thousands)")
    latency.set_ylim(0, max(limit, *(r.p99_ms for r in rows)) * 1.15)
    latency.legend(fontsize=8, loc="lower center", ncol=3)
    memory.set_title(title, fontsize=9)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)


def shown(path: Path) -> str:
    """``path`` relative to the repository when it lies in it (the report names no machine)."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def report(args: argparse.Namespace, rows: list[Row], changes: list[dict], notes: dict) -> str:
    result = verdict(rows)
    ok = {True: "**met**", False: "**missed**"}
    failed = [c for c in changes if "error" in c]
    adds = [c["add_ms"] for c in changes if "add_ms" in c]
    lines = [
        f"# Soak ({args.requests} registrations, concurrency {args.concurrency})",
        "",
        f"{platform.machine()} {_cpu_model()}, {os.cpu_count()} CPUs; one `catalign serve` "
        f"({args.workers} worker processes of 1 thread, queue {QUEUE}, deadline "
        f"{DEADLINE_S:.0f} s) on a copy of `{shown(args.library)}` ({notes['models']} models); "
        f"{args.concurrency} client threads sharing one SDK `Client` (binary, no retries), "
        f"{len(notes['views'])} views of {args.points} points (chairs {notes['views']}) in turn, "
        f"up=+Z, seed=0; a library change (add a chair as a PLY mesh, remove the one added "
        f"before) every {args.change_every} answered registrations: {len(changes)} changes, "
        f"{len(failed)} failed, add median {np.median(adds) if adds else float('nan'):.0f} ms. "
        f"Server ready in {notes['ready_s']:.0f} s; load average {notes['load_before']:.2f} "
        f"before, {load_average():.2f} after; {notes['minutes']:.1f} min in all.",
        "",
        f"A row every {args.block} answered registrations; latency end to end over the block; "
        "memory, descriptors and threads summed over the server and every process below it "
        "(its worker processes and multiprocessing's resource tracker) at the block's end.",
        "",
        HEADER,
        *(format_row(r) for r in rows),
        "",
        f"- RSS: {result['rss_first_mib']:.0f} MiB after the first block, "
        f"{result['rss_last_mib']:.0f} MiB after the last: {result['rss_growth']:+.1%} "
        f"(highest after the first: {result['rss_peak_growth']:+.1%}); target at most "
        f"+{TARGETS['rss']:.0%}: {ok[result['rss_ok']]}.",
        f"- Open descriptors: {result['fds_first']} after the first block, "
        f"{result['fds_last']} after the last (highest {result['fds_max']}); target no growth: "
        f"{ok[result['fds_ok']]}.",
        f"- p99: {result['p99_second_ms']:.0f} ms in the second block, "
        f"{result['p99_last_ms']:.0f} ms in the last: {result['p99_ratio']:.2f}x; target at "
        f"most {TARGETS['p99']}x: {ok[result['p99_ok']]}."
        if len(rows) > 2
        else "- p99: fewer than 3 blocks, nothing to compare.",
        f"- Failed registrations: {result['errors']}."
        + (f" First: {notes['messages'][0]}" if notes["messages"] else ""),
    ]
    if failed:
        lines.append(f"- Failed library changes: {len(failed)}; first: {failed[0]['error']}")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=20_000)
    parser.add_argument("--concurrency", type=int, default=4)
    parser.add_argument("--block", type=int, default=1000, help="registrations per row")
    parser.add_argument("--change-every", type=int, default=500)
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--views", type=int, default=8, help="distinct views, in turn")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--library", type=Path, default=LIBRARY, help="copied, then changed")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--rows", type=Path, default=ROWS)
    parser.add_argument("--figure", type=Path, default=FIGURE)
    parser.add_argument(
        "--redraw", action="store_true", help="only draw --figure again from the --rows file"
    )
    args = parser.parse_args()
    if args.redraw:
        saved = json.loads(args.rows.read_text())
        draw([Row(**row) for row in saved["rows"]], args.figure, saved["title"])
        return
    if not 1 <= args.views <= len(VIEW_SEEDS):
        parser.error(f"--views must be 1 to {len(VIEW_SEEDS)}")
    if min(args.requests, args.concurrency, args.block, args.change_every) < 1:
        parser.error("counts must be at least 1")

    load_before = load_average()
    wall = time.perf_counter()
    seeds = VIEW_SEEDS[: args.views]
    views = [query_cloud(seed, count=args.points) for seed in seeds]
    with tempfile.TemporaryDirectory(prefix="catalign-soak-") as work:
        library = Path(work) / "library"
        shutil.copytree(args.library, library, ignore=shutil.ignore_patterns(".spool", ".lock"))
        meshes = upload_meshes(Path(work))
        models = count_entries(library)
        server = ServerProcess(args.workers, QUEUE, "processes", 1, library, DEADLINE_S)
        try:
            ready_s = server.wait_ready()
            soak = Soak(args, server, library)
            client = Client(
                server.url,
                timeout=CLIENT_TIMEOUT_S,
                retries=0,
                transport=httpx.HTTPTransport(limits=httpx.Limits(keepalive_expiry=KEEPALIVE_S)),
            )
            changes: list[dict] = []
            changer = threading.Thread(
                target=lambda: changes.extend(change(soak, server.url, meshes, args.change_every))
            )
            threads = [
                threading.Thread(target=register, args=(soak, client, views))
                for _ in range(args.concurrency)
            ]
            print(HEADER, file=sys.stderr)
            for thread in [changer, *threads]:
                thread.start()
            for thread in [*threads, changer]:
                thread.join()
            client.close()
        except Exception:
            print(f"catalign serve log (tail):\n{server.log()}", file=sys.stderr)
            raise
        finally:
            server.stop()
    notes = {
        "models": models,
        "views": list(seeds),
        "ready_s": ready_s,
        "load_before": load_before,
        "minutes": (time.perf_counter() - wall) / 60,
        "messages": soak.messages,
    }
    publish(report(args, soak.rows, changes, notes), args.out)
    args.rows.parent.mkdir(parents=True, exist_ok=True)
    rows = [asdict(r) for r in soak.rows]
    title = (
        f"soak: {args.requests} registrations at concurrency {args.concurrency}, "
        f"a library change every {args.change_every}"
    )
    payload = {"rows": rows, "changes": changes, "verdict": verdict(soak.rows), **notes}
    args.rows.write_text(json.dumps({"title": title, **payload}, indent=1) + "\n")
    draw(soak.rows, args.figure, title)


if __name__ == "__main__":
    main()
