"""Fixtures for the SDK's unit tests: canned answers, instant back-off, and one facade that runs
every behaviour test against both :class:`Client` and :class:`AsyncClient`."""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest

from catalign_client import AsyncClient, Client
from catalign_client import _client as client_module

Handler = Callable[[httpx.Request], httpx.Response]


def _align_answer(**overrides: Any) -> dict[str, Any]:
    """A contract-shaped ``POST /register`` answer."""
    answer: dict[str, Any] = {
        "model_id": "chair_0042",
        "category": "chair",
        "symmetry": {"order": 1, "yaws_deg": [0.0]},
        "category_confidence": 0.97,
        "pose": [[0.0, -2.0, 0.0, 0.5], [2.0, 0.0, 0.0, -0.25], [0.0, 0.0, 2.0, 1.0], [0, 0, 0, 1]],
        "scale": 2.0,
        "fitness": 0.91,
        "inlier_rmse": 0.012,
        "num_inliers": 812,
        "inlier_ratio": 0.64,
        "points_set_aside": 3,
        "up": [0.0, 0.0, 1.0],
        "up_estimated": False,
        "confidence": 0.87,
        "accepted": True,
        "reason": None,
        "alternatives": [
            {
                "model_id": "c7",
                "pose": [[-1.0, 0, 0, 0.5], [0, -1.0, 0, -0.25], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0]],
                "scale": 1.0,
                "score": 0.4,
                "fitness": 0.55,
                "confidence": 0.06,
            }
        ],
        "candidates": [{"model_id": "chair_0042", "score": 0.91}, {"model_id": "c7", "score": 0.4}],
        "timings_ms": {"features": 41.5, "ransac": 12.0},
        "request_id": "req-123",
    }
    answer.update(overrides)
    return answer


def _model_answer(model_id: str = "chair_0042") -> dict[str, Any]:
    """A contract-shaped library model."""
    return {
        "model_id": model_id,
        "source": f"/library/{model_id}.obj",
        "units": "m",
        "num_points": 2048,
        "bbox_min": [-0.25, 0.0, -0.25],
        "bbox_max": [0.25, 0.9, 0.25],
        "size": [0.5, 0.9, 0.5],
        "category": "chair",
        "symmetry": {"order": 2, "yaws_deg": [0.0, 180.0]},
    }


def _error_answer(
    status: int, code: str, message: str, request_id: str = "req-err"
) -> httpx.Response:
    body = {"error": {"code": code, "message": message}, "request_id": request_id}
    return httpx.Response(status, json=body)


class Facade:
    """Calls a client's methods synchronously, whichever client it is, and records requests."""

    def __init__(self, client: Client | AsyncClient, requests: list[httpx.Request]) -> None:
        self.client = client
        self.requests = requests

    def __getattr__(self, name: str) -> Callable[..., Any]:
        method = getattr(self.client, name)
        if not inspect.iscoroutinefunction(method):
            return method
        return lambda *args, **kwargs: asyncio.run(method(*args, **kwargs))

    def close(self) -> None:
        if isinstance(self.client, AsyncClient):
            asyncio.run(self.client.aclose())
        else:
            self.client.close()


@pytest.fixture(params=["sync", "async"])
def make_api(request: pytest.FixtureRequest) -> Iterator[Callable[..., Facade]]:
    """``make_api(handler, **client_options)``: a :class:`Facade` over a mock-backed client."""
    made: list[Facade] = []

    def make(handler: Handler, **options: Any) -> Facade:
        requests: list[httpx.Request] = []

        def recording(http_request: httpx.Request) -> httpx.Response:
            http_request.read()
            requests.append(http_request)
            return handler(http_request)

        options.setdefault("base_url", "http://catalign.test")
        cls = Client if request.param == "sync" else AsyncClient
        facade = Facade(cls(transport=httpx.MockTransport(recording), **options), requests)
        made.append(facade)
        return facade

    yield make
    for facade in made:
        facade.close()


@pytest.fixture(autouse=True)
def sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """Back-off waits, recorded instead of slept (for both clients)."""
    waited: list[float] = []

    async def async_sleep(seconds: float) -> None:
        waited.append(seconds)

    monkeypatch.setattr(client_module, "_sleep", waited.append)
    monkeypatch.setattr(client_module, "_async_sleep", async_sleep)
    return waited


@pytest.fixture
def align_answer() -> Callable[..., dict[str, Any]]:
    return _align_answer


@pytest.fixture
def model_answer() -> Callable[..., dict[str, Any]]:
    return _model_answer


@pytest.fixture
def error_answer() -> Callable[..., httpx.Response]:
    return _error_answer
