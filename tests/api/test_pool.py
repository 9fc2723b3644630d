"""The worker pool admits workers + queue jobs, refuses the next at once, and frees every slot."""

from __future__ import annotations

import asyncio
import os
import platform
import threading
import time
from collections.abc import Iterator
from functools import partial

import pytest

from catalign.api.errors import BusyError
from catalign.api.metrics import Metrics
from catalign.api.pool import WorkPool
from catalign.deadline import Deadline
from catalign.errors import DeadlineExceededError
from catalign.threads import limit_threads, release_free_memory


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


def test_admission_refuses_what_could_not_finish_in_time() -> None:
    """Once a job has measured 0.2 s, one worker and a 0.5 s budget admit a running job and one
    waiting behind it; a third would finish after 0.6 s and is refused."""
    release = threading.Event()

    async def scenario() -> None:
        pool = WorkPool(workers=1, queue=10, metrics=Metrics(), max_wait_s=0.5)
        await pool.run(time.sleep, 0.2)
        admitted = [asyncio.ensure_future(pool.run(release.wait)) for _ in range(2)]
        await asyncio.sleep(0.05)
        assert pool.full
        with pytest.raises(BusyError):
            await pool.run(lambda: 0)
        release.set()
        assert await asyncio.gather(*admitted) == [True, True]
        pool.shutdown()

    asyncio.run(scenario())


def checking_until_stopped(
    deadline: Deadline, started: threading.Event, stopped: threading.Event
) -> str:
    """A job that works in small steps and checks its deadline between them, as the engine
    does; ``stopped`` is set when it gives its thread back."""
    started.set()
    try:
        for _ in range(2_000):
            deadline.check()
            time.sleep(0.005)
        return "finished"
    finally:
        stopped.set()


def test_a_deadline_answers_at_once_and_stops_the_running_job() -> None:
    started, stopped = threading.Event(), threading.Event()

    async def scenario() -> None:
        pool = WorkPool(workers=1, queue=0, metrics=Metrics())
        deadline = Deadline(0.2)
        began = time.monotonic()
        with pytest.raises(DeadlineExceededError, match=r"deadline of 0\.2 s"):
            await pool.run(checking_until_stopped, deadline, started, stopped, deadline=deadline)
        assert time.monotonic() - began < 1.0  # not the job's 10 s
        assert await asyncio.to_thread(stopped.wait, 2.0)  # the worker gave its thread back
        await asyncio.sleep(0.05)
        assert pool._admitted == 0 and pool._running == 0
        pool.shutdown()

    asyncio.run(scenario())


def test_a_caller_that_goes_away_stops_the_running_job() -> None:
    started, stopped = threading.Event(), threading.Event()

    async def scenario() -> None:
        pool = WorkPool(workers=1, queue=0, metrics=Metrics())
        deadline = Deadline(60.0)
        waiting = asyncio.ensure_future(
            pool.run(checking_until_stopped, deadline, started, stopped, deadline=deadline)
        )
        assert await asyncio.to_thread(started.wait, 2.0)
        waiting.cancel()  # e.g. the HTTP client disconnected
        with pytest.raises(asyncio.CancelledError):
            await waiting
        assert await asyncio.to_thread(stopped.wait, 2.0)
        with pytest.raises(DeadlineExceededError, match="went away"):
            deadline.check()
        pool.shutdown()

    asyncio.run(scenario())


def test_a_job_whose_deadline_passed_in_the_queue_never_runs() -> None:
    release = threading.Event()
    ran: list[int] = []

    async def scenario() -> None:
        pool = WorkPool(workers=1, queue=1, metrics=Metrics())
        blocking = asyncio.ensure_future(pool.run(release.wait))
        await asyncio.sleep(0.05)
        with pytest.raises(DeadlineExceededError):
            await pool.run(ran.append, 1, deadline=Deadline(0.1))
        release.set()
        assert await blocking is True
        await asyncio.sleep(0.1)
        assert ran == []
        assert await pool.run(ran.append, 2, deadline=Deadline(5.0)) is None
        assert ran == [2]
        pool.shutdown()

    asyncio.run(scenario())


@pytest.fixture
def thread_limits_restored() -> Iterator[None]:
    """The limits :func:`limit_threads` sets are process-wide: give the other tests theirs
    back."""
    import open3d
    import torch
    from threadpoolctl import threadpool_info, threadpool_limits

    saved = torch.get_num_threads(), threadpool_info(), open3d.utility.get_max_threads()
    yield
    torch.set_num_threads(saved[0])
    threadpool_limits(limits={pool["prefix"]: pool["num_threads"] for pool in saved[1]})
    open3d.utility.set_max_threads(saved[2])


@pytest.mark.usefixtures("thread_limits_restored")
def test_workers_run_with_the_thread_limits_of_their_share() -> None:
    """Each worker thread gets its thread-pool limits once, before its first job."""
    import open3d
    import torch
    from threadpoolctl import threadpool_info

    def limits() -> tuple[int, dict[str, set[int]], int]:
        counts: dict[str, set[int]] = {}
        for pool in threadpool_info():
            counts.setdefault(pool["user_api"], set()).add(pool["num_threads"])
        return torch.get_num_threads(), counts, open3d.utility.get_max_threads()

    async def scenario() -> None:
        pool = WorkPool(
            workers=2, queue=0, metrics=Metrics(), initializer=partial(limit_threads, 2, total=2)
        )
        torch_threads, counts, open3d_threads = await pool.run(limits)
        assert torch_threads == 2 and counts["blas"] == {1}  # BLAS: one thread whatever the share
        assert counts.get("openmp", {2}) == {2}
        assert open3d_threads == 2
        pool.shutdown()

    asyncio.run(scenario())


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_memory_freed_inside_the_heap_goes_back_to_the_system() -> None:
    """Freed blocks below one still in use stay resident until ``release_free_memory``."""

    def resident() -> int:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    blocks = [bytearray(64 * 1024) for _ in range(1024)]  # 64 MiB from the heap, written
    kept = blocks[-1]  # the last keeps the heap's top in use: free() cannot give the rest back
    del blocks
    before = resident()
    assert release_free_memory() is True
    assert before - resident() > 32 * 2**20
    assert len(kept) == 64 * 1024


@pytest.mark.usefixtures("thread_limits_restored")
def test_icp_takes_the_thread_budget_its_worker_was_given(monkeypatch) -> None:
    """ICP's threads follow the worker's share (one here), not the machine's cores."""
    import catalign.threads

    monkeypatch.setattr(catalign.threads, "_budget", None)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert catalign.threads.worker_threads() == catalign.threads.cores()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # as torch's default follows it
    assert catalign.threads.worker_threads() == 1

    async def scenario() -> int:
        pool = WorkPool(
            workers=1, queue=0, metrics=Metrics(), initializer=partial(limit_threads, 1, total=1)
        )
        try:
            return await pool.run(catalign.threads.worker_threads)
        finally:
            pool.shutdown()

    assert asyncio.run(scenario()) == 1
