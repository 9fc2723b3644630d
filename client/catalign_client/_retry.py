"""When the SDK sends a request again and how long it waits first: one policy, both clients.

Resent, up to ``retries`` times:

* a request that is safe to send twice (:attr:`Request.idempotent`: a registration or a read,
  which change nothing, or a library change carrying an ``Idempotency-Key``, which the server
  answers once) after a transport error (connection refused, reset or closed without an answer,
  a timeout) or a 502, 503 or 504 (a proxy that lost its server, a busy or starting server, a
  proxy's time-out);
* any request whose connection could not be opened: nothing reached the server.

Never resent: a 4xx (the request is the caller's to fix), a 500 (a bug, which the same request
meets again), and a library change without a key once it may have reached the server (any
answer, a reset, a timeout): sent twice it could add a model twice, or answer 404 to a removal
that worked.

The wait: the server's ``Retry-After`` when it sends one, else ``backoff * 2**n``; the first times
a random 1 to 1.2, the second a random 0.5 to 1 (jitter: clients that failed together do not
come back together); never over :data:`MAX_RETRY_DELAY`. No attempt starts later than ``budget``
seconds after the first one started, so a call lasts at most ``budget`` plus one attempt.
"""

from __future__ import annotations

import logging
import math
import random
from dataclasses import dataclass

import httpx

from ._exceptions import retry_after_seconds
from ._requests import Request

logger = logging.getLogger("catalign_client")

MAX_RETRY_DELAY = 10.0
"""Longest wait between two attempts in seconds, whatever ``Retry-After`` asks for."""

DEFAULT_RETRY_BUDGET = 30.0
"""Seconds after a call's first attempt started past which no other attempt starts."""

RETRIED_STATUSES = frozenset({502, 503, 504})
"""Answers after which a request that is safe to send twice is sent again."""

# Errors raised before any byte of the request reached the server: safe to resend anything.
_NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)


@dataclass(frozen=True)
class RetryPolicy:
    """How often and after how long a failed request is sent again (see the module's text)."""

    retries: int = 2
    backoff: float = 0.2
    budget: float = DEFAULT_RETRY_BUDGET

    def __post_init__(self) -> None:
        retries = self.retries
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise ValueError(f"retries must be a non-negative integer, got {retries!r}")
        if not _seconds(self.backoff):
            raise ValueError(
                f"backoff must be a non-negative number of seconds, got {self.backoff!r}"
            )
        if not _seconds(self.budget):
            raise ValueError(
                f"retry_budget must be a non-negative number of seconds, got {self.budget!r}"
            )

    def delay(
        self,
        request: Request,
        attempt: int,
        elapsed: float,
        *,
        response: httpx.Response | None = None,
        error: httpx.TransportError | None = None,
    ) -> float | None:
        """Seconds to wait before sending ``request`` again after ``attempt`` (0-based) failed
        ``elapsed`` seconds after the first started, or ``None``: do not."""
        if not request.retry or attempt >= self.retries:
            return None
        hint: float | None = None
        if error is not None:
            if not (request.idempotent or isinstance(error, _NOT_SENT)):
                return None
            reason = f"{type(error).__name__}: {error}"
        elif (
            response is not None and response.status_code in RETRIED_STATUSES and request.idempotent
        ):
            hint = retry_after_seconds(response)
            reason = f"{response.status_code} {response.reason_phrase}"
        else:
            return None
        delay = self.wait(attempt, hint)
        where = f"{request.method} {request.path}: {reason}"
        if elapsed + delay > self.budget:
            logger.info(
                "%s; no retry: %.2f s from now is past the retry budget of %.1f s",
                where,
                delay,
                self.budget,
            )
            return None
        logger.info("%s; retry %d of %d in %.2f s", where, attempt + 1, self.retries, delay)
        return delay

    def wait(self, attempt: int, hint: float | None) -> float:
        """The jittered wait after ``attempt``: ``hint`` (a ``Retry-After``) or the back-off."""
        if hint is not None:
            return min(hint * random.uniform(1.0, 1.2), MAX_RETRY_DELAY)
        return min(self.backoff * 2**attempt * random.uniform(0.5, 1.0), MAX_RETRY_DELAY)


def _seconds(value: object) -> bool:
    """Whether ``value`` is a finite, non-negative number (not a bool)."""
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value >= 0
    )
