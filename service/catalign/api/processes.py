"""Registration worker processes: one engine per process, so that workers do not share a GIL.

The engine's Python between its numeric kernels holds the GIL, so two worker threads of one
process wait for each other: ``bench/workers.py`` measured two threads at 1.41x the throughput of
one request at a time, and two processes at 2.16x, for twice the memory. :class:`EngineProcesses`
starts ``count`` spawned processes, each loading the weights and the library itself; a worker
thread of the :class:`~catalign.api.pool.WorkPool` hands one registration at a time to an idle
process over a pipe and waits (the GIL released) for the answer. Admission, queueing and
deadlines stay in the server process; the pool has as many threads as there are processes, so a
thread always finds one idle.

* **Library changes**: every job carries the stamp of the library the server serves; a process
  whose library is older loads it from disk first (entries are immutable files, so this is the
  same load as the server's own), then hands the memory the old engine held back to the system.
* **Deadlines**: a job carries its time left, and its :class:`~catalign.deadline.Deadline`'s
  cancellation (the client went away) reaches the process through a shared event, which the
  engine checks between its stages as it checks its own clock.
* **Failures**: an error raised by the engine is raised again in the server, as from a thread.
  A process that dies (killed, out of memory) is replaced, and its request is answered 503. A
  process whose server died sees its pipe close and exits.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import pickle
import queue
import time
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from multiprocessing.synchronize import Event
from typing import TYPE_CHECKING, Any

import numpy as np

from catalign.api.errors import BusyError
from catalign.deadline import Deadline
from catalign.errors import CatalignError
from catalign.library.store import manifest_stamp
from catalign.registration.config import served_config

if TYPE_CHECKING:
    from catalign.api.settings import ServiceSettings
    from catalign.features.extractor import FeatureExtractor
    from catalign.library.loaded import Library
    from catalign.registration.engine import Engine
    from catalign.registration.results import RegistrationResult

logger = logging.getLogger(__name__)

# How often a waiting worker thread passes its request's cancellation on to the process.
_POLL_S = 0.05
# A process that is not ready this long after it started has failed to start.
_START_TIMEOUT_S = 300.0
_CANCELLED = "the caller went away"


@dataclass(frozen=True)
class Job:
    """One registration for a process: the query, the engine's options, the time left and the
    stamp of the library it must run against."""

    points: np.ndarray
    options: dict[str, Any]
    seconds: float
    library_stamp: object


class _Shared(Deadline):
    """A deadline that a process's server side can also cancel, through a shared event."""

    def __init__(self, seconds: float, cancelled: Event) -> None:
        super().__init__(seconds)
        self._cancelled = cancelled

    def check(self) -> None:
        if self._cancelled.is_set():
            self.cancel(_CANCELLED)
        super().check()


class _Process:
    """One worker process and the server's end of its pipe."""

    def __init__(self, settings: ServiceSettings, threads: int, niceness: int) -> None:
        context = multiprocessing.get_context("spawn")
        self.connection, child = context.Pipe()
        self.cancelled = context.Event()
        self.process = context.Process(
            target=serve,
            args=(child, self.cancelled, settings, threads, niceness),
            name="catalign-engine",
            daemon=True,
        )
        self.process.start()
        child.close()

    def wait_ready(self) -> None:
        """Block until the process has loaded and warmed up; its start-up error, if any."""
        if not self.connection.poll(_START_TIMEOUT_S):
            raise CatalignError("a registration worker process did not start in time")
        status, detail = self.connection.recv()
        if status != "ready":
            raise detail

    def run(self, job: Job, deadline: Deadline) -> RegistrationResult:
        """The job's result (or its error) from the process; the deadline's cancellation is
        passed on while it runs."""
        self.cancelled.clear()
        self.connection.send(job)
        while not self.connection.poll(_POLL_S):
            if deadline.expired:
                self.cancelled.set()
        status, answer = self.connection.recv()
        if status == "error":
            raise answer
        return answer

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.connection.send(None)
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.connection.close()


