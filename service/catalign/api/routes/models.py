"""``/models``: list, inspect, add and remove the library models the server registers against.

Adding uploads a shape file (mesh or point cloud) with an optional ``model_id`` (default: the
file stem), ``units`` and ``category`` (default: chair); the server describes it, writes the
library atomically and serves the new library from then on. Listing goes by pages
(:mod:`catalign.api.paging`), may keep one ``category``, and counts every category's models.
``/models/{id}/points`` serves a model's surface points (metres, as stored), evenly thinned
to at most ``max_points``, as raw float32 for viewers and plots. Ids are checked against the
library's id pattern, also after URL decoding (``..%2Fx`` is refused with 422, not routed
somewhere else). Adding and removing take an ``Idempotency-Key``
(:mod:`catalign.api.idempotency`): a repeat with the key answers the first answer and changes
nothing, so a client may send the change again when its answer was lost.
"""

from __future__ import annotations

from pathlib import Path as FilePath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request, Response, status
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from catalign.api.deps import IdempotencyDep, IdempotencyKeyDep, ServiceDep, require_writable
from catalign.api.errors import documented_methods
from catalign.api.idempotency import Answer, Change, IdempotencyStore
from catalign.api.inputs import BINARY, MULTIPART, read_upload
from catalign.api.paging import CURSOR_PATTERN, DEFAULT_PAGE, MAX_PAGE, page
from catalign.api.routes import error_responses
from catalign.api.schemas import ModelList, ModelPublic, ModelRemoved
from catalign.errors import ModelNotFoundError
from catalign.geometry.io import SUPPORTED_SUFFIXES
from catalign.library.entry import LibraryEntry, file_sha256
from catalign.library.sources import (
    CATEGORY_PATTERN,
    MODEL_ID_PATTERN,
    UNIT_FACTORS,
    validate_category,
    validate_model_id,
)

router = APIRouter(prefix="/models", tags=["models"])

DEFAULT_MODEL_POINTS = 5_000
MAX_MODEL_POINTS = 20_000  # a library entry keeps 10,000


def documented_method(request: Request) -> None:
    """405 (naming the methods there) for a path of one documented resource that
    ``{model_id:path}`` took in as an id: ``DELETE /models/x/points`` removes no model
    ``x/points``. Checked before anything else, a read-only server included."""
    documented = documented_methods(request.app, request.scope["path"])
    if documented is not None and request.method not in documented:
        raise StarletteHTTPException(status.HTTP_405_METHOD_NOT_ALLOWED)


def checked_model_id(
    model_id: Annotated[
        str,
        Path(
            description="A library model id.",
            json_schema_extra={"pattern": f"^{MODEL_ID_PATTERN.pattern}$", "maxLength": 128},
        ),
    ],
) -> str:
    """The path's model id (already URL-decoded), or 422 if it is not a valid id (checked here
    rather than by FastAPI, so that the message says what a valid id is)."""
    return validate_model_id(model_id)


ModelId = Annotated[str, Depends(checked_model_id)]

_UPLOAD_BODY = {
    "required": True,
    "content": {
        MULTIPART: {
            "schema": {
                "type": "object",
                "properties": {
                    "file": {
                        "type": "string",
                        "format": "binary",
                        "description": "A mesh or point cloud: "
                        + ", ".join(sorted(SUPPORTED_SUFFIXES)),
                    },
                    "model_id": {
                        "type": "string",
                        "description": "Id of the new model (default: the file stem).",
                    },
                    "units": {
                        "type": "string",
                        "enum": list(UNIT_FACTORS),
                        "default": "m",
                        "description": "Units of the file's coordinates.",
                    },
                    "category": {
                        "type": "string",
                        "pattern": f"^{CATEGORY_PATTERN.pattern}$",
                        "description": "The kind of object it is (a short lower-case name: "
                        "chair, table); default: the library's (chair unless it was built with "
                        "another).",
                    },
                },
                "required": ["file"],
            }
        }
    },
}


@router.get("", response_model=ModelList, responses=error_responses(401, 422))
async def list_models(
    service: ServiceDep,
    category: Annotated[
        str | None,
        Query(
            description="Only the models of this category (none of an unknown one).",
            json_schema_extra={"pattern": f"^{CATEGORY_PATTERN.pattern}$"},
        ),
    ] = None,
    limit: Annotated[
        int, Query(ge=1, le=MAX_PAGE, description="Models per page, at most 10,000.")
    ] = DEFAULT_PAGE,
    cursor: Annotated[
        str | None,
        Query(
            max_length=400,
            description="The next_cursor of the page before; leave it out for the first page.",
            json_schema_extra={"pattern": f"^{CURSOR_PATTERN.pattern}$"},
        ),
    ] = None,
) -> ModelList:
    """The models of the library being served (or of one ``category``) sorted by id, one page
    at a time, and how many models each category holds."""
    if category is not None:
        validate_category(category)
    library = await service.current_library()
    ids = library.ids
    if category is not None:
        ids = [i for i, c in zip(ids, library.categories, strict=True) if c == category]
    shown, next_cursor = page(ids, ids, limit, cursor)
    return ModelList(
        count=len(shown),
        total=len(ids),
        models=[ModelPublic.of(library, model_id) for model_id in shown],
        categories=library.category_counts(),
        next_cursor=next_cursor,
    )


