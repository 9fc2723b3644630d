"""A real server on loopback: uvicorn in a background thread, a small procedural library.

Tests talk to it over HTTP (httpx) and gRPC exactly as clients do. The library (3 procedural
chairs) is built once per session with the shipped weights (``model_store/``); without them
every server test is skipped. ``CATALIGN_TEST_MODEL_DIR`` points the tests at other weights
(a development checkpoint) while ``model_store/`` is being trained.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn

from catalign.api.app import create_app
from catalign.api.settings import ServiceSettings
from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.geometry.se3 import make_pose
from catalign.paths import DEFAULT_MODEL_DIR
from catalign_client import Client

LIBRARY_SEEDS = 3  # proc-0000, proc-0001, proc-0002
START_TIMEOUT_S = 180.0


@dataclass(frozen=True)
class Server:
    """A running server: where to reach it and how it was configured."""

    url: str
    grpc_target: str | None
    settings: ServiceSettings


@dataclass(frozen=True)
class View:
    """A partial, noisy view of a procedural chair placed with a known model -> world pose."""

    seed: int
    points: np.ndarray  # float32, world frame (+Z up)
    pose: np.ndarray


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture(scope="session")
def library_dir(model_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library of 3 procedural chairs, built once; tests that change it copy it first."""
    from catalign.features.extractor import LearnedExtractor
    from catalign.library.index import build_procedural

    out = tmp_path_factory.mktemp("api") / "library"
    build_procedural(out, LearnedExtractor(model_dir, threads=1), LIBRARY_SEEDS, progress=False)
    return out


@pytest.fixture
def library_copy(library_dir: Path, tmp_path: Path) -> Path:
    target = tmp_path / "library"
    shutil.copytree(library_dir, target)
    return target


@pytest.fixture(scope="session")
def serve(model_dir: Path) -> Callable[..., AbstractContextManager[Server]]:
    """``with serve(library=..., grpc=True, **settings) as server:`` runs a server."""
    return partial(run_server, model_dir=model_dir)


@pytest.fixture(scope="module")
def shipped_client(serve: Callable) -> Iterator[Client]:
    """The SDK on a server of the shipped model and the default library, as a user starts
    it, for one test module."""
    library = Path(DEFAULT_MODEL_DIR) / "library"
    with serve(library=library, warmup=False) as server, Client(server.url, timeout=120) as sdk:
        yield sdk


@pytest.fixture(scope="session")
def views() -> Callable[..., View]:
    """``views(seed, yaw=0.7, step=1)``: a partial view of a procedural chair."""
    return chair_view


@contextmanager
def run_server(*, grpc: bool = False, **overrides: object) -> Iterator[Server]:
    """Serve ``create_app`` on a free loopback port until the block ends; waits until ready."""
    settings = ServiceSettings(
        host="127.0.0.1",
        port=free_port(),
        grpc_port=free_port() if grpc else 0,
        threads_per_worker=1,
        **overrides,
    )
    app = create_app(settings)
    config = uvicorn.Config(
        app, host="127.0.0.1", port=settings.port, log_config=None, access_log=False
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{settings.port}"
    try:
        _wait_ready(url, thread.is_alive)
        grpc_target = f"127.0.0.1:{settings.grpc_port}" if settings.grpc_enabled else None
        yield Server(url=url, grpc_target=grpc_target, settings=settings)
    finally:
        server.should_exit = True
        thread.join(timeout=60)


@dataclass(frozen=True)
class ServerProcess:
    """``catalign serve`` running as a process of its own: where to reach it, and its process."""

    url: str
    process: subprocess.Popen


@pytest.fixture(scope="session")
def serve_process(model_dir: Path) -> Callable[..., AbstractContextManager[ServerProcess]]:
    """``with serve_process(library, *flags, env={...}, preexec_fn=None) as server:`` runs
    ``catalign serve`` in its own process (own GIL, own memory), stopped when the block ends."""
    return partial(run_server_process, model_dir=model_dir)


@contextmanager
def run_server_process(
    library: Path,
    *flags: str,
    model_dir: Path,
    env: dict[str, str] | None = None,
    preexec_fn: Callable[[], None] | None = None,
) -> Iterator[ServerProcess]:
    """``catalign serve`` on a free loopback port (gRPC off), ``CATALIGN_*`` from ``env`` only."""
    port = free_port()
    environment = {k: v for k, v in os.environ.items() if not k.startswith("CATALIGN_")}
    command = [
        sys.executable,
        "-c",
        "from catalign.cli import app; app()",
        "serve",
        *("--model-dir", str(model_dir), "--library", str(library)),
        *("--port", str(port), "--grpc-port", "0", *flags),
    ]
    process = subprocess.Popen(
        command,
        env=environment | (env or {}),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        preexec_fn=preexec_fn,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        _wait_ready(url, lambda: process.poll() is None)
        yield ServerProcess(url=url, process=process)
    finally:
        process.terminate()
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()


def _wait_ready(url: str, alive: Callable[[], bool]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if not alive():
            raise RuntimeError("the server stopped during start-up (see the log)")
        try:
            if httpx.get(f"{url}/health/ready", timeout=5).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"the server at {url} was not ready after {START_TIMEOUT_S:.0f} s")


def chair_view(seed: int, yaw: float = 0.7, step: int = 1) -> View:
    """Chair ``seed`` standing on the floor (+Z up) at ``yaw``, seen from 2 m, 25 degrees up."""
    shape = procedural_shape(seed)
    position = np.array([0.3, -0.2, -shape.points[:, 1].min()])
    pose = make_pose(upright_rotation(yaw), position)
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(seed))
    return View(seed, np.ascontiguousarray(points[::step], dtype=np.float32), pose)
