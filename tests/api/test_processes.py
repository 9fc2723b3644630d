"""Worker processes: each worker its own engine in a process of its own, behind the same pool."""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np

from catalign.data.shapes import procedural_shape
from catalign_client import Client

if TYPE_CHECKING:
    from tests.api.conftest import View

BINARY = {"content-type": "application/octet-stream"}
FAST = {"top_k": 1, "seed": 3, "up": "0,0,1"}


def _engines() -> list[multiprocessing.Process]:
    return [p for p in multiprocessing.active_children() if p.name == "catalign-engine"]


def _register(http: httpx.Client, view: View) -> httpx.Response:
    return http.post("/register", params=FAST, content=view.points.tobytes(), headers=BINARY)


def test_each_worker_runs_in_its_own_process_and_stops_with_the_server(
    serve: Callable, library_dir: Path, views: Callable[..., View]
) -> None:
    view = views(seed=1)
    with serve(library=library_dir, workers=2) as server:
        engines = _engines()
        assert len(engines) == 2
        assert all(p.pid != os.getpid() and p.is_alive() for p in engines)
        result = Client(server.url).align(view.points, up=(0, 0, 1), top_k=1, seed=3)
        assert result.model_id == "proc-0001"
    assert not _engines()


def test_threads_share_the_servers_engine_when_asked(
    serve: Callable, library_dir: Path, views: Callable[..., View]
) -> None:
    view = views(seed=1)
    with serve(library=library_dir, workers=2, worker_processes=False) as server:
        assert not _engines()
        result = Client(server.url).align(view.points, up=(0, 0, 1), top_k=1, seed=3)
        assert result.model_id == "proc-0001"


def test_a_killed_worker_process_costs_one_request_and_is_replaced(
    serve: Callable, library_dir: Path, views: Callable[..., View]
) -> None:
    view = views(seed=1)
    with (
        serve(library=library_dir, workers=1) as server,
        httpx.Client(base_url=server.url, timeout=120) as http,
    ):
        (engine,) = _engines()
        os.kill(engine.pid, signal.SIGKILL)
        engine.join(timeout=10)
        first = _register(http, view)
        assert first.status_code == 503
        assert "worker" in first.json()["error"]["message"]
        assert first.headers["retry-after"] == "1"
        (replacement,) = _engines()
        assert replacement.pid != engine.pid
        second = _register(http, view)
        assert second.status_code == 200, second.text
        assert second.json()["model_id"] == "proc-0001"


def test_a_library_change_reaches_every_process(
    serve: Callable, library_copy: Path, views: Callable[..., View], tmp_path: Path
) -> None:
    """A model removed, then added again under another id, through the server: what both
    workers' engines find next."""
    view = views(seed=1)
    shape = tmp_path / "chair-1.npy"
    np.save(shape, procedural_shape(1).points)
    with (
        serve(library=library_copy, workers=2) as server,
        httpx.Client(base_url=server.url, timeout=120) as http,
    ):
        assert http.delete("/models/proc-0001").status_code == 200
        without = [_register(http, view) for _ in range(2)]  # one on each worker
        assert all(a.status_code == 200 for a in without)
        assert "proc-0001" not in {a.json()["model_id"] for a in without}
        with shape.open("rb") as file:
            added = http.post("/models", data={"model_id": "again-0001"}, files={"file": file})
        assert added.status_code == 201, added.text
        answers = [_register(http, view) for _ in range(2)]
        assert all(a.status_code == 200 for a in answers)
        assert {a.json()["model_id"] for a in answers} == {"again-0001"}
