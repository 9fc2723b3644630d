"""The one place where errors become HTTP (and gRPC) answers.

The service adds a few errors of its own to catalign's hierarchy (:mod:`catalign.errors`)::

    CatalignError
    ├── InvalidInputError ─┬─ ModelExistsError       409 model_exists
    │                      └─ IdempotencyKeyReusedError  422 idempotency_key_reused
    ├── LibraryError ──────┬─ EmptyLibraryError      409 library_empty
    │                      └─ LibraryChangedError    503 library_changed (with Retry-After)
    └── ServiceError
        ├── PayloadTooLargeError                     413 payload_too_large
        ├── UnsupportedMediaTypeError                415 unsupported_media_type
        ├── UnauthorizedError                        401 unauthorized
        ├── ReadOnlyError                            403 read_only
        ├── BusyError                                503 busy (with Retry-After)
        └── ClientGoneError                          499 client_closed_request
    DeadlineExceededError (catalign.errors)          503 deadline_exceeded (with Retry-After)

:data:`ERROR_TABLE` maps every class to its status, code and gRPC status name (the most
specific class wins); every answer has the body ``{"error": {"code", "message"}, "request_id"}``.
An exception outside the hierarchy is a bug: 500 ``internal``, logged with its traceback, its
text never shown to the caller.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from catalign.errors import (
    CatalignError,
    ConfigError,
    DeadlineExceededError,
    DegenerateInputError,
    InvalidInputError,
    LibraryChangedError,
    LibraryError,
    ModelNotFoundError,
    ShapeReadError,
)

logger = logging.getLogger(__name__)


class ServiceError(CatalignError):
    """Errors only the service raises (limits, authentication, load)."""


class PayloadTooLargeError(ServiceError):
    """The request body is larger than the configured limit."""


class UnsupportedMediaTypeError(ServiceError):
    """The request body has a content type the endpoint does not read."""


class UnauthorizedError(ServiceError):
    """The API key is missing or wrong."""


class ReadOnlyError(ServiceError):
    """The library cannot be changed: the server runs read-only."""


class BusyError(ServiceError):
    """Every worker is busy and the queue is full; retry after ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int = 1) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class ClientGoneError(ServiceError):
    """The client disconnected before its answer was ready (logged; nobody reads the answer)."""


class ModelExistsError(InvalidInputError):
    """A model with this id is already in the library."""


class IdempotencyKeyReusedError(InvalidInputError):
    """An ``Idempotency-Key`` sent again with another request than the first time."""


class EmptyLibraryError(LibraryError):
    """The library has no model to register against."""


@dataclass(frozen=True)
class ErrorKind:
    """How one error class is answered: HTTP status, stable code, gRPC status name."""

    status: int
    code: str
    grpc: str


INTERNAL = ErrorKind(500, "internal", "INTERNAL")

# Most specific first: the first class an error is an instance of decides.
ERROR_TABLE: tuple[tuple[type[Exception], ErrorKind], ...] = (
    (ModelExistsError, ErrorKind(409, "model_exists", "ALREADY_EXISTS")),
    (DegenerateInputError, ErrorKind(422, "degenerate_input", "INVALID_ARGUMENT")),
    (IdempotencyKeyReusedError, ErrorKind(422, "idempotency_key_reused", "INVALID_ARGUMENT")),
    (InvalidInputError, ErrorKind(422, "invalid_input", "INVALID_ARGUMENT")),
    (ShapeReadError, ErrorKind(422, "invalid_file", "INVALID_ARGUMENT")),
    (ModelNotFoundError, ErrorKind(404, "model_not_found", "NOT_FOUND")),
    (EmptyLibraryError, ErrorKind(409, "library_empty", "FAILED_PRECONDITION")),
    (LibraryChangedError, ErrorKind(503, "library_changed", "UNAVAILABLE")),
    (LibraryError, ErrorKind(500, "library_error", "INTERNAL")),
    (ConfigError, ErrorKind(500, "config_error", "INTERNAL")),
    (PayloadTooLargeError, ErrorKind(413, "payload_too_large", "RESOURCE_EXHAUSTED")),
    (UnsupportedMediaTypeError, ErrorKind(415, "unsupported_media_type", "INVALID_ARGUMENT")),
    (UnauthorizedError, ErrorKind(401, "unauthorized", "UNAUTHENTICATED")),
    (ReadOnlyError, ErrorKind(403, "read_only", "PERMISSION_DENIED")),
    (BusyError, ErrorKind(503, "busy", "RESOURCE_EXHAUSTED")),
    (DeadlineExceededError, ErrorKind(503, "deadline_exceeded", "DEADLINE_EXCEEDED")),
    (ClientGoneError, ErrorKind(499, "client_closed_request", "CANCELLED")),
)

