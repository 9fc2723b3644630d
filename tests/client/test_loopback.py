"""Both clients over real sockets against a stdlib HTTP server on loopback: what MockTransport
cannot show (headers and bodies as sent on the wire, a refused connection)."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from catalign_client import AsyncClient, Client, NotFoundError, TransportError


@pytest.fixture
def loopback(align_answer) -> Iterator[tuple[str, list[dict]]]:
    seen: list[dict] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["Content-Length"]))
            seen.append({"path": self.path, "headers": dict(self.headers), "body": body})
            self._answer(200, align_answer())

        def do_GET(self) -> None:
            error = {"error": {"code": "model_not_found", "message": "no x"}, "request_id": "r"}
            self._answer(404, error)

        def _answer(self, status: int, body: dict) -> None:
            data = json.dumps(body).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", seen
    server.shutdown()
    server.server_close()


def test_sync_and_async_send_the_same_bytes(loopback):
    url, seen = loopback
    points = np.random.default_rng(0).normal(size=(100, 3))
    with Client(url, api_key="k") as client:
        assert client.align(points, seed=1).pose.shape == (4, 4)
        with pytest.raises(NotFoundError):
            client.model("x")

    async def use() -> None:
        async with AsyncClient(url, api_key="k") as client:
            await client.align(points, seed=1)

    asyncio.run(use())
    sync, asynchronous = seen
    assert sync["path"] == asynchronous["path"] == "/register?estimate_scale=false&seed=1"
    assert sync["body"] == asynchronous["body"] == points.astype("<f4").tobytes()
    assert sync["headers"]["X-API-Key"] == asynchronous["headers"]["X-API-Key"] == "k"


def test_refused_connection_is_a_transport_error(sleeps):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]  # closed again before the client connects
    with Client(f"http://127.0.0.1:{port}", retries=1) as client, pytest.raises(TransportError):
        client.models()
    assert len(sleeps) == 1