@router.get(
    "/{model_id:path}/points",
    response_class=Response,
    responses={
        200: {
            "content": {BINARY: {"schema": {"type": "string", "format": "binary"}}},
            "description": "N * 12 bytes: little-endian float32 x, y, z per point (metres, "
            "model frame); N is in the X-Point-Count header.",
        },
        **error_responses(401, 404, 422),
    },
)
async def get_model_points(
    model_id: ModelId,
    service: ServiceDep,
    max_points: Annotated[
        int,
        Query(ge=1, le=MAX_MODEL_POINTS, description="At most this many points, evenly thinned."),
    ] = DEFAULT_MODEL_POINTS,
) -> Response:
    """A library model's surface points, evenly thinned to at most ``max_points``."""
    points = (await service.model(model_id)).points
    step = -(-len(points) // max_points)  # ceiling division: at most max_points rows
    thinned = np.ascontiguousarray(points[::step], dtype="<f4")
    return Response(
        thinned.tobytes(), media_type=BINARY, headers={"X-Point-Count": str(len(thinned))}
    )


@router.get(
    "/{model_id:path}", response_model=ModelPublic, responses=error_responses(401, 404, 422)
)
async def get_model(model_id: ModelId, service: ServiceDep) -> ModelPublic:
    """One model of the library."""
    return ModelPublic.of(await service.current_library(), model_id)


@router.post(
    "",
    response_model=ModelPublic,
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(require_writable)],
    openapi_extra={"requestBody": _UPLOAD_BODY},
    responses=error_responses(401, 403, 409, 413, 415, 422, 503),
)
async def add_model(
    request: Request, service: ServiceDep, keys: IdempotencyDep, key: IdempotencyKeyDep
) -> Response:
    """Describe an uploaded shape and add it to the library (persisted atomically)."""
    service.ensure_capacity()
    async with read_upload(request, SUPPORTED_SUFFIXES, service.spool) as upload:
        model_id = upload.fields.get("model_id") or FilePath(upload.filename).stem
        units = upload.fields.get("units") or "m"
        category = upload.fields.get("category") or None  # None: the library's default
        sha256 = "" if key is None else await run_in_threadpool(file_sha256, upload.path)

        def added(entry: LibraryEntry) -> Answer:
            return Answer(201, ModelPublic.from_entry(entry).model_dump(mode="json"))

        async def add() -> Answer:
            return added(await service.add_model(upload, model_id, units, category))

        async def committed() -> Answer | None:
            try:
                entry = await service.model(model_id)
            except ModelNotFoundError:
                return None
            return added(entry) if entry.source_sha256 == sha256 else None

        fields = {"model_id": model_id, "units": units, "category": category or ""}
        asked = {"method": "POST", "path": "/models", "file": upload.filename, **fields}
        return await once(keys, key, Change(asked | {"sha256": sha256}, add, committed))


@router.delete(
    "/{model_id:path}",
    response_model=ModelRemoved,
    dependencies=[Depends(documented_method), Depends(require_writable)],
    responses=error_responses(401, 403, 404, 422, 503),
)
async def remove_model(
    model_id: ModelId, service: ServiceDep, keys: IdempotencyDep, key: IdempotencyKeyDep
) -> Response:
    """Remove a model from the library (persisted atomically)."""

    def removed(count: int) -> Answer:
        return Answer(200, ModelRemoved(removed=model_id, count=count).model_dump(mode="json"))

    async def remove() -> Answer:
        return removed(await service.remove_model(model_id))

    async def committed() -> Answer | None:
        library = await service.current_library()
        return None if model_id in library else removed(len(library))

    asked = {"method": "DELETE", "path": f"/models/{model_id}"}
    return await once(keys, key, Change(asked, remove, committed))


async def once(keys: IdempotencyStore, key: str | None, change: Change) -> Response:
    """``change`` made now (no key), or at most once for ``key`` (see idempotency.py)."""
    if key is None:
        answer = await change.run()
        return JSONResponse(answer.body, answer.status)
    return await keys.respond(key, change)
