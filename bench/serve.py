"""End-to-end latency and throughput of the served engine: SDK binary, SDK JSON and gRPC.

Starts the real server as a subprocess (``catalign serve``: shipped weights ``model_store/``,
default library ``model_store/library``, 2 workers, a queue deep enough for every request
in flight, a per-request deadline as long as the client's timeout so that no request is cut off)
on free 127.0.0.1 ports for HTTP and gRPC, so client and server do not share a GIL. One 20k-point
partial view of a procedural chair that is in no library is registered with a fixed ``top_k``
and ``seed`` (every request does the same work) at concurrency 1, 2, 4 and 16 (below, at and
above the 2 workers) through three transports: ``catalign_client.Client.align(encoding="binary")``
(float32 body), ``encoding="json"``, and the grpcio ``Catalign/Register`` stub (packed float32).
Per concurrency level the transports run interleaved, in ``--rounds`` rounds with a rotating
order, so a change in the machine's load hits all of them alike.

The whole run is repeated, one server at a time in the given order, for each worker mode of
``--worker-modes`` (``CATALIGN_WORKER_PROCESSES``: ``processes``, each worker a spawned process
with its own engine, or ``threads`` of the server process sharing one engine and its GIL) and
each value of ``--threads-per-worker`` (``CATALIGN_THREADS_PER_WORKER``: the torch, BLAS/OpenMP
and Open3D threads of each worker). The default, ``processes threads`` with 1 thread per worker
(the even share of a 2-core machine with 2 workers, the server's default there and the best
measured), compares worker processes with worker threads. With one thread per worker,
throughput should rise up to the core count and then stay flat; the ratio of the sdk-binary
req/s of the first server run to the second is printed below the table.

Latency is measured per request from before encoding to the parsed answer. The engine's own time
is the ``timings_ms['total']`` the server returns (from submission to its worker pool to the
result, so at concurrency > 1 it includes waiting for a worker); the reference "engine median"
of each server is its median over the concurrency-1 requests of every transport. Two overheads
are reported: the median of (end-to-end - server total) per request, which is the transport's own
cost (encoding, loopback, decoding, the HTTP or gRPC stack) at any concurrency, and end-to-end
median minus engine median, which at concurrency 1 is the same thing seen from outside and at
higher concurrency mostly queueing. A few direct ``Engine.register`` calls in this process (with
the threads of one server worker, once per thread count) give the engine's time with no server
at all. For each server run the table's notes give the load average at its start and the share
of the machine's CPU time that other processes used while it was measured (``/proc/stat`` minus
this process, the server and its worker processes): the timings mean something only when that
share is near 0.

Prints a markdown table and writes it to ``--out`` (default ``bench/results/serve.md``).

With ``--replicas 1,2`` it measures replicas behind HAProxy instead (``haproxy`` installed;
see ``docs/deploy-replicas.md``): as many ``catalign serve --read-only`` processes as the largest
count, each with one worker process of one thread, share the default library behind one HAProxy
(``tests/deploy/_replicas.py``, the set-up the deployment tests use), and the SDK registers the
same query through HAProxy at concurrency 8. Each count is measured with the replicas beyond it
put in maintenance on HAProxy's stats socket (idle, so they use no CPU), in ``--rounds`` rounds
with a rotating order, so every count sees the same machine. The table goes to ``--out``
(default ``bench/results/serve-replicas.md``), with the req/s of the largest count over the
smallest.

    .venv/bin/python bench/serve.py [--concurrency 1 2 4 16] [--requests 8 12 16 32]
        [--worker-modes processes threads] [--threads-per-worker 1] [--requests-scale 1.0]
        [--top-k 5] [--seed 0] [--points 20000] [--workers 2] [--rounds 2] [--engine-runs 3]
        [--out bench/results/serve.md]
    .venv/bin/python bench/serve.py --replicas 1,2 [--concurrency 8] [--requests 48] [--rounds 2]
        [--out bench/results/serve-replicas.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import grpc
import httpx
import numpy as np
from _report import load_average, publish

from catalign.api import catalign_pb2, catalign_pb2_grpc
from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import random_object_pose, render_view
from catalign.errors import CatalignError
from catalign.geometry.sampling import subsample
from catalign.library.store import list_ids
from catalign_client import Client

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "serve.md"
REPLICA_RESULTS = Path(__file__).parent / "results" / "serve-replicas.md"
MODEL_DIR = ROOT / "model_store"
LIBRARY = MODEL_DIR / "library"
UP = (0.0, 0.0, 1.0)
TRANSPORTS = ("sdk-binary", "sdk-json", "grpc")
START_TIMEOUT_S = 300.0
REQUEST_TIMEOUT_S = 600.0
KEEPALIVE_S = 2.0  # client-side expiry of idle HTTP connections, under uvicorn's 5 s
WORKER_MODES = ("processes", "threads")  # CATALIGN_WORKER_PROCESSES true / false

# One server run: worker mode ("processes" or "threads") and numeric threads per worker.
Run = tuple[str, int]


@dataclass(frozen=True)
class Sample:
    """One request: which server (worker mode, threads per worker), which transport, at what
    concurrency, how long, and the server's own time."""

    mode: str
    threads: int
    transport: str
    concurrency: int
    e2e_ms: float
    total_ms: float
    queue_ms: float


