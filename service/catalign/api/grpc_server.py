"""The gRPC front door: ``catalign.v1.Catalign`` (Register, ListModels) and the standard health
service, on the same event loop and the same :class:`~catalign.api.service.RegistrationService`
as HTTP, so both share the worker pool, the limits and the answers.

Errors map through :data:`catalign.api.errors.ERROR_TABLE` to gRPC status codes; the catalign
error code travels in the trailing metadata ``catalign-error-code`` and the request id (taken from
``x-request-id`` metadata or generated) in ``x-request-id``. With an API key configured, calls to
``Catalign`` need it in ``x-api-key`` metadata (or, as over HTTP, ``authorization: Bearer <key>``
metadata); health checks stay open.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TypeVar

import grpc

from catalign.api import catalign_pb2, catalign_pb2_grpc, health_pb2, health_pb2_grpc
from catalign.api.deps import check_api_key
from catalign.api.errors import INTERNAL, kind_of, message_of
from catalign.api.inputs import decode_binary, parse_options
from catalign.api.metrics import Metrics
from catalign.api.middleware import valid_request_id
from catalign.api.paging import DEFAULT_PAGE, MAX_PAGE, page
from catalign.api.schemas import ModelPublic, RegisterResponse
from catalign.api.service import RegistrationService
from catalign.api.settings import ServiceSettings
from catalign.errors import ConfigError, InvalidInputError
from catalign.library.sources import validate_category

logger = logging.getLogger("catalign.api.grpc")

SERVICE_NAME = "catalign.v1.Catalign"
R = TypeVar("R")
Serving = health_pb2.HealthCheckResponse.ServingStatus


class CatalignServicer(catalign_pb2_grpc.CatalignServicer):
    """Register and ListModels over gRPC, with HTTP's semantics and errors."""

    def __init__(self, service: RegistrationService, settings: ServiceSettings, metrics: Metrics):
        self.service = service
        self.settings = settings
        self.metrics = metrics

    async def Register(
        self, request: catalign_pb2.RegisterRequest, context: grpc.aio.ServicerContext
    ) -> catalign_pb2.RegisterReply:
        async def run(request_id: str) -> catalign_pb2.RegisterReply:
            options = parse_options(
                {
                    "top_k": request.top_k if request.HasField("top_k") else None,
                    "up": list(request.up) or None,
                    "estimate_scale": request.estimate_scale,
                    "seed": request.seed,
                    "category": request.category if request.HasField("category") else None,
                    "min_confidence": (
                        request.min_confidence if request.HasField("min_confidence") else None
                    ),
                }
            )
            self.service.ensure_capacity()
            query = decode_binary(request.points, options, self.settings.max_points)
            result = await self.service.register(query, deadline_s=context.time_remaining())
            answer = RegisterResponse.from_result(
                result, request_id, min_confidence=options.min_confidence
            )
            return register_reply(answer)

        return await self._call("Register", context, run)

    async def ListModels(
        self, request: catalign_pb2.ListModelsRequest, context: grpc.aio.ServicerContext
    ) -> catalign_pb2.ListModelsReply:
        async def run(request_id: str) -> catalign_pb2.ListModelsReply:
            category = request.category or None
            if category is not None:
                validate_category(category)
            if not 0 <= request.page_size <= MAX_PAGE:
                raise InvalidInputError(
                    f"page_size {request.page_size} is outside 0 to {MAX_PAGE} (0: {DEFAULT_PAGE})"
                )
            library = await self.service.current_library()
            ids = library.ids
            if category is not None:
                ids = [i for i, c in zip(ids, library.categories, strict=True) if c == category]
            shown, next_token = page(
                ids, ids, request.page_size or DEFAULT_PAGE, request.page_token or None
            )
            models = [_model(ModelPublic.of(library, model_id)) for model_id in shown]
            return catalign_pb2.ListModelsReply(
                count=len(models), models=models, next_page_token=next_token or "", total=len(ids)
            )

        return await self._call("ListModels", context, run)

    async def _call(
        self,
        method: str,
        context: grpc.aio.ServicerContext,
        run: Callable[[str], Awaitable[R]],
    ) -> R:
        """Authenticate, run, count, log, and turn errors into gRPC statuses."""
        metadata = {k: v for k, v in (context.invocation_metadata() or ()) if isinstance(v, str)}
        request_id = valid_request_id(metadata.get("x-request-id"))
        await context.send_initial_metadata((("x-request-id", request_id),))
        started = time.perf_counter()
        try:
            check_api_key(
                self.settings.api_key,
                metadata.get("x-api-key"),
                metadata.get("authorization"),
                key_in="the x-api-key metadata",
                bearer_in="the authorization metadata",
            )
            reply = await run(request_id)
        except Exception as error:
            kind = kind_of(error)
            if kind is INTERNAL:
                logger.exception("request_id=%s unhandled error in %s", request_id, method)
            self._log(method, request_id, kind.grpc, started)
            context.set_trailing_metadata(
                (("catalign-error-code", kind.code), ("x-request-id", request_id))
            )
            await context.abort(grpc.StatusCode[kind.grpc], message_of(error))
        self._log(method, request_id, "OK", started)
        return reply

    def _log(self, method: str, request_id: str, code: str, started: float) -> None:
        self.metrics.grpc_requests.labels(method, code).inc()
        logger.info(
            "request_id=%s grpc=%s code=%s ms=%.1f",
            request_id,
            method,
            code,
            (time.perf_counter() - started) * 1e3,
        )


