"""Health checks for orchestrators: liveness (the process answers) and readiness (it can work).

Both stay open when an API key is configured. Ready means the weights and the library are
loaded and one warm-up registration ran; until then ``/health/ready`` answers 503.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from catalign.api.deps import ServiceDep
from catalign.api.schemas import LiveStatus, ReadyStatus

router = APIRouter(prefix="/health", tags=["health"])


@router.get("/live", response_model=LiveStatus)
async def live() -> LiveStatus:
    """The process is up and its event loop answers."""
    return LiveStatus()


@router.get(
    "/ready",
    response_model=ReadyStatus,
    responses={503: {"model": ReadyStatus, "description": "Still loading or warming up"}},
)
async def ready(service: ServiceDep) -> ReadyStatus | JSONResponse:
    """200 once the service can register, 503 ``starting`` before."""
    if service.ready:
        return ReadyStatus(status="ready")
    return JSONResponse(ReadyStatus(status="starting").model_dump(), status_code=503)
