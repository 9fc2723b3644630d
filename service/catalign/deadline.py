"""A request's deadline and cancellation token, checked by the work between its stages.

A registration runs on a worker thread, where Python cannot interrupt it. The caller's side (the
HTTP route, the gRPC handler, the pool) holds a :class:`Deadline` and may :meth:`~Deadline.cancel`
it when the client goes away or the time runs out; the worker calls :meth:`~Deadline.check`
between stages and gives its thread back with :class:`~catalign.errors.DeadlineExceededError`.
The cost of a stage is bounded by the input checks, so a check between stages is enough.
"""

from __future__ import annotations

import math
import threading
import time

from catalign.errors import DeadlineExceededError


class Deadline:
    """Time left for one request, and whether somebody stopped waiting for it.

    ``seconds`` counts from construction; ``None`` or ``inf`` never expires (only
    :meth:`cancel` stops the work).
    """

    def __init__(self, seconds: float | None) -> None:
        self.seconds = math.inf if seconds is None else float(seconds)
        self._at = time.monotonic() + self.seconds
        self._reason: str | None = None
        self._lock = threading.Lock()

    @property
    def remaining(self) -> float:
        """Seconds left (0 when expired; ``inf`` without a limit)."""
        return max(0.0, self._at - time.monotonic())

    @property
    def expired(self) -> bool:
        return self._reason is not None or time.monotonic() >= self._at

    def cancel(self, reason: str) -> None:
        """Stop the work at its next check (the first reason given is kept)."""
        with self._lock:
            if self._reason is None:
                self._reason = reason

    def check(self) -> None:
        """Raise :class:`DeadlineExceededError` if cancelled or out of time."""
        if self._reason is not None:
            raise DeadlineExceededError(self._reason)
        if time.monotonic() >= self._at:
            self.cancel(f"the request ran past its deadline of {self.seconds:g} s")
            raise DeadlineExceededError(self._reason or "deadline exceeded")
