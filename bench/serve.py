"""End-to-end latency and throughput of the served engine: SDK binary, SDK JSON and gRPC.

Starts the real server as a subprocess (``catalign serve``: shipped weights ``model_store/``,
default library ``model_store/library``, 2 worker threads, a queue deep enough for every request
in flight) on free 127.0.0.1 ports for HTTP and gRPC, so client and server do not share a GIL.
One 20k-point partial view of a procedural chair that is in no library is registered with a
fixed ``top_k`` and ``seed`` (every request does the same work) at concurrency 1, 4 and 16
through three transports: ``catalign_client.Client.align(encoding="binary")`` (float32 body),
``encoding="json"``, and the grpcio ``Catalign/Register`` stub (packed float32). Per concurrency
level the transports run interleaved, in ``--rounds`` rounds with a rotating order, so a change
in the machine's load hits all of them alike.

Latency is measured per request from before encoding to the parsed answer. The engine's own time
is the ``timings_ms['total']`` the server returns (from submission to its worker pool to the
result, so at concurrency > 1 it includes waiting for a worker); the reference "engine median"
is its median over the concurrency-1 requests of every transport. Two overheads are reported:
the median of (end-to-end - server total) per request, which is the transport's own cost
(encoding, loopback, decoding, the HTTP or gRPC stack) at any concurrency, and end-to-end median
minus engine median, which at concurrency 1 is the same thing seen from outside and at higher
concurrency mostly queueing. A few direct ``Engine.register`` calls in this process (1 torch
thread, like one server worker) give the engine's time with no server at all.

Prints a markdown table and writes it to ``bench/results/serve.md``.

    .venv/bin/python bench/serve.py [--concurrency 1 4 16] [--requests 8 16 32]
        [--requests-scale 1.0] [--top-k 5] [--seed 0] [--rounds 2] [--engine-runs 3]
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
from catalign.data.shapes import procedural_shape
from catalign.data.views import camera_at, random_object_pose, render_view
from catalign.geometry.sampling import subsample
from catalign_client import Client

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "serve.md"
MODEL_DIR = ROOT / "model_store"
LIBRARY = MODEL_DIR / "library"
UP = (0.0, 0.0, 1.0)
TRANSPORTS = ("sdk-binary", "sdk-json", "grpc")
START_TIMEOUT_S = 300.0
REQUEST_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class Sample:
    """One request: which transport, at what concurrency, how long, and the server's own time."""

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
    """``catalign serve`` on free loopback ports, until ``stop``; its log goes to a temp file."""

    def __init__(self, workers: int, queue: int) -> None:
        self.port = free_port()
        self.grpc_port = free_port()
        while self.grpc_port == self.port:
            self.grpc_port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.grpc_target = f"127.0.0.1:{self.grpc_port}"
        self.workers = workers
        self.queue = queue
        self._log = tempfile.NamedTemporaryFile(prefix="catalign-serve-", suffix=".log")  # noqa: SIM115
        exe = shutil.which("catalign", path=str(Path(sys.executable).parent)) or "catalign"
        env = {k: v for k, v in os.environ.items() if not k.startswith("CATALIGN_")}
        env["CATALIGN_TORCH_THREADS"] = "1"
        env["CATALIGN_LOG_LEVEL"] = "warning"  # no line per request in the timed loop
        flags = {
            "--model-dir": MODEL_DIR,
            "--library": LIBRARY,
            "--host": "127.0.0.1",
            "--port": self.port,
            "--grpc-port": self.grpc_port,
            "--workers": workers,
            "--queue": queue,
        }
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
        self.http = Client(server.url, timeout=REQUEST_TIMEOUT_S, retries=0)
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


def run_batch(call: Callable[[], tuple[float, float]], count: int, concurrency: int):
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


