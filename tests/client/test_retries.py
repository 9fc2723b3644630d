"""The retry rules over real sockets: a stdlib HTTP server on loopback answers from a script
(502, 503 with ``Retry-After``, 504, a reset connection, then a success), and the clients wait
for real. What is resent, with which key, after how long, and within which total time."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from catalign_client import (
    AsyncClient,
    Client,
    ConflictError,
    InvalidInputError,
    NotFoundError,
    ServerError,
    ServiceUnavailableError,
    TransportError,
)
from catalign_client import _client as client_module

CLOUD = np.random.default_rng(0).normal(size=(50, 3))
RESET = "reset"  # close the connection without an answer (TCP RST)


@dataclass
class Script:
    """What the server answers, request after request: a status with headers, or ``RESET``;
    the last step repeats. ``seen`` holds each request's arrival time, method, path, headers."""

    steps: list[tuple[int, dict[str, str]] | str]
    ok_body: dict[str, Any]
    seen: list[dict[str, Any]] = field(default_factory=list)


@pytest.fixture(autouse=True)
def sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The clients' waits, recorded and really slept (the unit tests only record them)."""
    waited: list[float] = []

    def sleep(seconds: float) -> None:
        waited.append(seconds)
        time.sleep(seconds)

    async def async_sleep(seconds: float) -> None:
        waited.append(seconds)
        await asyncio.sleep(seconds)

    monkeypatch.setattr(client_module, "_sleep", sleep)
    monkeypatch.setattr(client_module, "_async_sleep", async_sleep)
    return waited


@pytest.fixture
def scripted(align_answer) -> Iterator[Callable[..., tuple[str, Script]]]:
    """``scripted(step, ...)``: a loopback server following those steps; its URL and script."""
    servers: list[ThreadingHTTPServer] = []

    def start(*steps: tuple[int, dict[str, str]] | str, ok_body: dict | None = None):
        script = Script(list(steps), ok_body or align_answer())

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def _act(self) -> None:
                length = int(self.headers.get("Content-Length") or 0)
                self.rfile.read(length)
                index = len(script.seen)
                script.seen.append(
                    {
                        "at": time.monotonic(),
                        "method": self.command,
                        "path": self.path,
                        "headers": dict(self.headers),
                    }
                )
                step = script.steps[min(index, len(script.steps) - 1)]
                if step == RESET:
                    linger = struct.pack("ii", 1, 0)  # close with RST, not FIN
                    self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, linger)
                    self.close_connection = True
                    return
                status, headers = step
                body = script.ok_body if status < 300 else {"error": {"code": "x", "message": "no"}}
                data = json.dumps(body).encode()
                self.send_response(status)
                for name, value in {"Content-Type": "application/json", **headers}.items():
                    self.send_header(name, value)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST = do_DELETE = _act

            def log_message(self, *args: object) -> None:
                pass

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        server.daemon_threads = True
        threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}", script

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()


def call(kind: str, url: str, method: str, *args: Any, **options: Any) -> Any:
    """``method`` of a fresh sync or async client on ``url``: its result, or what it raised."""
    client_options = {
        k: options.pop(k) for k in ("retries", "backoff", "retry_budget") if k in options
    }
    if kind == "sync":
        with Client(url, **client_options) as client:
            return getattr(client, method)(*args, **options)

    async def run() -> Any:
        async with AsyncClient(url, **client_options) as client:
            return await getattr(client, method)(*args, **options)

    return asyncio.run(run())


