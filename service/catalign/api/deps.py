"""Request dependencies as ``Annotated`` aliases, so that handler signatures read as plain types.

``ServiceDep`` and ``SettingsDep`` hand a route the app's service and settings (tests may
override :func:`get_service`); ``require_api_key`` and ``require_writable`` guard routers and
routes. The key is compared in constant time.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader

from catalign.api.errors import ReadOnlyError, UnauthorizedError
from catalign.api.service import RegistrationService
from catalign.api.settings import ServiceSettings

api_key_header = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="Required when the server was started with an API key (CATALIGN_API_KEY).",
)


def get_service(request: Request) -> RegistrationService:
    return request.app.state.service


def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


ServiceDep = Annotated[RegistrationService, Depends(get_service)]
SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]


def require_api_key(
    settings: SettingsDep, given: Annotated[str | None, Security(api_key_header)]
) -> None:
    """401 unless no key is configured or ``X-API-Key`` holds it."""
    if settings.api_key is None:
        return
    expected = settings.api_key.get_secret_value().encode()
    if given is None or not hmac.compare_digest(given.encode(), expected):
        raise UnauthorizedError(
            "missing API key: send it in the X-API-Key header"
            if given is None
            else "wrong API key in the X-API-Key header"
        )


def require_writable(settings: SettingsDep) -> None:
    """403 when the server runs read-only."""
    if settings.read_only:
        raise ReadOnlyError("the server runs read-only (--read-only): the library cannot change")
