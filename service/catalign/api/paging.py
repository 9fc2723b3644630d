"""Pages of ``GET /models``: a page of at most ``limit`` models in id order, and an opaque cursor
that resumes after the last one.

The cursor names the last id given (keyset paging), not an offset: a model added or removed
between two pages moves no other model to another page, so no model is given twice and none
that stayed is skipped. It is opaque to clients (base64url of ``after:<id>``) so that its form
may change without changing the contract.
"""

from __future__ import annotations

import base64
import binascii
from bisect import bisect_right
from collections.abc import Sequence
from typing import TypeVar

from catalign.errors import InvalidInputError
from catalign.library.sources import MODEL_ID_PATTERN

DEFAULT_PAGE = 1_000
MAX_PAGE = 10_000
_PREFIX = "after:"

T = TypeVar("T")


def encode_cursor(last_id: str) -> str:
    """The cursor that resumes after ``last_id``."""
    return base64.urlsafe_b64encode((_PREFIX + last_id).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> str:
    """The id a cursor resumes after; InvalidInputError (a 422) for one this server never gave."""
    try:
        text = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
    except (binascii.Error, UnicodeDecodeError, ValueError):
        text = ""
    last_id = text.removeprefix(_PREFIX)
    if not text.startswith(_PREFIX) or MODEL_ID_PATTERN.fullmatch(last_id) is None:
        raise InvalidInputError(
            f"cursor {cursor[:40]!r} is not one this server gave; pass the next_cursor of the "
            "page before, or leave it out for the first page"
        )
    return last_id


def page(
    ids: Sequence[str], items: Sequence[T], limit: int, cursor: str | None
) -> tuple[list[T], str | None]:
    """The ``items`` (in the order of their sorted ``ids``) after ``cursor``, at most ``limit``,
    and the cursor of the next page (None after the last)."""
    start = 0 if cursor is None else bisect_right(ids, decode_cursor(cursor))
    chosen = list(items[start : start + limit])
    more = start + limit < len(ids)
    return chosen, encode_cursor(ids[start + limit - 1]) if more else None
