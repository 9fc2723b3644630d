"""Turn request bodies into queries: JSON, raw float32 or an uploaded file, checked at the edge.

Every way of sending points ends in the same :class:`PointQuery`, so the three encodings cannot
drift apart. Checks that need no geometry (JSON syntax, shapes, NaN, the byte count, the point
limit) happen here, before a worker is spent; whether the cloud can fix a pose is the engine's.
Uploaded files are spooled to a folder of the server's spool (:mod:`catalign.api.spool`) that
exists for the request's lifetime.
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import AsyncIterator, Iterator, Mapping
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
from fastapi import Request
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from catalign.api.errors import UnsupportedMediaTypeError, describe_validation_errors
from catalign.api.schemas import RegisterOptions
from catalign.api.spool import Spool
from catalign.errors import InvalidInputError, ShapeReadError

JSON = "application/json"
BINARY = "application/octet-stream"
MULTIPART = "multipart/form-data"
CLOUD_SUFFIXES = frozenset({".ply", ".pcd", ".npy", ".xyz"})
_OPTION_NAMES = frozenset(RegisterOptions.model_fields)
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


@dataclass(frozen=True)
class PointQuery:
    """One registration: the points, or a file to read them from, and the options."""

    options: RegisterOptions
    points: np.ndarray | None = None
    path: Path | None = None
    filename: str = "the upload"


@dataclass(frozen=True)
class Upload:
    """An uploaded file spooled to disk, its original name and the form's text fields."""

    path: Path
    filename: str
    fields: Mapping[str, str] = field(default_factory=dict)


@contextmanager
def shown_as(path: Path, name: str) -> Iterator[None]:
    """Name an uploaded file by its original name, not its temporary path, in read errors."""
    try:
        yield
    except ShapeReadError as error:
        message = str(error).replace(str(path.resolve()), name).replace(str(path), name)
        raise ShapeReadError(message) from None


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def parse_options(values: Mapping[str, object]) -> RegisterOptions:
    """Validated options, or InvalidInputError naming the bad field."""
    try:
        return RegisterOptions.model_validate(dict(values))
    except ValidationError as error:
        raise InvalidInputError(describe_validation_errors(error.errors())) from None


_NUMBER = r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*"
# The query-parameter form of ``up``: three decimal numbers, comma-separated (the contract
# states it, so that a client learns it from the schema rather than from a refusal).
UP_PATTERN = re.compile(f"{_NUMBER},{_NUMBER},{_NUMBER}")


def parse_up(text: str | None) -> list[float] | None:
    """``"0,0,1"`` as three numbers (query-parameter form of ``up``)."""
    if text is None:
        return None
    values = [float(v) for v in text.split(",")] if UP_PATTERN.fullmatch(text) else []
    if len(values) != 3:
        raise InvalidInputError(
            f"up must be three comma-separated numbers like 0,0,1, got {text!r}"
        )
    return values


def check_cloud(points: np.ndarray, max_points: int) -> np.ndarray:
    """``points`` as finite float64 (N, 3) within the point limit, or InvalidInputError."""
    if points.size == 0:
        raise InvalidInputError("the point cloud is empty")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(
            f"points must be an (N, 3) array of x, y, z rows, got shape {points.shape}"
        )
    if len(points) > max_points:
        raise InvalidInputError(
            f"the point cloud has {len(points)} points, more than the limit of {max_points}; "
            "downsample it first"
        )
    bad = int((~np.isfinite(points).all(axis=1)).sum())
    if bad:
        raise InvalidInputError(
            f"{bad} of {len(points)} points have NaN or infinite coordinates; remove them first"
        )
    return np.ascontiguousarray(points, dtype=np.float64)