def query_cloud(seed: int = 5000, count: int = 20_000) -> np.ndarray:
    """A noisy 640x480 view of a chair outside every library, cut to ``count`` points."""
    rng = np.random.default_rng(seed)
    shape = procedural_shape(seed)
    pose = random_object_pose(rng, "upright", height=shape.height / 2)
    camera = camera_at(pose[:3, 3], 1.6, 25.0, 40.0, width=640, height=480)
    cloud = subsample(render_view(shape, pose, camera, rng), count, rng)
    return np.ascontiguousarray(cloud, dtype=np.float32)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class ServerProcess:
    """``catalign serve`` on free loopback ports, until ``stop``; its log goes to a temp file.
    ``mode``: its workers are ``processes`` (one engine each) or ``threads`` (one engine);
    ``library``: the library it serves; ``deadline_s``: each request's deadline (by default as
    long as the client's timeout, so that no request is cut off); ``api_key``: the X-API-Key it
    requires (none by default)."""

    def __init__(
        self,
        workers: int,
        queue: int,
        mode: str,
        threads_per_worker: int,
        library: Path = LIBRARY,
        deadline_s: float = REQUEST_TIMEOUT_S,
        api_key: str | None = None,
    ) -> None:
        self.port = free_port()
        self.grpc_port = free_port()
        while self.grpc_port == self.port:
            self.grpc_port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.grpc_target = f"127.0.0.1:{self.grpc_port}"
        self.workers = workers
        self.queue = queue
        self.mode = mode
        self.threads_per_worker = threads_per_worker
        self._log = tempfile.NamedTemporaryFile(prefix="catalign-serve-", suffix=".log")  # noqa: SIM115
        exe = shutil.which("catalign", path=str(Path(sys.executable).parent)) or "catalign"
        env = {k: v for k, v in os.environ.items() if not k.startswith("CATALIGN_")}
        env["CATALIGN_WORKER_PROCESSES"] = "true" if mode == "processes" else "false"
        env["CATALIGN_THREADS_PER_WORKER"] = str(threads_per_worker)
        # Every request must finish: a deadline would turn slow (oversubscribed) runs into 503s.
        env["CATALIGN_DEADLINE_S"] = str(deadline_s)
        env["CATALIGN_LOG_LEVEL"] = "warning"  # no line per request in the timed loop
        flags = {
            "--model-dir": MODEL_DIR,
            "--library": library,
            "--host": "127.0.0.1",
            "--port": self.port,
            "--grpc-port": self.grpc_port,
            "--workers": workers,
            "--queue": queue,
        }
        if api_key is not None:
            flags["--api-key"] = api_key
        command = [exe, "serve", *(str(x) for pair in flags.items() for x in pair)]
        self._process = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
        )

    def wait_ready(self) -> float:
        started = time.monotonic()
        deadline = started + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise RuntimeError(f"catalign serve exited during start-up:\n{self.log()}")
            try:
                if httpx.get(f"{self.url}/health/ready", timeout=5).status_code == 200:
                    return time.monotonic() - started
            except httpx.TransportError:
                pass
            time.sleep(0.25)
        raise RuntimeError(f"catalign serve not ready after {START_TIMEOUT_S:.0f} s:\n{self.log()}")

    @property
    def pid(self) -> int:
        return self._process.pid

    def log(self) -> str:
        return Path(self._log.name).read_text(errors="replace")[-4000:]

    def stop(self) -> None:
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._log.close()


