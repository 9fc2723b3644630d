"""Pages of ``GET /models``: a page of at most ``limit`` models in id order, and an opaque cursor
that resumes after the last one.

The cursor names the last id given (keyset paging), not an offset: a model added or removed
between two pages moves no other model to another page, so no model is given twice and none
that stayed is skipped. It is opaque to clients (base64url of ``after:<id>``) so that its form
may change without changing the contract. Any cursor of that form is a position among the
sorted ids, so ``CURSOR_PATTERN`` (which ``openapi.yaml`` gives clients) says exactly which are
taken.
"""

from __future__ import annotations

import base64
import re
from bisect import bisect_right
from collections.abc import Sequence
from typing import TypeVar

from catalign.errors import InvalidInputError

DEFAULT_PAGE = 1_000
MAX_PAGE = 10_000
_PREFIX = "after:"
# base64url of "after:" (six bytes: four characters a byte-aligned three), then any unpadded
# base64url text: whole quartets and an optional tail of two or three characters.
CURSOR_PATTERN = re.compile(r"YWZ0ZXI6(?:[A-Za-z0-9_-]{4})*(?:[A-Za-z0-9_-]{2,3})?")

T = TypeVar("T")


def encode_cursor(last_id: str) -> str:
    """The cursor that resumes after ``last_id``."""
    return base64.urlsafe_b64encode((_PREFIX + last_id).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> str:
    """The id a cursor resumes after; InvalidInputError (a 422) for one not of a cursor's form."""
    if CURSOR_PATTERN.fullmatch(cursor) is None:
        raise InvalidInputError(
            f"cursor {cursor[:40]!r} is not one this server gave; pass the next_cursor of the "
            "page before, or leave it out for the first page"
        )
    text = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4))
    return text.decode("utf-8", errors="replace").removeprefix(_PREFIX)


def page(
    ids: Sequence[str], items: Sequence[T], limit: int, cursor: str | None
) -> tuple[list[T], str | None]:
    """The ``items`` (in the order of their sorted ``ids``) after ``cursor``, at most ``limit``,
    and the cursor of the next page (None after the last)."""
    start = 0 if cursor is None else bisect_right(ids, decode_cursor(cursor))
    chosen = list(items[start : start + limit])
    more = start + limit < len(ids)
    return chosen, encode_cursor(ids[start + limit - 1]) if more else None
