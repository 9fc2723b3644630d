"""The HTTP routes, one ``APIRouter`` per resource, and the error answers they document."""

from __future__ import annotations

from typing import Any

from catalign.api.schemas import ErrorResponse

_DESCRIPTIONS = {
    401: "Missing or wrong X-API-Key (unauthorized)",
    403: "The server is read-only (read_only)",
    404: "No such model (model_not_found)",
    409: "The model id exists (model_exists) or the library is empty (library_empty)",
    413: "The body is over the server's limit (payload_too_large)",
    415: "Unsupported content type (unsupported_media_type)",
    422: "Bad input: invalid_input, degenerate_input or invalid_file",
    503: "Every worker busy and the queue full (busy, see Retry-After), or the request ran "
    "past its deadline (deadline_exceeded)",
}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for these error statuses, all with the error body."""
    return {s: {"model": ErrorResponse, "description": _DESCRIPTIONS[s]} for s in statuses}