def register_reply(answer: RegisterResponse) -> catalign_pb2.RegisterReply:
    """The gRPC form of an HTTP answer, so that both carry the same fields and values."""
    return catalign_pb2.RegisterReply(
        model_id=answer.model_id,
        category=answer.category or "",
        category_confidence=answer.category_confidence,
        symmetry=(
            None
            if answer.symmetry is None
            else catalign_pb2.Symmetry(
                order=answer.symmetry.order, yaws_deg=answer.symmetry.yaws_deg
            )
        ),
        pose=_row_major(answer.pose),
        scale=answer.scale,
        fitness=answer.fitness,
        inlier_rmse=answer.inlier_rmse,
        num_inliers=answer.num_inliers,
        inlier_ratio=answer.inlier_ratio,
        points_set_aside=answer.points_set_aside,
        up=answer.up or [],
        up_estimated=answer.up_estimated,
        confidence=answer.confidence,
        accepted=answer.accepted,
        reason=answer.reason or "",
        alternatives=[
            catalign_pb2.Alternative(
                model_id=a.model_id,
                pose=_row_major(a.pose),
                scale=a.scale,
                score=a.score,
                fitness=a.fitness,
                confidence=a.confidence,
            )
            for a in answer.alternatives
        ],
        candidates=[
            catalign_pb2.Candidate(model_id=c.model_id, score=c.score) for c in answer.candidates
        ],
        timings_ms=answer.timings_ms,
        request_id=answer.request_id,
    )


def _model(model: ModelPublic) -> catalign_pb2.Model:
    """A model as ``ListModels`` answers it: the fields ``GET /models`` shows."""
    symmetry = model.symmetry
    return catalign_pb2.Model(
        model_id=model.model_id,
        category=model.category,
        symmetry=catalign_pb2.Symmetry(order=symmetry.order, yaws_deg=symmetry.yaws_deg),
        source=model.source,
        units=model.units,
        num_points=model.num_points,
        bbox_min=model.bbox_min,
        bbox_max=model.bbox_max,
        size=model.size,
    )


def _row_major(pose: list[list[float]]) -> list[float]:
    """A 4x4 pose as the 16 values the proto's ``pose`` fields hold."""
    return [v for row in pose for v in row]


class HealthServicer(health_pb2_grpc.HealthServicer):
    """``grpc.health.v1.Health``: SERVING once the service is ready (as ``/health/ready``)."""

    KNOWN = frozenset({"", SERVICE_NAME})
    WATCH_INTERVAL_S = 1.0

    def __init__(self, service: RegistrationService) -> None:
        self.service = service

    def _status(self, name: str) -> int:
        if name not in self.KNOWN:
            return Serving.SERVICE_UNKNOWN
        return Serving.SERVING if self.service.ready else Serving.NOT_SERVING

    async def Check(
        self, request: health_pb2.HealthCheckRequest, context: grpc.aio.ServicerContext
    ) -> health_pb2.HealthCheckResponse:
        if request.service not in self.KNOWN:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"unknown service {request.service!r}")
        return health_pb2.HealthCheckResponse(status=self._status(request.service))

    async def Watch(
        self, request: health_pb2.HealthCheckRequest, context: grpc.aio.ServicerContext
    ) -> AsyncIterator[health_pb2.HealthCheckResponse]:
        last = None
        while True:
            status = self._status(request.service)
            if status != last:
                yield health_pb2.HealthCheckResponse(status=status)
                last = status
            await asyncio.sleep(self.WATCH_INTERVAL_S)


async def start_grpc_server(
    service: RegistrationService, settings: ServiceSettings, metrics: Metrics
) -> tuple[grpc.aio.Server, int]:
    """Serve both gRPC services on ``settings.host:settings.grpc_port``; returns the bound port."""
    server = grpc.aio.server(
        options=[
            ("grpc.max_receive_message_length", settings.max_body_bytes),
            ("grpc.so_reuseport", 0),
        ]
    )
    catalign_pb2_grpc.add_CatalignServicer_to_server(
        CatalignServicer(service, settings, metrics), server
    )
    health_pb2_grpc.add_HealthServicer_to_server(HealthServicer(service), server)
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    address = f"{host}:{settings.grpc_port}"
    try:
        port = server.add_insecure_port(address)
    except RuntimeError as error:
        raise ConfigError(f"cannot listen for gRPC on {address} ({error}); is it in use?") from None
    await server.start()
    logger.info("gRPC listening on %s:%d", settings.host, port)
    return server, port