class Transports:
    """One shared client per transport (as an application would hold one), thread-safe."""

    def __init__(self, server: ServerProcess, points: np.ndarray, top_k: int, seed: int) -> None:
        self.points = points
        self.top_k = top_k
        self.seed = seed
        # Idle connections are dropped by the client before uvicorn's 5 s keep-alive closes them:
        # else a connection idle for about 5 s (while another transport runs) can be reused just
        # as the server closes it ("Server disconnected without sending a response").
        keepalive = httpx.Limits(keepalive_expiry=KEEPALIVE_S)
        self.http = Client(
            server.url,
            timeout=REQUEST_TIMEOUT_S,
            retries=0,
            transport=httpx.HTTPTransport(limits=keepalive),
        )
        self.channel = grpc.insecure_channel(
            server.grpc_target,
            options=[
                ("grpc.max_send_message_length", 64 << 20),
                ("grpc.max_receive_message_length", 64 << 20),
            ],
        )
        grpc.channel_ready_future(self.channel).result(timeout=30)
        self.stub = catalign_pb2_grpc.CatalignStub(self.channel)
        self.calls: dict[str, Callable[[], tuple[float, float]]] = {
            "sdk-binary": lambda: self._sdk("binary"),
            "sdk-json": lambda: self._sdk("json"),
            "grpc": self._grpc,
        }

    def _sdk(self, encoding: str) -> tuple[float, float]:
        result = self.http.align(
            self.points, top_k=self.top_k, up=UP, seed=self.seed, encoding=encoding
        )
        return result.timings_ms["total"], result.timings_ms.get("queue", 0.0)

    def _grpc(self) -> tuple[float, float]:
        # The packing (float32 bytes) is part of the client's work, as the SDK's encoding is.
        request = catalign_pb2.RegisterRequest(
            points=np.ascontiguousarray(self.points, dtype="<f4").tobytes(),
            top_k=self.top_k,
            up=list(UP),
            seed=self.seed,
        )
        reply = self.stub.Register(request, timeout=REQUEST_TIMEOUT_S)
        return reply.timings_ms["total"], reply.timings_ms["queue"]

    def close(self) -> None:
        self.http.close()
        self.channel.close()


def run_batch(
    call: Callable[[], tuple[float, float]], count: int, concurrency: int
) -> tuple[list[tuple[float, float, float]], float]:
    """``count`` requests with ``concurrency`` in flight; per-request (e2e, total, queue), wall."""
    lock = threading.Lock()
    out: list[tuple[float, float, float]] = []

    def one(_: int) -> None:
        started = time.perf_counter()
        total, queue = call()
        e2e = (time.perf_counter() - started) * 1e3
        with lock:
            out.append((e2e, total, queue))

    started = time.perf_counter()
    with ThreadPoolExecutor(max_workers=concurrency) as pool:
        list(pool.map(one, range(count)))  # re-raises the first failure
    return out, time.perf_counter() - started


