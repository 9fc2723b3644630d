"""The worker pool admits workers + queue jobs, refuses the next at once, and frees every slot."""

from __future__ import annotations

import asyncio
import threading

import pytest

from catalign.api.errors import BusyError
from catalign.api.metrics import Metrics
from catalign.api.pool import WorkPool


def test_admission_is_bounded_and_slots_come_back() -> None:
    release = threading.Event()

    async def scenario() -> None:
        pool = WorkPool(workers=1, queue=1, metrics=Metrics())
        running = asyncio.ensure_future(pool.run(release.wait))
        waiting = asyncio.ensure_future(pool.run(lambda: 42))
        await asyncio.sleep(0.05)
        with pytest.raises(BusyError) as refused:
            await pool.run(lambda: 0)
        assert refused.value.retry_after >= 1 and pool.full
        waiting.cancel()  # its caller went away before a worker took it
        release.set()
        assert await running is True
        with pytest.raises(asyncio.CancelledError):
            await waiting
        await asyncio.sleep(0.05)
        assert not pool.full
        assert await pool.run(lambda: 7) == 7
        assert pool._admitted == 0 and pool._running == 0
        pool.shutdown()

    asyncio.run(scenario())
