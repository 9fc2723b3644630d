"""SDK clients registering a view back to back through a load balancer, every call recorded.

Used by ``tests/deploy/test_replicas.py``, ``tests/deploy/test_failover.py`` and
``bench/failover.py``: ``clients`` threads, each with its own :class:`catalign_client.Client`,
call ``align`` until stopped; each call's start, end and error (any exception the SDK raises
is a failure the caller would see) is kept, and the SDK's own retries are counted from its
log (the ``catalign_client`` logger's "retry n of m" lines), by reason (``502 Bad Gateway``...).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

import catalign_client as sdk
from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.geometry.se3 import make_pose

UP = (0.0, 0.0, 1.0)


def chair_view(seed: int, yaw: float = 0.7, step: int = 2) -> np.ndarray:
    """Chair ``seed`` on the floor (+Z up) seen from 2 m, as tests/api/conftest.py renders it."""
    shape = procedural_shape(seed)
    pose = make_pose(upright_rotation(yaw), np.array([0.3, -0.2, -shape.points[:, 1].min()]))
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    points = render_view(shape, pose, camera, np.random.default_rng(seed))
    return np.ascontiguousarray(points[::step], dtype=np.float32)


@dataclass(frozen=True)
class Call:
    """One SDK call: when it started and ended (``time.monotonic()``), and its error if any."""

    started: float
    ended: float
    error: str | None = None

    @property
    def ms(self) -> float:
        return (self.ended - self.started) * 1e3


class RetryLog(logging.Handler):
    """Counts the SDK's retries by reason while attached to the ``catalign_client`` logger."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.reasons: Counter[str] = Counter()
        self._lock_reasons = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if "; retry " in message:  # "POST /register: 502 Bad Gateway; retry 1 of 2 in 0.13 s"
            reason = message.split("; retry ", 1)[0].split(": ", 1)[-1]
            with self._lock_reasons:
                self.reasons[reason] += 1


class Load:
    """``clients`` SDK clients registering ``points`` through ``url`` back to back, from start
    until :meth:`stop` (at most ``limit_s``); ``retries`` and ``timeout`` go to each client."""

    def __init__(
        self,
        url: str,
        points: np.ndarray,
        clients: int,
        limit_s: float,
        *,
        retries: int = 2,
        timeout: float = 60.0,
    ) -> None:
        self.url, self.points = url, points
        self.retries, self.timeout = retries, timeout
        self.calls: list[Call] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._end = time.monotonic() + limit_s
        self._log = RetryLog()
        self._logger = logging.getLogger("catalign_client")
        self._level = self._logger.level
        self._logger.addHandler(self._log)
        self._logger.setLevel(logging.INFO)
        self.started = time.monotonic()
        self._threads = [threading.Thread(target=self._client) for _ in range(clients)]
        for thread in self._threads:
            thread.start()

    def _client(self) -> None:
        with sdk.Client(self.url, timeout=self.timeout, retries=self.retries) as client:
            while not self._stop.is_set() and time.monotonic() < self._end:
                started, error = time.monotonic(), None
                try:
                    client.align(self.points, up=UP, seed=0)
                except sdk.CatalignError as caught:
                    error = repr(caught)
                with self._lock:
                    self.calls.append(Call(started, time.monotonic(), error))

    @property
    def ok(self) -> int:
        return sum(call.error is None for call in self.done())

    @property
    def failures(self) -> list[str]:
        return [call.error for call in self.done() if call.error is not None]

    @property
    def retry_reasons(self) -> Counter[str]:
        return Counter(self._log.reasons)

    def done(self) -> list[Call]:
        with self._lock:
            return list(self.calls)

    def wait_for(self, calls: int, since: float, timeout: float) -> None:
        """Wait until ``calls`` calls that started after ``since`` have succeeded."""
        deadline = time.monotonic() + timeout
        while sum(c.error is None and c.started > since for c in self.done()) < calls:
            if time.monotonic() > deadline:
                raise AssertionError(f"fewer than {calls} calls succeeded in {timeout:.0f} s")
            time.sleep(0.1)

    def stop(self, at_least_s: float = 0.0) -> None:
        """Stop once the load has run ``at_least_s`` seconds in all; wait for the clients."""
        time.sleep(max(0.0, min(self.started + at_least_s, self._end) - time.monotonic()))
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=90)
        self._logger.removeHandler(self._log)
        self._logger.setLevel(self._level)

    def __enter__(self) -> Load:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q`` percentile (0 to 100) of ``values``, NaN for none."""
    return float(np.percentile(values, q)) if len(values) else float("nan")
