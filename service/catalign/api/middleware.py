"""What every HTTP request goes through: an id, a body limit, one log line, metrics, no leaks.

A pure ASGI middleware (not ``BaseHTTPMiddleware``) so that bodies stream through untouched.
The request id comes from a well-formed ``X-Request-ID`` header or is generated; it is stored
in ``request.state.request_id``, echoed in the response header and logged. Bodies over the limit
are refused from ``Content-Length`` before they are read, and while they are read otherwise
(chunked uploads). ``refuse_early`` may refuse a request from its method and path alone (a full
worker queue): answered here, before routing and after a short pause (:data:`REFUSAL_PAUSE_S`),
a refusal costs the event loop little, and clients that retry at once cannot make it answer
thousands a second while health checks wait behind them. An exception no handler took is a
bug: logged with its traceback and the request id, answered 500 ``internal`` without details.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
import uuid
from collections.abc import Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from catalign.api.errors import PayloadTooLargeError, error_response
from catalign.api.metrics import Metrics

logger = logging.getLogger("catalign.api.access")

REQUEST_ID_HEADER = "x-request-id"
_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")
# How long a refused registration waits for its 503. Measured with 64 clients retrying at once
# (loopback, 2 cores): /health/live p50 21-38 ms without a pause, 1.9 ms with 0.1 s, and two to
# eight times the accepted registrations; 0.25 s leaves margin. A client told to retry later
# loses nothing by the wait.
REFUSAL_PAUSE_S = 0.25


def new_request_id() -> str:
    return uuid.uuid4().hex


def valid_request_id(value: str | None) -> str:
    """The caller's id when it is safe to log and echo, else a fresh one."""
    return value if value and _REQUEST_ID.fullmatch(value) else new_request_id()


class RequestContextMiddleware:
    """Request id, body limit, access log and request metrics for every HTTP request."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        max_body_bytes: int,
        metrics: Metrics,
        refuse_early: Callable[[str, str], Exception | None] = lambda method, path: None,
    ) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.metrics = metrics
        self.refuse_early = refuse_early

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        request_id = valid_request_id(headers.get(REQUEST_ID_HEADER))
        scope.setdefault("state", {})["request_id"] = request_id
        started = time.perf_counter()
        status = 500
        response_started = False

        async def send_with_id(message: Message) -> None:
            nonlocal status, response_started
            if message["type"] == "http.response.start":
                status = message["status"]
                response_started = True
                message["headers"] = [
                    *message.get("headers", []),
                    (REQUEST_ID_HEADER.encode(), request_id.encode()),
                ]
            await send(message)

        received = 0

        async def receive_limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise self._too_large()
            return message

        try:
            declared = _content_length(headers)
            refusal = self.refuse_early(scope["method"], scope["path"])
            if refusal is not None:
                await asyncio.sleep(REFUSAL_PAUSE_S)
            elif declared is not None and declared > self.max_body_bytes:
                refusal = self._too_large(declared)
            if refusal is not None:
                await error_response(refusal, request_id)(scope, receive, send_with_id)
            else:
                await self.app(scope, receive_limited, send_with_id)
        except asyncio.CancelledError:
            status = 499  # the server is stopping; nobody will read an answer
            raise
        except Exception as error:
            if isinstance(error, PayloadTooLargeError):
                logger.info("request_id=%s %s", request_id, error)
            else:
                logger.exception("request_id=%s unhandled error", request_id)
            if not response_started:
                await error_response(error, request_id)(scope, receive, send_with_id)
        finally:
            elapsed = time.perf_counter() - started
            route = _route_of(scope)
            self.metrics.observe_request(scope["method"], route, status, elapsed)
            logger.info(
                "request_id=%s method=%s route=%s status=%d ms=%.1f",
                request_id,
                scope["method"],
                route,
                status,
                elapsed * 1e3,
            )

    def _too_large(self, size: int | None = None) -> PayloadTooLargeError:
        what = f"{size} bytes" if size is not None else "more bytes than allowed"
        return PayloadTooLargeError(
            f"the request body has {what}; the limit is {self.max_body_bytes} bytes "
            "(CATALIGN_MAX_BODY_BYTES)"
        )


def _content_length(headers: dict[str, str]) -> int | None:
    try:
        return int(headers["content-length"])
    except (KeyError, ValueError):
        return None


def _route_of(scope: Scope) -> str:
    """The matched route's template (bounded label values), or ``unmatched``."""
    route = scope.get("route")
    path = getattr(route, "path", None)
    return path if isinstance(path, str) else "unmatched"