def decode_json(body: bytes, max_points: int) -> PointQuery:
    """A JSON body ``{"points": [[x, y, z], ...], ...options}``."""
    # Each row opens a bracket; counting them (a fast scan) refuses too many points before
    # parsing builds millions of Python floats (about 200 bytes per point).
    if body.count(b"[") > max_points + 2:  # the list of rows and ``up`` open one each
        raise InvalidInputError(
            f"the point cloud has more than {max_points} points, the limit; downsample it first"
        )
    try:
        data = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InvalidInputError(f"the body is not valid JSON ({error})") from None
    except RecursionError:
        raise InvalidInputError("the JSON body is nested too deeply") from None
    if not isinstance(data, dict) or "points" not in data:
        raise InvalidInputError('expected a JSON object {"points": [[x, y, z], ...], ...}')
    rows = data.pop("points")
    options = parse_options(data)
    if isinstance(rows, list) and len(rows) > max_points:
        raise InvalidInputError(
            f"the point cloud has {len(rows)} points, more than the limit of {max_points}; "
            "downsample it first"
        )
    try:
        points = np.array(rows)
    except ValueError:  # ragged rows
        points = np.array([], dtype=object)
    if points.dtype.kind not in "iuf":
        raise InvalidInputError("points must be a list of [x, y, z] rows of numbers")
    return PointQuery(options=options, points=check_cloud(points, max_points))


def decode_binary(body: bytes, options: RegisterOptions, max_points: int) -> PointQuery:
    """A body of N * 12 bytes: little-endian float32 x, y, z per point."""
    if len(body) % 12:
        raise InvalidInputError(
            f"the body has {len(body)} bytes, not a multiple of 12 "
            "(each point is three little-endian float32: x, y, z)"
        )
    points = np.frombuffer(body, dtype="<f4").reshape(-1, 3)
    return PointQuery(options=options, points=check_cloud(points, max_points))


async def decode_body(request: Request, options: RegisterOptions, max_points: int) -> PointQuery:
    """The query of a JSON or raw float32 body (parsed off the event loop)."""
    kind = media_type(request)
    if kind == JSON or kind.endswith("+json"):
        given = _OPTION_NAMES & set(request.query_params)
        if given:
            names = ", ".join(sorted(given))
            raise InvalidInputError(
                f"with a JSON body, options go in the body, not the query: {names}"
            )
        return await run_in_threadpool(decode_json, await request.body(), max_points)
    if kind == BINARY:
        return await run_in_threadpool(decode_binary, await request.body(), options, max_points)
    raise UnsupportedMediaTypeError(
        f"unsupported content type {kind or '(none)'!r}; send {JSON}, {BINARY} or {MULTIPART}"
    )


@asynccontextmanager
async def read_upload(
    request: Request, suffixes: frozenset[str], spool: Spool
) -> AsyncIterator[Upload]:
    """Spool the multipart field ``file`` to a folder of ``spool`` for the request's duration."""
    if media_type(request) != MULTIPART:
        raise UnsupportedMediaTypeError(f"send the file as {MULTIPART} with a 'file' field")
    try:
        form = await request.form(max_files=1, max_fields=8)
    except StarletteHTTPException as error:  # malformed multipart, too many parts
        raise InvalidInputError(f"unreadable multipart body: {error.detail}") from None
    try:
        upload = form.get("file")
        if not isinstance(upload, UploadFile):
            raise InvalidInputError("the multipart body needs a file in the field 'file'")
        filename = Path(upload.filename or "").name
        suffix = Path(filename).suffix.lower()
        if suffix not in suffixes:
            raise ShapeReadError(
                f"{filename or 'the upload'}: unsupported file type {suffix or '(none)'}; "
                f"supported: {' '.join(sorted(suffixes))}"
            )
        name = filename if _SAFE_NAME.fullmatch(filename) else f"upload{suffix}"
        fields = {k: v for k, v in form.items() if isinstance(v, str)}
        with spool.temporary_folder() as folder:
            path = folder / name
            await run_in_threadpool(_copy, upload.file, path)
            yield Upload(path=path, filename=filename, fields=fields)
    finally:
        await form.close()


def _copy(source: BinaryIO, target: Path) -> None:
    source.seek(0)
    with open(target, "wb") as out:
        shutil.copyfileobj(source, out)
