"""Stop waiting for an answer whose client has gone.

Starlette does not cancel a handler when its client disconnects, so a registration would run to
the end for nobody. :func:`unless_disconnected` awaits the work and, at the same time, the
``http.disconnect`` message; whichever comes first wins. On a disconnect the work is cancelled
(the worker pool turns that into a cancelled deadline, and the worker stops at its next check)
and :class:`~catalign.api.errors.ClientGoneError` is raised, answered 499 to nobody and logged.
Call it only once the request body has been read: after that, the next message the server can
receive is the disconnect.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

from starlette.requests import Request

from catalign.api.errors import ClientGoneError

T = TypeVar("T")


async def unless_disconnected(request: Request, work: Coroutine[Any, Any, T]) -> T:
    """The result of ``work``, or ClientGoneError (``work`` cancelled) if the client leaves."""
    task = asyncio.ensure_future(work)
    gone = asyncio.ensure_future(_disconnected(request))
    try:
        await asyncio.wait({task, gone}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if not task.done():
            task.cancel()
        gone.cancel()
    if task.done() and not task.cancelled():
        return task.result()
    raise ClientGoneError("the client disconnected before the answer was ready")


async def _disconnected(request: Request) -> None:
    while (await request.receive())["type"] != "http.disconnect":
        pass