def engine_direct(
    points: np.ndarray, top_k: int, seed: int, runs: int, threads: list[int]
) -> dict[int, list[float]]:
    """Engine.register in this process, no server, with the numeric threads of one server worker
    (torch, BLAS/OpenMP and Open3D limited to ``t``) for each ``t`` in ``threads``: run times."""
    if runs <= 0:
        return {}
    from catalign.features.extractor import LearnedExtractor
    from catalign.library.loaded import load
    from catalign.registration.config import EngineConfig
    from catalign.registration.engine import Engine
    from catalign.threads import limit_threads

    extractor = LearnedExtractor(MODEL_DIR)
    engine = Engine(
        extractor, load(LIBRARY, extractor.fingerprint), config=EngineConfig(top_k=top_k)
    )
    up = np.asarray(UP)
    cloud = points.astype(np.float64)
    out: dict[int, list[float]] = {}
    for t in threads:
        limit_threads(t, total=t)  # as a worker's initializer does; one worker here
        engine.register(cloud, top_k=top_k, up=up, seed=seed)  # warm-up
        out[t] = []
        for _ in range(runs):
            started = time.perf_counter()
            engine.register(cloud, top_k=top_k, up=up, seed=seed)
            out[t].append((time.perf_counter() - started) * 1e3)
    return out


def serve_run(
    run: Run,
    args: argparse.Namespace,
    counts: list[int],
    queue: int,
    points: np.ndarray,
    walls: dict[tuple[str, int, str, int], float],
) -> tuple[list[Sample], float, float]:
    """Every concurrency level, transports interleaved, on one server whose workers are ``mode``
    with ``threads`` numeric threads each: the samples (wall times added to ``walls``), the
    server's start-up time and the share of the machine's CPU time that other processes used
    while it was measured."""
    mode, threads = run
    server = ServerProcess(args.workers, queue, mode, threads)
    samples: list[Sample] = []
    try:
        ready_s = server.wait_ready()
        pids = _process_tree(server.pid)  # the server and its worker processes, all started
        cpu_before = _cpu_seconds(*pids)
        transports = Transports(server, points, args.top_k, args.seed)
        try:
            for name in TRANSPORTS:  # warm-up: connections, lazy imports, first-call paths
                transports.calls[name]()
            for concurrency, count in zip(args.concurrency, counts, strict=True):
                chunks = _split(count, args.rounds)
                for r, chunk in enumerate(chunks):
                    order = TRANSPORTS[r % 3 :] + TRANSPORTS[: r % 3]
                    for name in order:
                        results, wall = run_batch(transports.calls[name], chunk, concurrency)
                        key = (mode, threads, name, concurrency)
                        walls[key] = walls.get(key, 0.0) + wall
                        samples += [
                            Sample(mode, threads, name, concurrency, *row) for row in results
                        ]
                        print(
                            f"{mode} threads/worker={threads} c={concurrency:<3} {name:<10} "
                            f"round {r + 1}: {chunk} requests in {wall:.1f} s",
                            file=sys.stderr,
                        )
        finally:
            transports.close()
        foreign = _foreign_share(cpu_before, _cpu_seconds(*pids))
    except Exception:
        print(f"catalign serve log (tail):\n{server.log()}", file=sys.stderr)
        raise
    finally:
        server.stop()
    return samples, ready_s, foreign


def replica_counts(text: str) -> list[int]:
    """``--replicas 1,2``: distinct positive replica counts, in the given order."""
    try:
        counts = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected counts such as 1,2, got {text!r}") from None
    if min(counts) < 1 or len(set(counts)) != len(counts):
        raise argparse.ArgumentTypeError(f"replica counts must differ and be >= 1: {text!r}")
    return counts