def engine_direct(points: np.ndarray, top_k: int, seed: int, runs: int) -> list[float]:
    """Engine.register in this process with 1 torch thread (one server worker), no server."""
    if runs <= 0:
        return []
    import torch

    from catalign.features.extractor import LearnedExtractor
    from catalign.library.index import load
    from catalign.registration.engine import Engine

    torch.set_num_threads(1)
    extractor = LearnedExtractor(MODEL_DIR, threads=1)
    engine = Engine(
        extractor, load(LIBRARY, extractor.fingerprint), headings=extractor.headings, top_k=top_k
    )
    up = np.asarray(UP)
    cloud = points.astype(np.float64)
    engine.register(cloud, top_k=top_k, up=up, seed=seed)  # warm-up
    out = []
    for _ in range(runs):
        started = time.perf_counter()
        engine.register(cloud, top_k=top_k, up=up, seed=seed)
        out.append((time.perf_counter() - started) * 1e3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--concurrency", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument(
        "--requests",
        type=int,
        nargs="+",
        default=[8, 16, 32],
        help="Timed requests per transport at each concurrency level (same order).",
    )
    parser.add_argument("--requests-scale", type=float, default=1.0)
    parser.add_argument("--top-k", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2, help="Interleaving rounds per level.")
    parser.add_argument("--engine-runs", type=int, default=3, help="Direct engine runs (0: none).")
    args = parser.parse_args()
    if len(args.requests) != len(args.concurrency):
        parser.error("--requests needs one count per --concurrency level")
    counts = [max(args.rounds, round(n * args.requests_scale)) for n in args.requests]

    points = query_cloud(count=args.points)
    binary_bytes = points.size * 4
    json_bytes = len(json.dumps({"points": points.tolist(), "top_k": args.top_k}))
    encode_ms = {
        "binary": _median_ms(lambda: np.ascontiguousarray(points, dtype="<f4").tobytes()),
        "JSON": _median_ms(lambda: json.dumps({"points": points.tolist()}).encode()),
    }
    load_before = f"{load_average():.2f}"
    wall_started = time.perf_counter()

    direct = engine_direct(points, args.top_k, args.seed, args.engine_runs)
    queue = max(64, 2 * max(args.concurrency))
    server = ServerProcess(args.workers, queue)
    samples: list[Sample] = []
    walls: dict[tuple[str, int], float] = {}
    try:
        ready_s = server.wait_ready()
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
                        walls[name, concurrency] = walls.get((name, concurrency), 0.0) + wall
                        samples += [Sample(name, concurrency, *row) for row in results]
                        print(
                            f"c={concurrency:<3} {name:<10} round {r + 1}: {chunk} requests "
                            f"in {wall:.1f} s",
                            file=sys.stderr,
                        )
        finally:
            transports.close()
    finally:
        server.stop()
    elapsed = time.perf_counter() - wall_started

    engine_ms = float(np.median([s.total_ms for s in samples if s.concurrency == 1]))
    lines = [
        "# Served latency and throughput (20k-point query, loopback)",
        "",
        f"{platform.machine()} {_cpu_model()}, {os.cpu_count()} CPUs; server: `catalign serve`, "
        f"{args.workers} workers x 1 torch thread, queue {queue}, {len(_library_ids())} library "
        f"models; query {len(points)} points (binary {binary_bytes / 1024:.0f} KiB, JSON "
        f"{json_bytes / 1024:.0f} KiB; client-side encoding alone: binary "
        f"{encode_ms['binary']:.1f} ms, JSON {encode_ms['JSON']:.0f} ms), "
        f"top_k={args.top_k}, seed={args.seed}, up=+Z; "
        f"{args.rounds} interleaved rounds per level; load average {load_before} before, "
        f"{load_average():.2f} after; {elapsed / 60:.1f} min in all "
        f"(server ready in {ready_s:.0f} s).",
        "",
        f"Engine median (server `timings_ms.total`, concurrency 1, all transports): "
        f"**{engine_ms:.0f} ms**"
        + (
            f"; direct `Engine.register` in-process, no server: median {np.median(direct):.0f} "
            f"ms over {len(direct)} runs."
            if direct
            else "."
        ),
        "",
        "| transport | concurrency | requests | median ms | p95 ms | req/s | server total "
        "median ms | overhead/request median ms | median - engine ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for concurrency in args.concurrency:
        for name in TRANSPORTS:
            cell = [s for s in samples if s.transport == name and s.concurrency == concurrency]
            e2e = np.array([s.e2e_ms for s in cell])
            total = np.array([s.total_ms for s in cell])
            lines.append(
                f"| {name} | {concurrency} | {len(cell)} | {np.median(e2e):.0f} | "
                f"{np.percentile(e2e, 95):.0f} | {len(cell) / walls[name, concurrency]:.2f} | "
                f"{np.median(total):.0f} | {np.median(e2e - total):.1f} | "
                f"{np.median(e2e) - engine_ms:+.0f} |"
            )
    lines += [
        "",
        "overhead/request = end-to-end minus the server's `timings_ms.total` of the same request "
        "(client encoding, loopback, server decoding, HTTP/gRPC stack, answer parsing); "
        "median - engine = end-to-end median minus the engine median above (includes queueing "
        "at concurrency > 1). Target: binary adds at most 10 ms to the engine's own time.",
    ]
    table = "\n".join(lines) + "\n"
    publish(table, RESULTS)


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
        return list(json.loads((LIBRARY / "manifest.json").read_text()).get("entries", {}))
    except (OSError, ValueError):
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
