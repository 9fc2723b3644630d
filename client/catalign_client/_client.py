"""The synchronous and asynchronous clients, sharing everything that does no I/O.

A robot's control loop is usually synchronous, a fleet gateway usually asyncio, and both must
behave identically: same validation, same encoding, same retries, same errors. So
:class:`_BaseClient` builds every request as plain data (:class:`Request`), decides whether and
how long to wait before a retry (:class:`~catalign_client._retry.RetryPolicy`), and parses every
answer; :class:`Client` and :class:`AsyncClient` only send requests and sleep, each in its own
way. Retries cover what is transient (no connection, a dropped one, a timeout, 502, 503, 504)
for requests that are safe to send twice; a 4xx is the caller's to fix and never retried.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterator, Mapping
from pathlib import Path
from typing import Any, Self
from urllib.parse import quote

import httpx
import numpy as np

from ._exceptions import DecodingError, TransportError, error_from_response
from ._models import AlignResult, ModelInfo, parse_models, parse_removed_count
from ._points import PointsLike, as_points, encode_binary, encode_json
from ._requests import (
    Encoding,
    IdempotencyKey,
    Request,
    UpLike,
    idempotency_headers,
    model_points_params,
    query,
    registration_options,
    up_vector,
    upload,
)
from ._retry import DEFAULT_RETRY_BUDGET, RetryPolicy
from ._version import __version__

# Indirections so tests can make back-off instant.
_sleep = time.sleep
_async_sleep = asyncio.sleep


class _BaseClient:
    """Options, request building, retry policy and answer parsing; no I/O."""

    def __init__(
        self,
        base_url: str,
        *,
        api_key: str | None,
        retry: RetryPolicy,
    ) -> None:
        self._base_url = base_url
        self._api_key = api_key
        self._retry = retry

    @property
    def base_url(self) -> str:
        return self._base_url

    def __repr__(self) -> str:
        return f"{type(self).__name__}(base_url={self._base_url!r})"

    def _headers(self) -> dict[str, str]:
        headers = {"User-Agent": f"catalign-client/{__version__}", "Accept": "application/json"}
        if self._api_key is not None:
            headers["X-API-Key"] = self._api_key
        return headers

    # Requests -----------------------------------------------------------------------------------

    def _align_request(
        self,
        points: PointsLike,
        *,
        top_k: int | None,
        up: UpLike | None,
        estimate_scale: bool,
        seed: int | None,
        category: str | None,
        min_confidence: float | None,
        encoding: Encoding,
    ) -> Request:
        cloud = as_points(points)
        options = registration_options(
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
        )
        if encoding == "binary":
            return Request(
                "POST",
                "/register",
                params=query(options),
                content=encode_binary(cloud),
                headers={"Content-Type": "application/octet-stream"},
            )
        if encoding == "json":
            return Request("POST", "/register", json={"points": encode_json(cloud), **options})
        raise ValueError(f"encoding must be 'binary' or 'json', got {encoding!r}")

    def _align_file_request(
        self,
        path: str | Path,
        *,
        top_k: int | None,
        up: UpLike | None,
        estimate_scale: bool,
        seed: int | None,
        category: str | None,
        min_confidence: float | None,
    ) -> Request:
        options = registration_options(
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
        )
        return Request("POST", "/register", params=query(options), files=upload(path))

    def _add_model_request(
        self,
        path: str | Path,
        model_id: str | None,
        units: str | None,
        category: str | None,
        idempotency_key: IdempotencyKey,
    ) -> Request:
        fields = {"model_id": model_id, "units": units, "category": category}
        data = {name: value for name, value in fields.items() if value is not None}
        headers = idempotency_headers(idempotency_key)
        return Request(
            "POST",
            "/models",
            files=upload(path),
            data=data or None,
            headers=headers,
            idempotent=headers is not None,  # resent only when the server answers a key once
        )

    def _remove_model_request(self, model_id: str, idempotency_key: IdempotencyKey) -> Request:
        headers = idempotency_headers(idempotency_key)
        path = self._model_path(model_id)
        return Request("DELETE", path, headers=headers, idempotent=headers is not None)

    @staticmethod
    def _models_request(category: str | None, page_size: int, cursor: str | None) -> Request:
        if isinstance(page_size, bool) or not isinstance(page_size, int) or page_size < 1:
            raise ValueError(f"page_size must be a positive integer, got {page_size!r}")
        fields = {"category": category, "limit": page_size, "cursor": cursor}
        params = {name: value for name, value in fields.items() if value is not None}
        return Request("GET", "/models", params=params)

    def _model_points_request(self, model_id: str, *, max_points: int) -> Request:
        return Request(
            "GET",
            self._model_path(model_id) + "/points",
            params=model_points_params(max_points),
            headers={"Accept": "application/octet-stream, application/json"},
        )

    @staticmethod
    def _model_path(model_id: str) -> str:
        if not isinstance(model_id, str) or not model_id:
            raise ValueError(f"model_id must be a non-empty string, got {model_id!r}")
        return "/models/" + quote(model_id, safe="")

    def _transport_error(
        self, request: Request, error: httpx.TransportError, attempts: int
    ) -> TransportError:
        return TransportError(
            f"{request.method} {self._base_url.rstrip('/')}{request.path} failed after "
            f"{attempts} attempt(s): {type(error).__name__}: {str(error) or 'no detail'}"
        )

    # Answers ------------------------------------------------------------------------------------

    @staticmethod
    def _json(response: httpx.Response) -> Any:
        """The decoded body of a success answer; the typed error of any other."""
        if not response.is_success:
            raise error_from_response(response)
        try:
            return response.json()
        except ValueError as exc:
            raise DecodingError(
                f"{response.request.method} {response.request.url.path}: answer is not JSON "
                f"({response.headers.get('content-type', 'no content type')})"
            ) from exc

    @staticmethod
    def _result(body: Any, up: UpLike | None) -> AlignResult:
        """The typed answer of ``POST /register``, remembering the ``up`` that was asked for."""
        if up is None:
            return AlignResult.from_json(body)
        x, y, z = up_vector(up)
        return AlignResult.from_json(body, up=(x, y, z))

    @staticmethod
    def _points(response: httpx.Response) -> np.ndarray:
        """An (N, 3) float64 array from a raw little-endian float32 answer; errors raise."""
        if not response.is_success:
            raise error_from_response(response)
        where = f"{response.request.method} {response.request.url.path}"
        body = response.content
        if len(body) % 12:
            raise DecodingError(f"{where}: {len(body)} bytes are not whole float32 x y z triples")
        count = len(body) // 12
        declared = response.headers.get("x-point-count")
        if declared is not None and declared.strip() != str(count):
            raise DecodingError(f"{where}: X-Point-Count says {declared}, the body holds {count}")
        return np.frombuffer(body, dtype="<f4").reshape(count, 3).astype(np.float64)

    @classmethod
    def _ready(cls, response: httpx.Response) -> bool:
        """``True`` when ready, ``False`` on 503 (starting or busy); other errors raise."""
        if response.status_code == 503:
            return False
        body = cls._json(response)
        return isinstance(body, Mapping) and body.get("status") == "ready"

    @classmethod
    def _info(cls, response: httpx.Response) -> dict[str, Any]:
        body = cls._json(response)
        if not isinstance(body, dict):
            raise DecodingError(f"GET /info: expected a JSON object, got {type(body).__name__}")
        return body


class Client(_BaseClient):
    """A synchronous client of the catalign registration service.

    Usage::

        with Client("http://localhost:8000", api_key="secret") as client:
            result = client.align(points, up=(0, 0, 1), seed=0)
            print(result.model_id, result.fitness)
            pose = result.pose  # numpy (4, 4): x_obs = R @ x_model + t

    Parameters:
        base_url: the server's root URL, e.g. ``"http://10.0.0.5:8000"``.
        api_key: sent as the ``X-API-Key`` header when given.
        timeout: seconds per attempt (or an :class:`httpx.Timeout`); ``None`` waits forever.
        retries: how many times to resend a request that is safe to send twice (a registration,
            a read, a library change with an ``idempotency_key``) after a transport error
            (refused, reset or dropped connection, timeout) or a 502, 503 or 504; a 4xx or a
            500 is never resent, nor a library change without a key once it may have reached
            the server.
        backoff: first wait in seconds; it doubles per retry, times a random 0.5 to 1; a
            ``Retry-After`` header replaces it (times 1 to 1.2); no wait exceeds
            ``MAX_RETRY_DELAY`` (10 s).
        retry_budget: no attempt starts later than this many seconds after the first one
            started (30 s), so a call lasts at most ``retry_budget`` plus one attempt.
        transport: an :class:`httpx.BaseTransport`, e.g. :class:`httpx.MockTransport` in tests.
    """

    def __init__(
        self,
        base_url: str,
        *,
        api_key: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 2,
        backoff: float = 0.2,
        retry_budget: float = DEFAULT_RETRY_BUDGET,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        retry = RetryPolicy(retries, backoff, retry_budget)
        super().__init__(base_url, api_key=api_key, retry=retry)
        self._http = httpx.Client(
            base_url=base_url, headers=self._headers(), timeout=timeout, transport=transport
        )

    def align(
        self,
        points: PointsLike,
        *,
        top_k: int | None = None,
        up: UpLike | None = None,
        estimate_scale: bool = False,
        seed: int | None = None,
        category: str | None = None,
        min_confidence: float | None = None,
        encoding: Encoding = "binary",
    ) -> AlignResult:
        """Find the library model that best explains ``points`` and its pose.

        ``points``: an (N, 3) array-like, nested lists, an object with ``.points`` (Open3D)
        or ``.vertices`` (trimesh), or a ROS ``sensor_msgs/msg/PointCloud2`` message (its finite
        x, y, z; NaN returns dropped). ``top_k``: how many shortlisted models to register (server
        default when ``None``). ``up``: the observation's up direction, e.g. ``(0, 0, 1)``.
        ``estimate_scale``: also fit a uniform scale (0.5 to 2). ``seed``: for a reproducible
        answer. ``category``: search only that category's models (e.g. ``"table"``, as the
        robot's detector labels the object; an unknown one raises :class:`InvalidInputError`
        listing the library's); the result's ``category`` says which the answer is.
        ``min_confidence``: a probability in [0, 1] the answer needs to be accepted; below it
        the result still has the pose, with ``accepted`` ``False`` and a ``reason`` (not an
        error: the caller decides, e.g. to look from another side).
        ``encoding``: ``"binary"`` (float32, compact) or ``"json"``.
        """
        request = self._align_request(
            points,
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
            encoding=encoding,
        )
        return self._result(self._call(request), up)

    def align_file(
        self,
        path: str | Path,
        *,
        top_k: int | None = None,
        up: UpLike | None = None,
        estimate_scale: bool = False,
        seed: int | None = None,
        category: str | None = None,
        min_confidence: float | None = None,
    ) -> AlignResult:
        """Like :meth:`align`, uploading a ``.ply/.pcd/.npy/.xyz`` file for the server to read."""
        request = self._align_file_request(
            path,
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
        )
        return self._result(self._call(request), up)

    def models(self, *, category: str | None = None, page_size: int = 1000) -> list[ModelInfo]:
        """Every model of the server's library, or only those of ``category``, sorted by id
        (fetched ``page_size`` at a time; see :meth:`iter_models` to handle them as they come)."""
        return list(self.iter_models(category=category, page_size=page_size))

    def iter_models(
        self, *, category: str | None = None, page_size: int = 1000
    ) -> Iterator[ModelInfo]:
        """The library's models one by one, fetching the next page of ``page_size`` when one is
        used up: a library of 100,000 models never sits in memory at once. A model added or
        removed meanwhile moves no other: none is given twice, none that stayed is missed."""
        cursor: str | None = None
        while True:
            page, cursor = parse_models(
                self._call(self._models_request(category, page_size, cursor))
            )
            yield from page
            if cursor is None:
                return

    def model(self, model_id: str) -> ModelInfo:
        """One library model; :class:`NotFoundError` when there is none with that id."""
        return ModelInfo.from_json(self._call(Request("GET", self._model_path(model_id))))

    def model_points(self, model_id: str, *, max_points: int = 5000) -> np.ndarray:
        """A library model's surface points, in model coordinates, as an (N, 3) float64 array.

        The server thins them evenly to at most ``max_points`` (1 to 20,000); move them into the
        observation with an :class:`AlignResult`'s pose, or hand them to
        :meth:`AlignResult.plot`. :class:`NotFoundError` when there is no model with that id.

        Usage::

            result = client.align(points, up=(0, 0, 1))
            model = client.model_points(result.model_id, max_points=2000)
            in_view = model @ result.pose[:3, :3].T + result.pose[:3, 3]
        """
        return self._points(self._send(self._model_points_request(model_id, max_points=max_points)))

    def add_model(
        self,
        path: str | Path,
        *,
        model_id: str | None = None,
        units: str | None = None,
        category: str | None = None,
        idempotency_key: IdempotencyKey = None,
    ) -> ModelInfo:
        """Upload a CAD file (mesh or point cloud) into the library; the id defaults to its stem,
        the category to ``chair``.

        ``idempotency_key``: a string (1 to 255 visible ASCII characters, e.g. a UUID) sent as
        the ``Idempotency-Key`` header, or ``True`` for a fresh UUID. With one, the server adds
        the model once and answers a repeat of the request with its first answer, so the call
        is retried like a registration; without one it is never resent once it may have reached
        the server. Reuse your own key to repeat the call yourself safely, e.g. after a
        :class:`TransportError`; the same key with another file or other fields is refused
        (:class:`InvalidInputError`, ``idempotency_key_reused``).
        """
        request = self._add_model_request(path, model_id, units, category, idempotency_key)
        return ModelInfo.from_json(self._call(request))

    def remove_model(self, model_id: str, *, idempotency_key: IdempotencyKey = None) -> int:
        """Remove a model from the library; returns how many models remain.
        ``idempotency_key``: as for :meth:`add_model` (a repeat answers the first count)."""
        request = self._remove_model_request(model_id, idempotency_key)
        return parse_removed_count(self._call(request))

    def health(self) -> bool:
        """Whether the server is ready to register (no retries: it answers for now)."""
        return self._ready(self._send(Request("GET", "/health/ready", retry=False)))

    def info(self) -> dict[str, Any]:
        """What the server says about itself (versions, library, settings)."""
        return self._info(self._send(Request("GET", "/info")))

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    @property
    def is_closed(self) -> bool:
        return self._http.is_closed

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _call(self, request: Request) -> Any:
        return self._json(self._send(request))

    def _send(self, request: Request) -> httpx.Response:
        attempt, started = 0, time.monotonic()
        while True:
            try:
                response = self._http.request(request.method, request.path, **request.arguments())
            except httpx.TransportError as exc:
                delay = self._retry.delay(request, attempt, time.monotonic() - started, error=exc)
                if delay is None:
                    raise self._transport_error(request, exc, attempt + 1) from exc
            else:
                delay = self._retry.delay(
                    request, attempt, time.monotonic() - started, response=response
                )
                if delay is None:
                    return response
            _sleep(delay)
            attempt += 1


class AsyncClient(_BaseClient):
    """An asyncio client of the catalign registration service, mirroring :class:`Client`.

    Usage::

        async with AsyncClient("http://localhost:8000") as client:
            result = await client.align(points, seed=0)
            pose = result.pose

    Parameters:
        base_url, api_key, timeout, retries, backoff, retry_budget: as for :class:`Client`.
        transport: an :class:`httpx.AsyncBaseTransport`, e.g. :class:`httpx.MockTransport`.
    """

    def __init__(
        self,
        base_url: str,
        *,
        api_key: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 2,
        backoff: float = 0.2,
        retry_budget: float = DEFAULT_RETRY_BUDGET,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        retry = RetryPolicy(retries, backoff, retry_budget)
        super().__init__(base_url, api_key=api_key, retry=retry)
        self._http = httpx.AsyncClient(
            base_url=base_url, headers=self._headers(), timeout=timeout, transport=transport
        )

    async def align(
        self,
        points: PointsLike,
        *,
        top_k: int | None = None,
        up: UpLike | None = None,
        estimate_scale: bool = False,
        seed: int | None = None,
        category: str | None = None,
        min_confidence: float | None = None,
        encoding: Encoding = "binary",
    ) -> AlignResult:
        """See :meth:`Client.align`."""
        request = self._align_request(
            points,
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
            encoding=encoding,
        )
        return self._result(await self._call(request), up)

    async def align_file(
        self,
        path: str | Path,
        *,
        top_k: int | None = None,
        up: UpLike | None = None,
        estimate_scale: bool = False,
        seed: int | None = None,
        category: str | None = None,
        min_confidence: float | None = None,
    ) -> AlignResult:
        """See :meth:`Client.align_file`."""
        request = self._align_file_request(
            path,
            top_k=top_k,
            up=up,
            estimate_scale=estimate_scale,
            seed=seed,
            category=category,
            min_confidence=min_confidence,
        )
        return self._result(await self._call(request), up)

    async def models(
        self, *, category: str | None = None, page_size: int = 1000
    ) -> list[ModelInfo]:
        """See :meth:`Client.models`."""
        return [m async for m in self.iter_models(category=category, page_size=page_size)]

    async def iter_models(
        self, *, category: str | None = None, page_size: int = 1000
    ) -> AsyncIterator[ModelInfo]:
        """See :meth:`Client.iter_models`."""
        cursor: str | None = None
        while True:
            request = self._models_request(category, page_size, cursor)
            page, cursor = parse_models(await self._call(request))
            for model in page:
                yield model
            if cursor is None:
                return

    async def model(self, model_id: str) -> ModelInfo:
        """See :meth:`Client.model`."""
        return ModelInfo.from_json(await self._call(Request("GET", self._model_path(model_id))))

    async def model_points(self, model_id: str, *, max_points: int = 5000) -> np.ndarray:
        """See :meth:`Client.model_points`."""
        request = self._model_points_request(model_id, max_points=max_points)
        return self._points(await self._send(request))

    async def add_model(
        self,
        path: str | Path,
        *,
        model_id: str | None = None,
        units: str | None = None,
        category: str | None = None,
        idempotency_key: IdempotencyKey = None,
    ) -> ModelInfo:
        """See :meth:`Client.add_model`."""
        request = self._add_model_request(path, model_id, units, category, idempotency_key)
        return ModelInfo.from_json(await self._call(request))

    async def remove_model(self, model_id: str, *, idempotency_key: IdempotencyKey = None) -> int:
        """See :meth:`Client.remove_model`."""
        request = self._remove_model_request(model_id, idempotency_key)
        return parse_removed_count(await self._call(request))

    async def health(self) -> bool:
        """See :meth:`Client.health`."""
        return self._ready(await self._send(Request("GET", "/health/ready", retry=False)))

    async def info(self) -> dict[str, Any]:
        """See :meth:`Client.info`."""
        return self._info(await self._send(Request("GET", "/info")))

    async def aclose(self) -> None:
        """Close the connection pool."""
        await self._http.aclose()

    @property
    def is_closed(self) -> bool:
        return self._http.is_closed

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.aclose()

    async def _call(self, request: Request) -> Any:
        return self._json(await self._send(request))

    async def _send(self, request: Request) -> httpx.Response:
        attempt, started = 0, time.monotonic()
        while True:
            try:
                response = await self._http.request(
                    request.method, request.path, **request.arguments()
                )
            except httpx.TransportError as exc:
                delay = self._retry.delay(request, attempt, time.monotonic() - started, error=exc)
                if delay is None:
                    raise self._transport_error(request, exc, attempt + 1) from exc
            else:
                delay = self._retry.delay(
                    request, attempt, time.monotonic() - started, response=response
                )
                if delay is None:
                    return response
            await _async_sleep(delay)
            attempt += 1
