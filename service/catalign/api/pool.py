"""A bounded worker pool: CPU work off the event loop, and a fast "busy" instead of a long queue.

Registrations take seconds of CPU; running them on the event loop would stall every other
request, and queueing them without bound would let latency grow without bound. :class:`WorkPool`
runs jobs on ``workers`` threads and admits at most ``workers + queue`` requests at once; one more
is refused immediately with :class:`~catalign.api.errors.BusyError` (503 with ``Retry-After``,
the time the queue ahead takes to drain at the measured mean job duration). A request takes its
:class:`Slot` with :meth:`WorkPool.reserve` *before* its body is read, so a crowd of clients
cannot make the server read and hold more bodies than it will ever run. With ``max_wait_s`` a
request is also refused when the jobs already admitted, at the measured mean duration, would not
let it finish within that time: under load the queue shortens instead of filling with requests
that would only run past their deadline.

A job may carry a :class:`~catalign.deadline.Deadline`. One that expired while it waited is
dropped without running; when it expires while the job runs, or the caller goes away, the
caller is answered at once and the deadline is cancelled, so the job stops at its next check
and frees its worker. ``initializer`` runs once in each worker thread (thread-pool limits).
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import nullcontext
from typing import TypeVar

from catalign.api.errors import BusyError
from catalign.api.metrics import Metrics
from catalign.deadline import Deadline
from catalign.errors import DeadlineExceededError

T = TypeVar("T")
_SMOOTHING = 0.2  # weight of the latest job in the mean job duration


class Slot:
    """One admitted request's place in the pool: taken before its body is read, given back
    when both the request and its job are done (a job may outlive a request answered 503)."""

    def __init__(self, release: Callable[[], None]) -> None:
        self._release = release
        self._holders = 1
        self._lock = threading.Lock()

    def hold(self) -> None:
        with self._lock:
            self._holders += 1

    def release(self) -> None:
        with self._lock:
            self._holders -= 1
            last = self._holders == 0
        if last:
            self._release()

    def __enter__(self) -> Slot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class WorkPool:
    """``workers`` threads, at most ``queue`` jobs waiting; ``run`` awaits a job's result."""

    def __init__(
        self,
        workers: int,
        queue: int,
        metrics: Metrics,
        *,
        initializer: Callable[[], None] | None = None,
        max_wait_s: float | None = None,
    ) -> None:
        self.workers = workers
        self.capacity = workers + queue
        self.max_wait_s = max_wait_s
        self._metrics = metrics
        self._executor = ThreadPoolExecutor(
            workers, thread_name_prefix="catalign-worker", initializer=initializer
        )
        self._lock = threading.Lock()
        self._admitted = 0
        self._running = 0
        self._mean_s: float | None = None  # mean job duration, once one was measured

    @property
    def full(self) -> bool:
        if self._admitted >= self.capacity:
            return True
        if self.max_wait_s is None or self._mean_s is None:
            return False
        # When would one more job finish, the jobs admitted ahead run at the mean duration?
        rounds = self._admitted // self.workers + 1
        return rounds * self._mean_s > self.max_wait_s

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: the queue drained at the mean job duration."""
        mean = 1.0 if self._mean_s is None else self._mean_s
        return max(1, math.ceil(mean * self.capacity / self.workers))

    def reserve(self) -> Slot:
        """A slot for one request (a context manager), or BusyError at once when none is free."""
        self._admit()
        return Slot(self._release)

    async def run(
        self,
        fn: Callable[..., T],
        *args: object,
        slot: Slot | None = None,
        deadline: Deadline | None = None,
    ) -> T:
        """Run ``fn(*args)`` on a worker, in ``slot`` or a new one (BusyError at once when none
        is free); DeadlineExceededError when ``deadline`` passes first (``fn`` should check it
        too)."""
        with self.reserve() if slot is None else nullcontext(slot) as held:
            held.hold()
            try:
                future = self._executor.submit(self._job, fn, args, deadline)
            except BaseException:
                held.release()
                raise
            future.add_done_callback(lambda _: held.release())
        waiting = asyncio.wrap_future(future)
        if deadline is None:
            return await waiting
        # An answer nobody awaits any more is still collected, so asyncio does not warn.
        waiting.add_done_callback(lambda done: done.cancelled() or done.exception())
        remaining = deadline.remaining
        try:
            return await asyncio.wait_for(
                asyncio.shield(waiting), None if math.isinf(remaining) else remaining
            )
        except TimeoutError:
            message = f"the request ran past its deadline of {deadline.seconds:g} s"
            deadline.cancel(message)
            future.cancel()  # not started yet: dropped now
            raise DeadlineExceededError(message, retry_after=self.retry_after()) from None
        except DeadlineExceededError as error:  # the job stopped itself, or never started
            raise DeadlineExceededError(str(error), retry_after=self.retry_after()) from None
        except asyncio.CancelledError:
            deadline.cancel("the caller went away")
            future.cancel()
            raise

    def submit(self, fn: Callable[..., T], *args: object) -> Future[T]:
        """Run ``fn(*args)`` on a worker outside admission control (warm-up)."""
        return self._executor.submit(fn, *args)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    def ensure_capacity(self) -> None:
        """Raise BusyError now if a job would be refused (checked again when it is admitted)."""
        if (refused := self.refusal()) is not None:
            raise refused

    def refusal(self) -> BusyError | None:
        """The BusyError a job would get now, or None while there is room."""
        return self._refuse() if self.full else None

    def _admit(self) -> None:
        with self._lock:
            if self.full:
                raise self._refuse()
            self._admitted += 1
            self._publish()

    def _refuse(self) -> BusyError:
        self._metrics.rejected.inc()
        return BusyError(
            f"all {self.workers} workers are busy and {self.capacity - self.workers} "
            "requests are already waiting; retry later",
            retry_after=self.retry_after(),
        )

    def _job(self, fn: Callable[..., T], args: tuple[object, ...], deadline: Deadline | None) -> T:
        if deadline is not None:
            deadline.check()  # it waited past its deadline in the queue: dropped unrun
        with self._lock:
            self._running += 1
            self._publish()
        started = time.perf_counter()
        try:
            return fn(*args)
        finally:
            elapsed = time.perf_counter() - started
            with self._lock:
                self._running -= 1
                mean = elapsed if self._mean_s is None else self._mean_s
                self._mean_s = mean + _SMOOTHING * (elapsed - mean)
                self._publish()

    def _release(self) -> None:
        with self._lock:
            self._admitted -= 1
            self._publish()

    def _publish(self) -> None:
        self._metrics.queue_depth.set(self._admitted - self._running)
        self._metrics.in_flight.set(self._running)