# Errors Starlette raises itself (unknown route, wrong method), by status.
_HTTP_CODES = {404: "not_found", 405: "method_not_allowed", 413: "payload_too_large"}
_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def kind_of(error: BaseException) -> ErrorKind:
    """The answer for ``error``: its table entry, else 500 ``internal``."""
    for cls, kind in ERROR_TABLE:
        if isinstance(error, cls):
            return kind
    return INTERNAL


def message_of(error: BaseException) -> str:
    """What the caller is told: the error's own sentence, never a bug's internals."""
    if kind_of(error) is INTERNAL:
        return "internal server error; the request id identifies it in the server's logs"
    return str(error)


def error_body(code: str, message: str, request_id: str) -> dict[str, object]:
    return {"error": {"code": code, "message": message}, "request_id": request_id}


def error_response(error: BaseException, request_id: str) -> JSONResponse:
    """The JSON answer for ``error`` (with ``Retry-After`` when it says when to retry)."""
    kind = kind_of(error)
    retry_after = getattr(error, "retry_after", None)
    headers = {"Retry-After": str(retry_after)} if retry_after is not None else None
    return JSONResponse(
        error_body(kind.code, message_of(error), request_id), kind.status, headers=headers
    )


def request_id_of(request: Request) -> str:
    return str(getattr(request.state, "request_id", "-"))


def install_error_handlers(app: FastAPI) -> None:
    """Answer catalign errors, validation errors and Starlette's HTTP errors as JSON."""

    async def on_catalign_error(request: Request, error: Exception) -> JSONResponse:
        return error_response(error, request_id_of(request))

    async def on_validation_error(request: Request, error: Exception) -> JSONResponse:
        assert isinstance(error, RequestValidationError)
        message = describe_validation_errors(error.errors())
        return error_response(InvalidInputError(message), request_id_of(request))

    async def on_http_error(request: Request, error: Exception) -> JSONResponse:
        assert isinstance(error, StarletteHTTPException)
        code = _HTTP_CODES.get(error.status_code, "http_error")
        headers = error.headers
        if error.status_code == 405:
            headers = {**(headers or {}), "Allow": ", ".join(allowed_methods(app, request))}
        return JSONResponse(
            error_body(code, str(error.detail), request_id_of(request)),
            error.status_code,
            headers=headers,
        )

    app.add_exception_handler(CatalignError, on_catalign_error)
    app.add_exception_handler(RequestValidationError, on_validation_error)
    app.add_exception_handler(StarletteHTTPException, on_http_error)


def allowed_methods(app: FastAPI, request: Request) -> list[str]:
    """Every method served at the request's path. Starlette's 405 names only the first route
    that matched the path, so a path served by two routes (GET and DELETE ``/models/{id}``)
    would claim to allow one. A documented path answers with the methods ``openapi.yaml`` gives
    its template (a parameter never spans a slash there, whereas ``/models/{id:path}`` also
    matches ``/models/x/points``); any other path with those of the routes that match it."""
    documented = documented_methods(app, request.scope["path"])
    if documented is not None:
        return documented
    allowed = []
    for method in _METHODS:
        scope = {**request.scope, "method": method}
        if any(route.matches(scope)[0] is Match.FULL for route in app.router.routes):
            allowed.append(method)
    return allowed


def documented_methods(app: FastAPI, path: str) -> list[str] | None:
    """The methods ``openapi.yaml`` gives the template ``path`` matches, None if it matches
    none."""
    for template, methods in _documented_paths(app):
        if template.fullmatch(path):
            return methods
    return None


def _documented_paths(app: FastAPI) -> list[tuple[re.Pattern[str], list[str]]]:
    """The OpenAPI paths of ``app`` as patterns (a parameter is one path segment), each with
    its methods in ``_METHODS`` order."""
    cached = getattr(app.state, "documented_paths", None)
    if cached is None:
        cached = []
        for path, operations in app.openapi()["paths"].items():
            pattern = re.sub(r"\\\{[^}]*\\\}", "[^/]+", re.escape(path))
            served = {method.upper() for method in operations}
            cached.append((re.compile(pattern), [m for m in _METHODS if m in served]))
        app.state.documented_paths = cached
    return cached


def describe_validation_errors(errors: object) -> str:
    """One sentence from pydantic/FastAPI validation errors: where and what, first three."""
    parts = []
    items = list(errors) if isinstance(errors, list | tuple) else []
    for item in items[:3]:
        loc = ".".join(str(p) for p in item.get("loc", ()) if p != "body")
        parts.append(f"{loc}: {item.get('msg', 'invalid')}" if loc else item.get("msg", ""))
    more = f" (and {len(items) - 3} more)" if len(items) > 3 else ""
    return "; ".join(parts) + more if parts else "invalid request"
