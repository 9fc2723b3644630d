"""Every error the SDK raises on purpose, and the one place HTTP answers become exceptions.

A robot's control loop needs to tell "my input was bad" (do not retry, fix the points) from "the
service is busy or unreachable" (wait and retry) from "the library lacks that model" without
parsing strings, so each server error code maps onto a class, and every class carries what a log
line needs: the HTTP status, the server's error code and message, and the request id that finds
the server's own log entry. The tree mirrors the server's error hierarchy::

    CatalignError                    base of everything raised on purpose
    ├── InvalidPointsError           points refused before sending (also a ValueError)
    ├── TransportError               connection refused or reset, DNS, timeouts
    ├── DecodingError                a success answer that does not match the contract
    └── APIError                     the server answered with an error status
        ├── InvalidInputError        400/422 invalid_input, invalid_file
        │   └── DegenerateInputError   422 degenerate_input (too few points, a line, a plane)
        ├── AuthenticationError      401 unauthorized (missing or wrong X-API-Key)
        ├── PermissionDeniedError    403 read_only
        ├── NotFoundError            404 model_not_found
        ├── ConflictError            409 model_exists
        ├── PayloadTooLargeError     413 payload_too_large
        └── ServerError              5xx internal
            └── ServiceUnavailableError  503 busy / starting (carries retry_after)
"""

from __future__ import annotations

import email.utils
import time
from typing import Any

import httpx

_MAX_BODY_IN_MESSAGE = 200


class CatalignError(Exception):
    """Base of every error the SDK raises on purpose."""


class InvalidPointsError(CatalignError, ValueError):
    """The points are not an (N, 3) array of finite numbers; nothing was sent."""


class TransportError(CatalignError):
    """The request did not get an HTTP answer: no connection, a reset, or a timeout."""


class DecodingError(CatalignError):
    """A success answer whose body does not follow the HTTP contract."""


class APIError(CatalignError):
    """The server answered with an error status.

    Parameters:
        status_code: the HTTP status, e.g. 422.
        code: the server's error code, e.g. ``"invalid_input"``; ``None`` when the body was not
            the server's JSON error (a proxy's HTML page, say).
        message: what was wrong, in the server's words (or the start of the body).
        request_id: the id the server logged the request under, when it sent one.
        response: the raw :class:`httpx.Response`, for anything else.
    """

    def __init__(
        self,
        status_code: int,
        code: str | None,
        message: str,
        *,
        request_id: str | None = None,
        response: httpx.Response | None = None,
    ) -> None:
        self.status_code = status_code
        self.code = code
        self.message = message
        self.request_id = request_id
        self.response = response
        super().__init__(self.__str__())

    def __str__(self) -> str:
        head = f"{self.status_code} {self.code}" if self.code else str(self.status_code)
        tail = f" (request id {self.request_id})" if self.request_id else ""
        return f"{head}: {self.message}{tail}"

    def __reduce__(self) -> tuple[Any, ...]:
        # Keyword-only arguments do not survive the default pickling of exceptions.
        return (_rebuild, (type(self), self.status_code, self.code, self.message, self.request_id))


def _rebuild(
    cls: type[APIError], status_code: int, code: str | None, message: str, request_id: str | None
) -> APIError:
    return cls(status_code, code, message, request_id=request_id)


class InvalidInputError(APIError):
    """The server refused the points, the file or an option (400/422)."""


class DegenerateInputError(InvalidInputError):
    """The points are valid but cannot be registered: too few, collinear or planar (422)."""


class AuthenticationError(APIError):
    """The API key is missing or wrong (401)."""


class PermissionDeniedError(APIError):
    """The server refuses this operation, e.g. library changes on a read-only server (403)."""


class NotFoundError(APIError):
    """No library model has that id (404)."""


class ConflictError(APIError):
    """A library model with that id already exists (409)."""


class PayloadTooLargeError(APIError):
    """The points or the file exceed the server's size limit (413)."""


class ServerError(APIError):
    """The server failed (5xx); the request itself may have been fine."""


class ServiceUnavailableError(ServerError):
    """The server is busy or still starting (503); ``retry_after`` is its hint in seconds."""

    @property
    def retry_after(self) -> float | None:
        return retry_after_seconds(self.response) if self.response is not None else None


_BY_STATUS: dict[int, type[APIError]] = {
    400: InvalidInputError,
    401: AuthenticationError,
    403: PermissionDeniedError,
    404: NotFoundError,
    409: ConflictError,
    413: PayloadTooLargeError,
    422: InvalidInputError,
    503: ServiceUnavailableError,
}
_BY_CODE: dict[str, type[APIError]] = {"degenerate_input": DegenerateInputError}


def error_from_response(response: httpx.Response) -> APIError:
    """The typed exception for an error answer, whatever its body looks like."""
    code, message, request_id = _parse_error_body(response)
    request_id = request_id or response.headers.get("x-request-id")
    cls = _BY_CODE.get(code or "") or _BY_STATUS.get(response.status_code)
    if cls is None:
        cls = ServerError if response.status_code >= 500 else APIError
    return cls(response.status_code, code, message, request_id=request_id, response=response)


def _parse_error_body(response: httpx.Response) -> tuple[str | None, str, str | None]:
    """``(code, message, request_id)`` from the contract's JSON error, FastAPI's default
    ``{"detail": ...}``, or any other body."""
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict):
        request_id = body.get("request_id")
        request_id = str(request_id) if request_id is not None else None
        error = body.get("error")
        if isinstance(error, dict) and "message" in error:
            code = error.get("code")
            return (str(code) if code is not None else None), str(error["message"]), request_id
        if "detail" in body:
            return None, _detail_message(body["detail"]), request_id
    text = " ".join(response.text.split())[:_MAX_BODY_IN_MESSAGE]
    return None, text or response.reason_phrase or "no message", None


def _detail_message(detail: Any) -> str:
    """FastAPI's validation detail (a list of ``{"loc", "msg"}``) in one line."""
    if isinstance(detail, list):
        parts = []
        for item in detail:
            if isinstance(item, dict):
                where = ".".join(str(p) for p in item.get("loc", ()))
                parts.append(f"{where}: {item.get('msg', item)}" if where else str(item.get("msg")))
            else:
                parts.append(str(item))
        return "; ".join(parts)
    return str(detail)


def retry_after_seconds(response: httpx.Response) -> float | None:
    """The ``Retry-After`` header in seconds (delta-seconds or an HTTP date), if usable."""
    value = response.headers.get("retry-after")
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError):
            return None
        seconds = when.timestamp() - time.time()
    if seconds != seconds:  # NaN
        return None
    return max(seconds, 0.0)