def replicas_main(args: argparse.Namespace, counts: list[int], points: np.ndarray) -> None:
    """``--replicas``: sdk-binary req/s through HAProxy for each replica count (see the module
    docstring), printed and written to ``--out`` (default ``bench/results/serve-replicas.md``)."""
    sys.path.insert(0, str(ROOT))  # the set-up is the deployment tests' own module
    from tests.deploy._replicas import Deployment

    replicas: list[int] = args.replicas
    load_before = load_average()
    wall_started = time.perf_counter()
    samples: dict[tuple[int, int], list[tuple[float, float, float]]] = {}
    walls: dict[tuple[int, int], float] = {}
    cpu: dict[int, list[float]] = {n: [0.0, 0.0, 0.0] for n in replicas}
    with (
        tempfile.TemporaryDirectory(prefix="catalign-replicas-") as work,
        Deployment(
            LIBRARY,
            MODEL_DIR,
            Path(work),
            readers=max(replicas),
            writer=False,
            workers=1,
            threads_per_worker=1,
            env={
                "CATALIGN_DEADLINE_S": str(REQUEST_TIMEOUT_S),
                "CATALIGN_WORKER_PROCESSES": "true",
            },
        ) as deployment,
    ):
        proxy = deployment.proxy
        servers = (r.process.pid for r in deployment.readers if r.process)
        pids = [proxy.process.pid, *(pid for s in servers for pid in _process_tree(s))]
        client = Client(
            deployment.url,
            timeout=REQUEST_TIMEOUT_S,
            retries=0,
            transport=httpx.HTTPTransport(limits=httpx.Limits(keepalive_expiry=KEEPALIVE_S)),
        )

        def call() -> tuple[float, float]:
            result = client.align(points, top_k=args.top_k, up=UP, seed=args.seed)
            return result.timings_ms["total"], result.timings_ms.get("queue", 0.0)

        def serve_with(count: int) -> None:
            """Put the readers beyond ``count`` in maintenance, the others back in service."""
            for index, reader in enumerate(deployment.readers):
                state = "ready" if index < count else "maint"
                proxy.command(f"set server readers/{reader.name} state {state}")
                proxy.wait_status(f"readers/{reader.name}", "UP" if state == "ready" else "MAINT")

        try:
            serve_with(max(replicas))
            run_batch(call, 2 * max(args.concurrency), max(args.concurrency))  # warm-up
            for concurrency, count in zip(args.concurrency, counts, strict=True):
                for r, chunk in enumerate(_split(count, args.rounds)):
                    for n in replicas[r % len(replicas) :] + replicas[: r % len(replicas)]:
                        serve_with(n)
                        before = _cpu_seconds(*pids)
                        results, wall = run_batch(call, chunk, concurrency)
                        after = _cpu_seconds(*pids)
                        for i, (a, b) in enumerate(zip(before, after, strict=True)):
                            cpu[n][i] += b - a
                        samples.setdefault((n, concurrency), []).extend(results)
                        walls[n, concurrency] = walls.get((n, concurrency), 0.0) + wall
                        print(
                            f"replicas={n} c={concurrency}: {chunk} requests in {wall:.1f} s "
                            f"(round {r + 1})",
                            file=sys.stderr,
                        )
            answered = {
                r.name: proxy.stats()[f"readers/{r.name}"]["hrsp_2xx"] for r in deployment.readers
            }
        finally:
            client.close()
    elapsed = time.perf_counter() - wall_started

    lines = [
        "# Replicas behind HAProxy (20k-point query, loopback)",
        "",
        f"{platform.machine()} {_cpu_model()}, {os.cpu_count()} CPUs; "
        f"{max(replicas)} `catalign serve --read-only --workers 1` processes "
        "(`CATALIGN_WORKER_PROCESSES=true`, `CATALIGN_THREADS_PER_WORKER=1`: one worker process "
        f"of one thread each) sharing the default library ({len(_library_ids())} models) "
        "behind HAProxy (`tests/deploy/_replicas.py`: leastconn, 2 requests per replica at "
        "once, the rest queued in HAProxy); a count of n serves with "
        "the first n, the others in maintenance; the SDK (`Client.align`, binary) through "
        f"HAProxy, query {len(points)} points, top_k={args.top_k}, seed={args.seed}, up=+Z; "
        f"{args.rounds} interleaved rounds; load average {load_before:.2f} before, "
        f"{load_average():.2f} after; {elapsed / 60:.1f} min in all. Answers per replica: "
        + ", ".join(f"{name} {count}" for name, count in answered.items())
        + ".",
        "",
        "| replicas | concurrency | requests | req/s | median ms | p95 ms | "
        "server total median ms | other processes' CPU share |",
        "|---|---|---|---|---|---|---|---|",
    ]
    rates: dict[tuple[int, int], float] = {}
    for n in replicas:
        busy, total, ours = cpu[n]
        foreign = max(0.0, busy - ours) / total if total > 0 else float("nan")
        for concurrency in args.concurrency:
            cell = np.array(samples[n, concurrency])
            rates[n, concurrency] = len(cell) / walls[n, concurrency]
            lines.append(
                f"| {n} | {concurrency} | {len(cell)} | {rates[n, concurrency]:.2f} | "
                f"{np.median(cell[:, 0]):.0f} | {np.percentile(cell[:, 0], 95):.0f} | "
                f"{np.median(cell[:, 1]):.0f} | {foreign:.0%} |"
            )
    if len(replicas) >= 2:
        low, high = min(replicas), max(replicas)
        ratios = ", ".join(
            f"c={c}: **{rates[high, c] / rates[low, c]:.2f}x**" for c in args.concurrency
        )
        lines += ["", f"req/s with {high} replicas over {low}: {ratios}."]
    publish("\n".join(lines) + "\n", args.out or REPLICA_RESULTS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--concurrency", type=int, nargs="+", help="Default 1 2 4 16; 8 with --replicas."
    )
    parser.add_argument(
        "--requests",
        type=int,
        nargs="+",
        help="Timed requests per transport at each concurrency level (same order; default "
        "8 12 16 32), or per replica count and level with --replicas (default 48).",
    )
    parser.add_argument(
        "--replicas",
        type=replica_counts,
        help="Replica counts to compare behind HAProxy, e.g. 1,2 (single-worker replicas).",
    )
    parser.add_argument(
        "--worker-modes",
        nargs="+",
        choices=WORKER_MODES,
        default=list(WORKER_MODES),
        help="CATALIGN_WORKER_PROCESSES of the server runs (processes: true, threads: false).",
    )
    parser.add_argument(
        "--threads-per-worker",
        type=int,
        nargs="+",
        default=[1],
        help="CATALIGN_THREADS_PER_WORKER of the server runs. A server runs for every worker "
        "mode and thread count (modes outer), one after another; the sdk-binary req/s of the "
        "first run is compared with the second.",
    )
    parser.add_argument("--requests-scale", type=float, default=1.0)
    parser.add_argument("--top-k", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2, help="Interleaving rounds per level.")
    parser.add_argument(
        "--engine-runs", type=int, default=3, help="Direct engine runs per thread count (0: none)."
    )
    parser.add_argument(
        "--out",
        type=Path,
        help=f"Where the table goes (default {RESULTS.relative_to(ROOT)}, or "
        f"{REPLICA_RESULTS.relative_to(ROOT)} with --replicas).",
    )
    args = parser.parse_args()
    if args.concurrency is None:
        args.concurrency = [8] if args.replicas else [1, 2, 4, 16]
    if args.requests is None:
        args.requests = [48] * len(args.concurrency) if args.replicas else [8, 12, 16, 32]
    if len(args.requests) != len(args.concurrency):
        parser.error("--requests needs one count per --concurrency level")
    if len(set(args.worker_modes)) != len(args.worker_modes):
        parser.error("--worker-modes values must differ")
    if len(set(args.threads_per_worker)) != len(args.threads_per_worker):
        parser.error("--threads-per-worker values must differ")
    if min(args.threads_per_worker) < 1:
        parser.error("--threads-per-worker values must be at least 1")
    counts = [max(args.rounds, round(n * args.requests_scale)) for n in args.requests]
    thread_counts: list[int] = args.threads_per_worker
    runs: list[Run] = [(m, t) for m in args.worker_modes for t in thread_counts]

    points = query_cloud(count=args.points)
    if args.replicas:
        replicas_main(args, counts, points)
        return
    binary_bytes = points.size * 4
    json_bytes = len(json.dumps({"points": points.tolist(), "top_k": args.top_k}))
    encode_ms = {
        "binary": _median_ms(lambda: np.ascontiguousarray(points, dtype="<f4").tobytes()),
        "JSON": _median_ms(lambda: json.dumps({"points": points.tolist()}).encode()),
    }
    load_before = f"{load_average():.2f}"
    wall_started = time.perf_counter()

    direct = engine_direct(points, args.top_k, args.seed, args.engine_runs, thread_counts)
    queue = max(64, 2 * max(args.concurrency))
    samples: list[Sample] = []
    walls: dict[tuple[str, int, str, int], float] = {}
    ready_s: dict[Run, float] = {}
    load_at_start: dict[Run, float] = {}
    foreign: dict[Run, float] = {}
    for run in runs:  # one server at a time, in the given order
        load_at_start[run] = load_average()
        run_samples, ready_s[run], foreign[run] = serve_run(run, args, counts, queue, points, walls)
        samples += run_samples
    elapsed = time.perf_counter() - wall_started

    engine_ms = {
        run: float(
            np.median(
                [s.total_ms for s in samples if (s.mode, s.threads) == run and s.concurrency == 1]
            )
        )
        if 1 in args.concurrency
        else float("nan")
        for run in runs
    }
    lines = [
        "# Served latency and throughput (20k-point query, loopback)",
        "",
        f"{platform.machine()} {_cpu_model()}, {os.cpu_count()} CPUs; server: `catalign serve`, "
        f"{args.workers} workers as {' or '.join(args.worker_modes)} "
        "(`CATALIGN_WORKER_PROCESSES`: a spawned process with its own engine each, or threads "
        f"sharing one engine) x {' or '.join(map(str, thread_counts))} threads "
        f"(`CATALIGN_THREADS_PER_WORKER`: torch, BLAS/OpenMP, Open3D), one server after another "
        f"in the order below, queue {queue}, deadline {REQUEST_TIMEOUT_S:.0f} s, "
        f"{len(_library_ids())} library models; query {len(points)} points (binary "
        f"{binary_bytes / 1024:.0f} KiB, JSON {json_bytes / 1024:.0f} KiB; client-side encoding "
        f"alone: binary {encode_ms['binary']:.1f} ms, JSON {encode_ms['JSON']:.0f} ms), "
        f"top_k={args.top_k}, seed={args.seed}, up=+Z; {args.rounds} interleaved rounds per "
        f"level; requests scale {args.requests_scale:g}; load average {load_before} before, "
        f"{load_average():.2f} after; {elapsed / 60:.1f} min in all.",
        "",
    ]
    for run in runs:
        lines.append(
            f"- {_label(run)}: engine median (server `timings_ms.total`, concurrency 1, "
            f"all transports) **{engine_ms[run]:.0f} ms**; server ready in {ready_s[run]:.0f} s; "
            f"load average {load_at_start[run]:.2f} at its start; other processes used "
            f"{foreign[run]:.0%} of the machine's CPU time during its run."
        )
    if direct:
        lines.append(
            "- direct `Engine.register` in-process, no server: "
            + "; ".join(
                f"{t} thread(s) median {np.median(direct[t]):.0f} ms over {len(direct[t])} runs"
                for t in thread_counts
            )
            + "."
        )
    lines += [
        "",
        "| workers | threads/worker | transport | concurrency | requests | median ms | p95 ms | "
        "req/s | server total median ms | overhead/request median ms | median - engine ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    rates: dict[tuple[str, int, str, int], float] = {}
    for mode, t in runs:
        for concurrency in args.concurrency:
            for name in TRANSPORTS:
                key = (mode, t, name, concurrency)
                cell = [
                    s for s in samples if (s.mode, s.threads, s.transport, s.concurrency) == key
                ]
                e2e = np.array([s.e2e_ms for s in cell])
                total = np.array([s.total_ms for s in cell])
                rates[key] = len(cell) / walls[key]
                lines.append(
                    f"| {mode} | {t} | {name} | {concurrency} | {len(cell)} | "
                    f"{np.median(e2e):.0f} | {np.percentile(e2e, 95):.0f} | {rates[key]:.2f} | "
                    f"{np.median(total):.0f} | {np.median(e2e - total):.1f} | "
                    f"{np.median(e2e) - engine_ms[mode, t]:+.0f} |"
                )
    lines += [
        "",
        "overhead/request = end-to-end minus the server's `timings_ms.total` of the same request "
        "(client encoding, loopback, server decoding, HTTP/gRPC stack, answer parsing); "
        "median - engine = end-to-end median minus the engine median of the same server above "
        "(includes queueing at concurrency > 1). Target: binary adds at most 10 ms to the "
        "engine's own time.",
    ]
    if len(runs) >= 2:
        first, second = runs[:2]
        binary = {run: [rates[(*run, "sdk-binary", c)] for c in args.concurrency] for run in runs}
        ratios = ", ".join(
            f"c={c}: **{a / b:.2f}x**"
            for c, a, b in zip(args.concurrency, binary[first], binary[second], strict=True)
        )
        lines += ["", f"sdk-binary req/s, {_label(first)} over {_label(second)}: {ratios}."]
    table = "\n".join(lines) + "\n"
    publish(table, args.out or RESULTS)


def _label(run: Run) -> str:
    """``processes, 1 thread/worker``: a server run as the notes and the ratio name it."""
    mode, threads = run
    return f"{mode}, {threads} thread{'s' if threads != 1 else ''}/worker"


def _process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants now (a server's spawned worker processes), from ``/proc``;
    just ``pid`` where ``/proc`` is missing."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])  # field 4
        except (OSError, ValueError, IndexError):
            continue  # gone meanwhile
        parents.setdefault(ppid, []).append(int(stat.parent.name))
    tree = [pid]
    for parent in tree:  # grows while it is walked: breadth first
        tree += parents.get(parent, [])
    return tree


def _cpu_seconds(*server_pids: int) -> tuple[float, float, float]:
    """CPU seconds so far: busy and in all (every core, from ``/proc/stat``), and used by this
    process plus the server processes (client and servers together); NaN where ``/proc`` is
    missing."""
    tick = os.sysconf("SC_CLK_TCK")
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
        user, nice, system, idle, iowait, irq, softirq, steal = fields
        server = 0.0
        for pid in server_pids:
            stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            server += (int(stat[11]) + int(stat[12])) / tick  # utime, stime (fields 14 and 15)
    except (OSError, ValueError, IndexError):
        return float("nan"), float("nan"), float("nan")
    busy = (user + nice + system + irq + softirq + steal) / tick
    return busy, busy + (idle + iowait) / tick, time.process_time() + server


def _foreign_share(before: tuple[float, float, float], after: tuple[float, float, float]) -> float:
    """Share of the machine's CPU time between two ``_cpu_seconds`` that neither the server nor
    this process used: other load that makes the timings unreliable (a few % is background)."""
    busy, total, ours = (b - a for a, b in zip(before, after, strict=True))
    return max(0.0, busy - ours) / total if total > 0 else float("nan")


def _median_ms(call: Callable[[], object], runs: int = 5) -> float:
    out = []
    for _ in range(runs):
        started = time.perf_counter()
        call()
        out.append((time.perf_counter() - started) * 1e3)
    return float(np.median(out))


def _split(count: int, parts: int) -> list[int]:
    return [count // parts + (r < count % parts) for r in range(parts)]


def _library_ids() -> list[str]:
    try:
        return list_ids(LIBRARY)
    except CatalignError:
        return []


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


if __name__ == "__main__":
    main()