@pytest.fixture
def cad(tmp_path: Path) -> Path:
    path = tmp_path / "stool.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return path


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_503_with_retry_after_then_502_then_success(scripted, sleeps, kind):
    url, script = scripted((503, {"Retry-After": "1"}), (502, {}), (200, {}))
    started = time.monotonic()
    result = call(kind, url, "align", CLOUD, retries=2, backoff=0.1)
    elapsed = time.monotonic() - started
    assert result.model_id == "chair_0042"
    first, second, third = (s["at"] for s in script.seen)
    assert 1.0 <= second - first < 1.5  # Retry-After: 1, times 1 to 1.2
    assert 0.05 <= third - second < 0.4  # back-off 0.1 * 2, times 0.5 to 1
    assert 1.0 <= sleeps[0] <= 1.2 and 0.1 <= sleeps[1] <= 0.2, sleeps
    assert elapsed < 2.0


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_a_reset_connection_and_a_504_are_retried(scripted, kind):
    url, script = scripted(RESET, (504, {}), (200, {}))
    assert call(kind, url, "align", CLOUD, retries=2, backoff=0.05).model_id == "chair_0042"
    assert [s["path"].split("?")[0] for s in script.seen] == ["/register"] * 3


@pytest.mark.parametrize(
    ("status", "error"),
    [
        (400, InvalidInputError),
        (404, NotFoundError),
        (409, ConflictError),
        (422, InvalidInputError),
    ],
)
def test_a_4xx_is_never_retried(scripted, sleeps, status, error):
    url, script = scripted((status, {"Retry-After": "0"}), (200, {}))
    with pytest.raises(error):
        call("sync", url, "align", CLOUD, retries=3, backoff=0.01)
    assert len(script.seen) == 1 and sleeps == []


@pytest.mark.parametrize("kind", ["sync", "async"])
@pytest.mark.parametrize(
    ("step", "error"),
    [
        ((503, {"Retry-After": "0"}), ServiceUnavailableError),
        ((502, {}), ServerError),
        (RESET, TransportError),
    ],
)
def test_post_models_without_a_key_is_never_retried(scripted, cad, sleeps, kind, step, error):
    url, script = scripted(step, (201, {}))
    with pytest.raises(error):
        call(kind, url, "add_model", cad, retries=3, backoff=0.01)
    assert len(script.seen) == 1 and sleeps == []
    assert "Idempotency-Key" not in script.seen[0]["headers"]


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_a_keyed_change_is_retried_with_the_same_key(scripted, model_answer, cad, kind):
    url, script = scripted(RESET, (503, {"Retry-After": "0"}), (201, {}), ok_body=model_answer())
    added = call(kind, url, "add_model", cad, retries=2, backoff=0.01, idempotency_key=True)
    assert added.model_id == "chair_0042"
    keys = {s["headers"]["Idempotency-Key"] for s in script.seen}
    assert len(script.seen) == 3 and len(keys) == 1
    removed_body = {"removed": "stool", "count": 2}
    url, script = scripted((502, {}), (200, {}), ok_body=removed_body)
    assert call(kind, url, "remove_model", "stool", backoff=0.01, idempotency_key="rm-1") == 2
    assert [(s["method"], s["headers"]["Idempotency-Key"]) for s in script.seen] == [
        ("DELETE", "rm-1"),
        ("DELETE", "rm-1"),
    ]


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_the_retry_budget_bounds_the_whole_call(scripted, sleeps, kind):
    """A server that stays unavailable: with 10 retries allowed but a 1.5 s budget, the call
    gives up once the next wait would end past 1.5 s from its start."""
    url, script = scripted((503, {"Retry-After": "1"}))
    started = time.monotonic()
    with pytest.raises(ServiceUnavailableError):
        call(kind, url, "align", CLOUD, retries=10, backoff=0.01, retry_budget=1.5)
    elapsed = time.monotonic() - started
    assert len(script.seen) == 2 and len(sleeps) == 1  # the second wait would end at 2 s or more
    assert script.seen[-1]["at"] - started <= 1.5
    assert elapsed < 1.5 + 0.5


def test_backoff_doubles_with_jitter_and_ends_in_the_last_answer(scripted, sleeps):
    url, script = scripted((503, {}))
    with pytest.raises(ServiceUnavailableError):
        call("sync", url, "models", retries=3, backoff=0.05)
    assert len(script.seen) == 4 and len(sleeps) == 3
    assert all(0.5 <= w / (0.05 * 2**n) <= 1.0 for n, w in enumerate(sleeps)), sleeps
