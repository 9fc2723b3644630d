"""Request dependencies as ``Annotated`` aliases, so that handler signatures read as plain types.

``ServiceDep`` and ``SettingsDep`` hand a route the app's service and settings (tests may
override :func:`get_service`), ``IdempotencyDep`` its key records and ``IdempotencyKeyDep`` a
library change's checked ``Idempotency-Key``; ``require_api_key`` and ``require_writable`` guard
routers and routes. The API key travels in the ``X-API-Key`` header, or as
``Authorization: Bearer <key>`` for clients that cannot set custom headers (a Prometheus
ServiceMonitor); :func:`check_api_key`, shared with gRPC, compares it in constant time.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Header, Request, Security
from fastapi.security import APIKeyHeader, HTTPBearer
from pydantic import SecretStr
from starlette.requests import HTTPConnection

from catalign.api.errors import ReadOnlyError, UnauthorizedError
from catalign.api.idempotency import KEY_HEADER, KEY_PATTERN, IdempotencyStore, checked_key
from catalign.api.service import RegistrationService
from catalign.api.settings import ServiceSettings

api_key_header = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="The API key, required when the server was started with one "
    "(CATALIGN_API_KEY): the primary way to send it.",
)


class _AuthorizationHeader(HTTPBearer):
    """Documents ``Authorization: Bearer`` in OpenAPI and hands over the raw header (or None),
    so that a header in another scheme is refused with a sentence instead of ignored."""

    async def __call__(self, request: HTTPConnection) -> str | None:  # type: ignore[override]
        return request.headers.get("authorization")


bearer_header = _AuthorizationHeader(
    scheme_name="APIKeyBearer",
    auto_error=False,
    description="The same API key as `Authorization: Bearer <key>`, for clients that cannot "
    "send an X-API-Key header (a Prometheus ServiceMonitor).",
)


def get_service(request: Request) -> RegistrationService:
    return request.app.state.service


def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


def get_idempotency(request: Request) -> IdempotencyStore:
    return request.app.state.idempotency


def idempotency_key(
    key: Annotated[
        str | None,
        Header(
            alias=KEY_HEADER,
            description="Makes the change safe to send again: a repeat with the same key and "
            "the same request answers the first answer (Idempotent-Replayed: true) and changes "
            "nothing; the same key with another request is refused (422 "
            "idempotency_key_reused). Keys are kept 24 h.",
            json_schema_extra={"pattern": f"^{KEY_PATTERN.pattern}$", "maxLength": 255},
        ),
    ] = None,
) -> str | None:
    return None if key is None else checked_key(key)


ServiceDep = Annotated[RegistrationService, Depends(get_service)]
SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
IdempotencyDep = Annotated[IdempotencyStore, Depends(get_idempotency)]
IdempotencyKeyDep = Annotated[str | None, Depends(idempotency_key)]


def check_api_key(
    expected: SecretStr | None,
    api_key: str | None,
    authorization: str | None,
    *,
    key_in: str = "the X-API-Key header",
    bearer_in: str = "the Authorization header",
) -> None:
    """Raise :class:`UnauthorizedError` unless no key is configured or the request carries it.

    The key comes in ``api_key`` (the ``X-API-Key`` header, gRPC ``x-api-key`` metadata) or as
    ``authorization`` reading ``Bearer <key>`` (scheme case-insensitive). Whatever is sent is
    checked: a wrong key in one place, or an ``authorization`` in another scheme, is refused
    even when the other place holds the right key. Keys are compared in constant time; messages
    never echo what was sent. ``key_in`` and ``bearer_in`` name the two places in them.
    """
    if expected is None:
        return
    if api_key is None and authorization is None:
        raise UnauthorizedError(
            f"missing API key: send it in {key_in} or in {bearer_in} as 'Bearer <key>'"
        )
    want = expected.get_secret_value().encode()
    if api_key is not None and not hmac.compare_digest(api_key.encode(), want):
        raise UnauthorizedError(f"wrong API key in {key_in}")
    if authorization is None:
        return
    scheme, _, token = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        raise UnauthorizedError(
            f"{bearer_in} must read 'Bearer <key>' (no other scheme is accepted), "
            f"or send the key in {key_in} alone"
        )
    if not hmac.compare_digest(token.strip().encode(), want):
        raise UnauthorizedError(f"wrong API key in {bearer_in} (Bearer)")


def require_api_key(
    settings: SettingsDep,
    api_key: Annotated[str | None, Security(api_key_header)],
    authorization: Annotated[str | None, Security(bearer_header)],
) -> None:
    """401 unless no key is configured or ``X-API-Key`` or ``Authorization: Bearer`` holds it
    (and no other credential is sent beside it)."""
    check_api_key(settings.api_key, api_key, authorization)


def require_writable(settings: SettingsDep) -> None:
    """403 when the server runs read-only."""
    if settings.read_only:
        raise ReadOnlyError("the server runs read-only (--read-only): the library cannot change")
