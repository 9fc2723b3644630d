"""``/info`` (what is being served: versions, model card, library) and ``/metrics`` (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from catalign.api.deps import ServiceDep
from catalign.api.metrics import CONTENT_TYPE
from catalign.api.routes import error_responses
from catalign.api.schemas import InfoResponse

router = APIRouter(tags=["system"])


@router.get("/info", response_model=InfoResponse, responses=error_responses(401))
async def info(service: ServiceDep) -> InfoResponse:
    """Service version, model card, library summary, voxel size, headings and versions."""
    return service.info()


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {
            "content": {CONTENT_TYPE: {"schema": {"type": "string"}}},
            "description": "Prometheus text exposition format",
        },
        **error_responses(401),
    },
)
async def metrics(request: Request) -> Response:
    """Request counts and latencies, stage latencies, inlier ratios, queue depth."""
    return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE)