class EngineProcesses:
    """``count`` worker processes, each with its own engine on ``settings``' weights and
    library and ``threads`` numeric threads, run ``niceness`` steps below the server."""

    def __init__(
        self, settings: ServiceSettings, count: int, *, threads: int, niceness: int = 0
    ) -> None:
        self._start = (settings, threads, niceness)
        self._idle: queue.SimpleQueue[_Process] = queue.SimpleQueue()
        started = [_Process(settings, threads, niceness) for _ in range(count)]
        try:
            for process in started:
                process.wait_ready()
        except BaseException:
            for process in started:
                process.close()
            raise
        for process in started:
            self._idle.put(process)
        self.count = count

    def register(self, job: Job, deadline: Deadline) -> RegistrationResult:
        """Run ``job`` on an idle process (the caller is one of the pool's worker threads)."""
        process = self._idle.get()
        try:
            return process.run(job, deadline)
        except (EOFError, OSError) as error:
            logger.error(
                "a registration worker process died (exit code %s); starting another",
                process.process.exitcode,
            )
            process.close()
            process = _Process(*self._start)
            process.wait_ready()
            raise BusyError(
                "the worker running this request stopped; retry", retry_after=1
            ) from error
        finally:
            self._idle.put(process)

    def close(self) -> None:
        for _ in range(self.count):
            self._idle.get().close()


def serve(
    connection: Connection, cancelled: Event, settings: ServiceSettings, threads: int, niceness: int
) -> None:
    """A worker process: load, warm up, say ready, then register each job until told to stop
    (None) or until the server's end of the pipe closes."""
    from catalign.features.extractor import LearnedExtractor
    from catalign.library.loaded import load
    from catalign.threads import limit_malloc_arenas, limit_threads, release_free_memory

    try:
        limit_malloc_arenas(2)
        limit_threads(threads, threads, niceness)
        extractor = LearnedExtractor(settings.model_dir, threads=threads)
        stamp = manifest_stamp(settings.library)
        library = load(settings.library, extractor.fingerprint)
        engine = served_engine(extractor, library, settings)
        warm_up(engine)
    except Exception as error:  # the server shows it and stops
        connection.send(("failed", _sendable(error)))
        return
    connection.send(("ready", None))
    while True:
        try:
            job = connection.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            if job.library_stamp != stamp:
                stamp = job.library_stamp
                library = load(settings.library, extractor.fingerprint)
                engine = served_engine(extractor, library, settings)
                release_free_memory()  # what the old engine's caches held
            result = engine.register(
                job.points, **job.options, deadline=_Shared(job.seconds, cancelled)
            )
            answer: tuple[str, object] = ("ok", replace(result, correspondences=None))
        except Exception as error:  # raised again in the server
            answer = ("error", _sendable(error))
        try:
            connection.send(answer)
        except OSError:  # the server is gone
            return


def served_engine(
    extractor: FeatureExtractor, library: Library, settings: ServiceSettings
) -> Engine:
    """An engine on ``library`` with the options it is served with: the library's own under
    the service's (:func:`~catalign.registration.config.served_config`)."""
    from catalign.registration.engine import Engine

    return Engine(
        extractor, library, config=served_config(settings.engine, library.manifest.engine)
    )


def warm_up(engine: Engine, points: int = 3000) -> None:
    """One registration, so that the first real request is not the slow one."""
    started = time.perf_counter()
    if len(engine.library) == 0:
        cube = np.random.default_rng(0).uniform(-0.3, 0.3, size=(points, 3))
        engine.extractor.describe(cube)
    else:
        surface = engine.library[engine.library.ids[0]].points.astype(np.float64)
        engine.register(surface[:: max(1, len(surface) // points)], top_k=1)
    logger.info("warm-up took %.1f s", time.perf_counter() - started)


def _sendable(error: Exception) -> Exception:
    """``error``, or a RuntimeError with its message when it cannot cross the pipe (every
    CatalignError can: its arguments are its message)."""
    try:
        pickle.loads(pickle.dumps(error))
    except Exception:  # any error that does not survive pickling
        return RuntimeError(f"{type(error).__name__}: {error}")
    return error
