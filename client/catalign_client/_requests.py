"""Requests as plain data, and the registration options checked and encoded for the wire.

A retry must resend exactly what was sent, and the sync and async clients must send exactly the
same thing, so every request is first built as a frozen :class:`Request` (files already read into
memory) that either client can hand to httpx as often as needed. The options are checked here,
before any I/O, and written the way the HTTP contract reads them: ``up=0,0,1``,
``estimate_scale=true`` and ``min_confidence=0.8`` as query parameters, or native JSON values in
a JSON body. A library change's ``Idempotency-Key`` is checked (or made) here too.
"""

from __future__ import annotations

import math
import numbers
import re
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

Encoding = Literal["binary", "json"]
UpLike = Sequence[float] | str
IdempotencyKey = str | bool | None
"""A key of your own, ``True`` for a fresh UUID, or ``None``/``False`` for none."""

IDEMPOTENCY_HEADER = "Idempotency-Key"
_IDEMPOTENCY_KEY = re.compile(r"[\x21-\x7e]{1,255}")  # as the server accepts it


@dataclass(frozen=True)
class Request:
    """One HTTP request as plain data, so that it can be sent again on a retry.

    ``idempotent`` says whether sending it twice is harmless (registration is a pure function;
    adding a model is not, unless it carries an ``Idempotency-Key`` the server answers once).
    ``retry`` off means "answer now".
    """

    method: str
    path: str
    params: Mapping[str, str] | None = None
    content: bytes | None = None
    json: Any = None
    files: Mapping[str, tuple[str, bytes, str]] | None = None
    data: Mapping[str, str] | None = None
    headers: Mapping[str, str] | None = None
    idempotent: bool = True
    retry: bool = True

    def arguments(self) -> dict[str, Any]:
        """Keyword arguments for ``httpx.Client.request``, unset ones left out."""
        names = ("params", "content", "json", "files", "data", "headers")
        return {name: getattr(self, name) for name in names if getattr(self, name) is not None}


def registration_options(
    *,
    top_k: int | None,
    up: UpLike | None,
    estimate_scale: bool,
    seed: int | None,
    category: str | None = None,
    min_confidence: float | None = None,
) -> dict[str, Any]:
    """The registration options, checked, with "not given" left out (the server's default)."""
    options: dict[str, Any] = {}
    if top_k is not None:
        if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
            raise ValueError(f"top_k must be a positive integer, got {top_k!r}")
        options["top_k"] = top_k
    if up is not None:
        options["up"] = up_vector(up)
    if not isinstance(estimate_scale, bool):
        raise TypeError(f"estimate_scale must be a bool, got {estimate_scale!r}")
    options["estimate_scale"] = estimate_scale
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        options["seed"] = seed
    if category is not None:
        if not isinstance(category, str) or not category:
            raise ValueError(f"category must be a non-empty string, got {category!r}")
        options["category"] = category
    if min_confidence is not None:
        options["min_confidence"] = confidence_threshold(min_confidence)
    return options


def confidence_threshold(value: float) -> float:
    """A probability in [0, 1] (``min_confidence``), as a float."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not 0.0 <= float(value) <= 1.0  # NaN fails too
    ):
        raise ValueError(f"min_confidence must be a number from 0 to 1, got {value!r}")
    return float(value)


def model_points_params(max_points: int) -> dict[str, str]:
    """The query of ``GET /models/{id}/points``; the server enforces its upper limit."""
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 1:
        raise ValueError(f"max_points must be a positive integer, got {max_points!r}")
    return {"max_points": str(max_points)}


def up_vector(up: UpLike) -> list[float]:
    """Three finite numbers, not all zero, from a sequence or a ``"0,0,1"`` string."""
    parts: Sequence[Any] = up.split(",") if isinstance(up, str) else up
    try:
        vector = [float(v) for v in parts]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"up must be three numbers such as (0, 0, 1), got {up!r}") from exc
    if len(vector) != 3 or not all(map(math.isfinite, vector)) or not any(vector):
        raise ValueError(f"up must be three finite numbers, not all zero, got {up!r}")
    return vector


def query(options: Mapping[str, Any]) -> dict[str, str]:
    """Options as query parameters: ``up=0,0,1``, ``estimate_scale=true``."""
    params = {}
    for name, value in options.items():
        if isinstance(value, bool):
            params[name] = "true" if value else "false"
        elif isinstance(value, list):
            params[name] = ",".join(_number(v) for v in value)
        else:
            params[name] = str(value)
    return params


def _number(value: float) -> str:
    """``1.0`` as ``"1"``, other floats in their shortest exact form."""
    return str(int(value)) if value.is_integer() else repr(value)


def upload(path: str | Path) -> dict[str, tuple[str, bytes, str]]:
    """The multipart ``file`` field, read into memory so that a retry can resend it."""
    path = Path(path)
    return {"file": (path.name, path.read_bytes(), "application/octet-stream")}


def idempotency_headers(key: IdempotencyKey) -> dict[str, str] | None:
    """The ``Idempotency-Key`` header for ``key`` (``True``: a fresh UUID), or None for none."""
    if key is None or key is False:
        return None
    if key is True:
        key = str(uuid.uuid4())
    if not isinstance(key, str) or not _IDEMPOTENCY_KEY.fullmatch(key):
        raise ValueError(
            "idempotency_key must be True or 1 to 255 visible ASCII characters (no spaces), "
            f"got {key!r}"
        )
    return {IDEMPOTENCY_HEADER: key}
