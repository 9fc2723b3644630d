"""The FastAPI application: ``create_app(settings)`` wires routes, errors, middleware, lifespan.

Nothing happens at import time and nothing heavy in ``create_app``: the lifespan loads the
weights and the library (a failure stops the server with the reason), starts gRPC when enabled,
and warms up in the background; ``/health/ready`` turns 200 when the warm-up ran.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

from fastapi import Depends, FastAPI
from pydantic import BaseModel

import catalign
from catalign.api.deps import require_api_key
from catalign.api.errors import install_error_handlers
from catalign.api.idempotency import FOLDER, IdempotencyStore
from catalign.api.metrics import Metrics
from catalign.api.middleware import RequestContextMiddleware
from catalign.api.routes import health, models, register, system, viewer
from catalign.api.schemas import RegisterRequest
from catalign.api.service import RegistrationService
from catalign.api.settings import ServiceSettings
from catalign.errors import ConfigError

if TYPE_CHECKING:
    import grpc

logger = logging.getLogger(__name__)

DESCRIPTION = (
    "Registers a partial point cloud of a chair against a CAD library: the best model, its "
    "SE(3) pose (model -> observation) and inlier statistics. Every error answers "
    '`{"error": {"code", "message"}, "request_id"}`; see the 4xx/5xx responses of each route.'
)


def create_app(settings: ServiceSettings) -> FastAPI:
    """A ready-to-serve app; the lifespan loads the model and the library."""
    metrics = Metrics()
    service = RegistrationService(settings, metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        grpc_server: grpc.aio.Server | None = None
        warm_up: asyncio.Task[None] | None = None
        try:
            await service.start()
            if settings.grpc_enabled:
                grpc_server, app.state.grpc_port = await _start_grpc(service, settings, metrics)
            warm_up = asyncio.create_task(service.warm_up(), name="catalign-warm-up")
            warm_up.add_done_callback(_report_warm_up)
            yield
        finally:
            if warm_up is not None:
                warm_up.cancel()
            if grpc_server is not None:
                await grpc_server.stop(grace=5)
            await service.close()

    app = FastAPI(
        title="catalign",
        version=catalign.__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.service = service
    app.state.idempotency = IdempotencyStore(settings.library / FOLDER)  # beside the library
    app.state.grpc_port = None
    install_error_handlers(app)
    app.add_middleware(
        RequestContextMiddleware,
        max_body_bytes=settings.max_body_bytes,
        metrics=metrics,
        refuse_early=service.refusal,
    )
    guarded = [Depends(require_api_key)]
    app.include_router(health.router)
    app.include_router(register.router, dependencies=guarded)
    app.include_router(models.router, dependencies=guarded)
    app.include_router(system.router, dependencies=guarded)
    app.include_router(viewer.router)  # public pages; the calls they make carry the key
    app.mount(viewer.STATIC_URL, viewer.static_files(), name="viewer-static")
    _document_request_models(app, RegisterRequest)
    return app


def _document_request_models(app: FastAPI, *models: type[BaseModel]) -> None:
    """List request models that routes read themselves among the OpenAPI components."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = generate()
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in models:
                components[model.__name__] = model.model_json_schema(
                    ref_template="#/components/schemas/{model}"
                )
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


async def _start_grpc(
    service: RegistrationService, settings: ServiceSettings, metrics: Metrics
) -> tuple[grpc.aio.Server, int]:
    try:
        from catalign.api.grpc_server import start_grpc_server
    except ImportError as error:  # protobuf missing: say so instead of a bare traceback
        raise ConfigError(
            f"gRPC cannot start ({error}); install catalign[serve] or pass --grpc-port 0"
        ) from error
    return await start_grpc_server(service, settings, metrics)


def _report_warm_up(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        logger.error("warm-up failed; the service stays unready", exc_info=task.exception())
