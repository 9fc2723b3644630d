"""``POST /register``: a partial cloud in, the best model with its pose and statistics out.

Three encodings of the same request: JSON (points and options in the body), raw little-endian
float32 (``application/octet-stream``, options as query parameters) and a multipart upload of a
.ply/.pcd/.npy/.xyz file (options as query parameters). The route only decodes, calls the
service and maps the answer.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request

from catalign.api.deps import ServiceDep, SettingsDep
from catalign.api.disconnect import unless_disconnected
from catalign.api.errors import request_id_of
from catalign.api.inputs import (
    BINARY,
    CLOUD_SUFFIXES,
    JSON,
    MULTIPART,
    UP_PATTERN,
    PointQuery,
    decode_body,
    media_type,
    parse_options,
    parse_up,
    read_upload,
)
from catalign.api.routes import error_responses
from catalign.api.schemas import (
    MAX_SEED,
    MAX_TOP_K,
    RegisterOptions,
    RegisterResponse,
)
from catalign.library.sources import CATEGORY_PATTERN

router = APIRouter(tags=["registration"])

# The route reads its body itself (three encodings), so FastAPI does not list the JSON form's
# model; app.py adds RegisterRequest to the OpenAPI components.
_REQUEST_BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/RegisterRequest"}},
        BINARY: {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "N * 12 bytes: little-endian float32 x, y, z per point.",
            }
        },
        MULTIPART: {
            "schema": {
                "type": "object",
                "properties": {
                    "file": {
                        "type": "string",
                        "format": "binary",
                        "description": "A point cloud file: " + ", ".join(sorted(CLOUD_SUFFIXES)),
                    }
                },
                "required": ["file"],
            }
        },
    },
}


def query_options(
    top_k: Annotated[
        int | None, Query(ge=1, le=MAX_TOP_K, description="Models to try (binary/file bodies).")
    ] = None,
    up: Annotated[
        str | None,
        Query(
            description="World up direction 'x,y,z', e.g. 0,0,1 (binary/file bodies).",
            json_schema_extra={"pattern": f"^{UP_PATTERN.pattern}$"},
        ),
    ] = None,
    estimate_scale: Annotated[
        bool,
        Query(
            description="Also estimate a uniform scale, between 0.5 and 2 times the model's size "
            "(binary/file bodies)."
        ),
    ] = False,
    seed: Annotated[int, Query(ge=0, le=MAX_SEED, description="RANSAC seed.")] = 0,
    category: Annotated[
        str | None,
        Query(
            description="Search only this category's models (binary/file bodies; e.g. table).",
            json_schema_extra={"pattern": f"^{CATEGORY_PATTERN.pattern}$"},
        ),
    ] = None,
    min_confidence: Annotated[
        float | None,
        Query(
            ge=0.0,
            le=1.0,
            description="Confidence in [0, 1] the answer needs to be accepted (binary/file "
            "bodies); below it the answer is still a 200, with accepted false and a reason.",
        ),
    ] = None,
) -> RegisterOptions:
    """Options given as query parameters (a JSON body carries them in the body instead)."""
    return parse_options(
        {
            "top_k": top_k,
            "up": parse_up(up),
            "estimate_scale": estimate_scale,
            "seed": seed,
            "category": category,
            "min_confidence": min_confidence,
        }
    )


@router.post(
    "/register",
    response_model=RegisterResponse,
    summary="Register a partial point cloud against the library",
    openapi_extra={"requestBody": _REQUEST_BODY},
    responses=error_responses(401, 409, 413, 415, 422, 503),
)
async def register(
    request: Request,
    service: ServiceDep,
    settings: SettingsDep,
    options: Annotated[RegisterOptions, Depends(query_options)],
) -> RegisterResponse:
    """The best library model for the cloud, its model -> observation pose and inlier stats,
    the probability that the pose is right (``confidence``) and other distinct answers.

    With ``min_confidence`` an answer below it is still a 200 with the pose, marked
    ``accepted: false`` with a ``reason``: the caller decides (e.g. to look from another view).

    Clouds over the server's ``max_points`` (default 500,000), or that cannot be one chair in
    metres, are refused with 422; a full queue answers 503 before the body is read, and a
    registration past the server's deadline (default 10 s) 503 ``deadline_exceeded``.
    """
    with service.reserve() as slot:  # a full queue answers 503 before the body is read
        if media_type(request) == MULTIPART:
            async with read_upload(request, CLOUD_SUFFIXES, service.spool) as upload:
                query = PointQuery(options=options, path=upload.path, filename=upload.filename)
                result = await unless_disconnected(request, service.register(query, slot=slot))
        else:
            query = await decode_body(request, options, settings.max_points)
            result = await unless_disconnected(request, service.register(query, slot=slot))
    return RegisterResponse.from_result(
        result, request_id_of(request), min_confidence=query.options.min_confidence
    )
