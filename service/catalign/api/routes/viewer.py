"""The browser viewer: ``/`` (links), ``/viewer`` (the page) and its static files.

People checking an answer want to see it: the page uploads a scan to ``POST /register`` and draws
the observed points with the chosen model placed by the returned pose (three.js, vendored under
``static/vendor/three``; see ``static/README.md``). The pages and their files hold no data, so
they stay outside the API-key guard and out of the OpenAPI schema (they are for people, not
clients); the calls the page makes send the key typed into it. Every answer carries a
Content-Security-Policy that keeps all requests on this origin: the one inline script, the
import map, is allowed by its SHA-256 hash, computed from the page itself, so editing the map
cannot silently break or widen the policy.
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import cache
from importlib.resources import files

from fastapi import APIRouter
from fastapi.responses import HTMLResponse
from starlette.responses import Response
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

router = APIRouter(tags=["viewer"], include_in_schema=False)

STATIC_URL = "/viewer/static"
_PACKAGE, _FOLDER = "catalign.api", "static"
_IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.DOTALL)


@router.get("/", response_class=HTMLResponse)
async def index() -> HTMLResponse:
    """A page of links: the viewer, the API documentation and the readiness check."""
    return _page("index.html")


@router.get("/viewer", response_class=HTMLResponse)
async def viewer() -> HTMLResponse:
    """The viewer page; its script and three.js load from :data:`STATIC_URL`."""
    return _page("viewer.html")


class ViewerStaticFiles(StaticFiles):
    """The viewer's scripts, styles and vendored three.js, with the pages' security headers."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        response.headers.update(security_headers())
        return response


def static_files() -> ViewerStaticFiles:
    """The app to mount at :data:`STATIC_URL` (files installed with the package)."""
    return ViewerStaticFiles(packages=[(_PACKAGE, _FOLDER)])


@cache
def security_headers() -> dict[str, str]:
    return {
        "Content-Security-Policy": content_security_policy(),
        "X-Content-Type-Options": "nosniff",
        "Referrer-Policy": "no-referrer",
    }


def content_security_policy() -> str:
    """Same origin only, no inline code but the viewer's import map (allowed by its hash)."""
    import_map = _IMPORT_MAP.search(_read("viewer.html"))
    if import_map is None:
        raise RuntimeError("viewer.html has no import map")
    digest = base64.b64encode(hashlib.sha256(import_map.group(1).encode()).digest()).decode()
    return "; ".join(
        (
            "default-src 'self'",
            f"script-src 'self' 'sha256-{digest}'",
            "style-src 'self'",
            "img-src 'self'",
            "connect-src 'self'",
            "object-src 'none'",
            "base-uri 'none'",
            "form-action 'none'",
            "frame-ancestors 'none'",
        )
    )


def _page(name: str) -> HTMLResponse:
    return HTMLResponse(_read(name), headers=security_headers())


@cache
def _read(name: str) -> str:
    return (files(_PACKAGE) / _FOLDER / name).read_text(encoding="utf-8")
