"""The service behind both front doors (HTTP and gRPC): engine, worker pool, library changes.

:class:`RegistrationService` loads the extractor and the library once, runs every registration
on the bounded :class:`~catalign.api.pool.WorkPool`, and serialises library changes: each change
is written with :mod:`catalign.library` (atomic on disk), the library is loaded again and a new
:class:`Served` (the extractor, the library and, where registrations run on the server's own
threads, an :class:`~catalign.registration.engine.Engine`; worker processes build their own)
replaces the old one in a single assignment, so requests already running finish on the library
they started with. Changes made by another process (``catalign library add`` on the served
folder) are noticed by the catalogue's stamp (its generation, one more at every committed
write) and loaded before the next request that reads the library. Every registration runs
under a :class:`~catalign.deadline.Deadline` of ``deadline_s`` from its arrival, so neither a
slow request nor a client that went away holds a worker longer than that. torch and open3d are
imported only when the service loads, never by the HTTP layer itself.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from catalign.api.about import service_info
from catalign.api.errors import BusyError, EmptyLibraryError, ModelExistsError
from catalign.api.inputs import PointQuery, Upload, check_cloud, shown_as
from catalign.api.metrics import Metrics
from catalign.api.pool import Slot, WorkPool
from catalign.api.processes import EngineProcesses, Job, served_engine, warm_up
from catalign.api.schemas import InfoResponse
from catalign.api.settings import ServiceSettings
from catalign.api.spool import Spool
from catalign.deadline import Deadline
from catalign.errors import (
    CatalignError,
    ConfigError,
    DeadlineExceededError,
    LibraryChangedError,
)
from catalign.library.store import Stamp, manifest_stamp
from catalign.threads import limit_threads, release_free_memory

if TYPE_CHECKING:
    from catalign.features.extractor import LearnedExtractor
    from catalign.library.entry import LibraryEntry
    from catalign.library.loaded import Library
    from catalign.registration.engine import Engine
    from catalign.registration.results import RegistrationResult

logger = logging.getLogger(__name__)

# Times a registration starts again on the library as it is now when an entry it shortlisted
# was replaced or removed on disk while it ran (each start loads the changed library first).
_CHANGED_RETRIES = 3


@dataclasses.dataclass(frozen=True)
class Served:
    """What the server process serves, replaced in one assignment on a library change: the
    extractor, the library, and the engine when registrations run on the server's own threads
    (None with worker processes, which build their own)."""

    extractor: LearnedExtractor
    library: Library
    engine: Engine | None


class RegistrationService:
    """Registrations and library changes for one extractor and one library folder."""

    def __init__(self, settings: ServiceSettings, metrics: Metrics) -> None:
        self.settings = settings
        self.metrics = metrics
        self.ready = False
        self._served: Served | None = None
        self._pool: WorkPool | None = None
        self._processes: EngineProcesses | None = None
        self._changes = asyncio.Lock()
        self._stamp: Stamp | None = None
        self.spool = Spool(settings.spool_dir, library=settings.library)

    # life cycle -------------------------------------------------------------------------------

    async def start(self) -> None:
        """Load weights and library (off the event loop); errors here stop the server."""
        threads, workers = self.settings.worker_threads, self.settings.workers
        self._pool = WorkPool(
            workers,
            self.settings.queue,
            self.metrics,
            initializer=partial(limit_threads, threads, total=threads * workers, niceness=5),
            max_wait_s=self.settings.deadline_s,
        )
        await asyncio.to_thread(self.spool.open)
        await asyncio.to_thread(self._load)
        if self.settings.worker_processes:
            self._processes = await asyncio.to_thread(
                EngineProcesses, self.settings, workers, threads=threads, niceness=5
            )

    async def warm_up(self) -> None:
        """One registration on a worker thread so that the first real request is not the slow
        one (worker processes warmed up as they started)."""
        try:
            if self.settings.warmup and self._processes is None:
                await asyncio.wrap_future(self.pool.submit(warm_up, self.served.engine))
        except CatalignError as error:
            logger.warning("warm-up registration refused: %s", error)
        self.ready = True
        logger.info("ready: %d models, %d workers", len(self.library), self.pool.workers)

    async def close(self) -> None:
        self.ready = False
        if self._pool is not None:
            await asyncio.to_thread(self._pool.shutdown)
        if self._processes is not None:
            await asyncio.to_thread(self._processes.close)
        await asyncio.to_thread(self.spool.close)

    @property
    def served(self) -> Served:
        if self._served is None:
            raise ConfigError("the service has not loaded its model and library yet")
        return self._served

    @property
    def pool(self) -> WorkPool:
        if self._pool is None:
            raise ConfigError("the service has not started yet")
        return self._pool

    @property
    def library(self) -> Library:
        return self.served.library

    # queries ----------------------------------------------------------------------------------

    def ensure_capacity(self) -> None:
        """Refuse early (before reading a body) when the queue is already full."""
        self.pool.ensure_capacity()

    def refusal(self, method: str, path: str) -> BusyError | None:
        """Busy for a registration that would find the queue full (checked before routing)."""
        if method == "POST" and path == "/register" and self._pool is not None:
            return self._pool.refusal()
        return None

    def reserve(self) -> Slot:
        """A place in the worker pool for one request, taken before its body is read."""
        return self.pool.reserve()

    async def register(
        self, query: PointQuery, *, slot: Slot | None = None, deadline_s: float | None = None
    ) -> RegistrationResult:
        """Register a query on a worker (in ``slot``, or a new one); timings gain ``queue``,
        ``read`` (files) and ``total``.

        The deadline is the server's ``deadline_s``, or ``deadline_s`` when the caller's is
        shorter (a gRPC deadline); a caller that stops waiting (a cancelled task) stops the work.
        """
        deadline = Deadline(min(self.settings.deadline_s, deadline_s or self.settings.deadline_s))
        submitted = time.perf_counter()
        try:
            for attempt in range(_CHANGED_RETRIES + 1):
                await self.refresh(slot)
                served = self.served
                if len(served.library) == 0:
                    raise EmptyLibraryError("the library has no models; add one with POST /models")
                try:
                    result = await self.pool.run(
                        self._register, served, query, submitted, deadline, slot=slot,
                        deadline=deadline,
                    )  # fmt: skip
                    break
                except LibraryChangedError:  # an entry it shortlisted was replaced meanwhile
                    if attempt == _CHANGED_RETRIES:
                        raise
        except DeadlineExceededError:
            self.metrics.stopped.labels("deadline").inc()
            raise
        except asyncio.CancelledError:
            self.metrics.stopped.labels("client_gone").inc()
            raise
        self.metrics.observe_registration(result.timings_ms, result.inlier_ratio)
        return result

    async def model(self, model_id: str) -> LibraryEntry:
        """One model's entry, read from its file (its points, its features...)."""
        return await asyncio.to_thread((await self.current_library()).__getitem__, model_id)

    async def current_library(self) -> Library:
        """The library as it is on disk now (loaded again if another process changed it)."""
        await self.refresh()
        return self.library

    async def refresh(self, slot: Slot | None = None) -> None:
        """Load the library again when another process changed it since it was loaded (on a
        worker, in the caller's ``slot`` when it has one).

        A library that no longer loads (rebuilt with other weights, say) is logged and the one
        in memory stays served: a bad edit on disk must not take the service down.
        """
        if self._stamp == manifest_stamp(self.settings.library):
            return
        async with self._changes:
            stamp = manifest_stamp(self.settings.library)
            if stamp == self._stamp:
                return
            extractor = self.served.extractor
            try:
                library = await self.pool.run(self._reload, extractor, slot=slot)
            except CatalignError as error:
                logger.warning("library changed on disk but cannot be loaded: %s", error)
                self._stamp = stamp
                return
            self._stamp = stamp  # read before the load: a change during it is loaded next time
            self._served = self._serve(extractor, library)
            self.metrics.library_models.set(len(library))
            logger.info("library changed on disk: now %d models", len(library))
            await asyncio.to_thread(release_free_memory)  # what the old library's engine held

    def info(self) -> InfoResponse:
        return service_info(self.settings, self.served.extractor, self.served.library)

    # library changes --------------------------------------------------------------------------

    async def add_model(
        self, upload: Upload, model_id: str, units: str, category: str | None
    ) -> LibraryEntry:
        """Describe an uploaded shape and add it as ``model_id`` of ``category`` (None: the
        library's default); 409 if the id exists."""
        from catalign.library.sources import unit_factor, validate_category, validate_model_id

        validate_model_id(model_id)
        if category is not None:
            validate_category(category)
        unit_factor(units)

        def check(library: Library) -> None:
            if model_id in library:
                raise ModelExistsError(
                    f"model {model_id!r} is already in the library; remove it first or choose "
                    "another model_id"
                )

        library = await self._change(check, self._add, upload, model_id, units, category)
        return library[model_id]

    async def remove_model(self, model_id: str) -> int:
        """Remove ``model_id``; returns how many models are left."""
        from catalign.library.sources import validate_model_id

        validate_model_id(model_id)

        def check(library: Library) -> None:
            library[model_id]  # ModelNotFoundError

        library = await self._change(check, self._remove, model_id)
        return len(library)

    async def _change(
        self, check: Callable[[Library], None], change: Callable[..., Library], *args: object
    ) -> Library:
        """Run one library change under the lock; shielded, so that a caller who goes away
        cannot leave the disk changed and the served library stale."""
        return await asyncio.shield(self._locked_change(check, change, *args))

    async def _locked_change(
        self, check: Callable[[Library], None], change: Callable[..., Library], *args: object
    ) -> Library:
        async with self._changes:
            extractor = self.served.extractor
            check(self.served.library)
            library = await self.pool.run(change, extractor, *args)
            self._stamp = manifest_stamp(self.settings.library)
            self._served = self._serve(extractor, library)
            self.metrics.library_models.set(len(library))
            await asyncio.to_thread(release_free_memory)  # what the change and old engine freed
            return library

    # worker-side ------------------------------------------------------------------------------

    def _load(self) -> None:
        from catalign.features.extractor import LearnedExtractor

        started = time.perf_counter()
        extractor = LearnedExtractor(self.settings.model_dir, threads=self.settings.worker_threads)
        self._stamp = manifest_stamp(self.settings.library)
        library = self._read_library(extractor)
        self._served = self._serve(extractor, library)
        self.metrics.library_models.set(len(library))
        logger.info(
            "loaded %s and %d models from %s in %.1f s",
            self.settings.model_dir,
            len(library),
            self.settings.library,
            time.perf_counter() - started,
        )

    def _reload(self, extractor: LearnedExtractor) -> Library:
        """The library again, after another process changed it."""
        return self._read_library(extractor)

    def _read_library(self, extractor: LearnedExtractor) -> Library:
        """The library as this process holds it: without the records' outlines when worker
        processes register (they read theirs), since only the shortlist reads them."""
        from catalign.library.loaded import load

        registers = not self.settings.worker_processes
        return load(self.settings.library, extractor.fingerprint, outlines=registers)

    def _serve(self, extractor: LearnedExtractor, library: Library) -> Served:
        """What the server holds: the extractor and the library, and an engine where
        registrations run on its own threads (worker processes build their own)."""
        threads = not self.settings.worker_processes
        engine = served_engine(extractor, library, self.settings) if threads else None
        return Served(extractor, library, engine)

    def _register(
        self, served: Served, query: PointQuery, submitted: float, deadline: Deadline
    ) -> RegistrationResult:
        timings = {"queue": (time.perf_counter() - submitted) * 1e3}
        points = query.points
        if points is None:
            from catalign.geometry.io import read_points

            assert query.path is not None
            started = time.perf_counter()
            max_points = self.settings.max_points
            with shown_as(query.path, query.filename):
                points = check_cloud(read_points(query.path, max_points=max_points), max_points)
            timings["read"] = (time.perf_counter() - started) * 1e3
        options = query.options
        engine_options = {
            "top_k": options.top_k,
            "up": None if options.up is None else np.asarray(options.up, dtype=np.float64),
            "estimate_scale": options.estimate_scale,
            "seed": options.seed,
            "category": options.category,
        }
        if served.engine is not None:
            result = served.engine.register(points, **engine_options, deadline=deadline)
        else:
            job = Job(points, engine_options, deadline.remaining, self._stamp)
            result = self._processes.register(job, deadline)
        timings |= result.timings_ms
        timings["total"] = (time.perf_counter() - submitted) * 1e3
        return dataclasses.replace(result, timings_ms=timings, correspondences=None)

    def _add(
        self,
        extractor: LearnedExtractor,
        upload: Upload,
        model_id: str,
        units: str,
        category: str | None,
    ) -> Library:
        from catalign.library.index import add

        # Keep the suffix (it selects the reader), and record the upload's own name as source.
        source = upload.path.rename(upload.path.with_name(model_id + upload.path.suffix.lower()))
        with shown_as(source, upload.filename):
            add(
                self.settings.library,
                [source],
                extractor,
                ids=[model_id],
                units=units,
                category=category,
                progress=False,
                source_name=f"upload:{upload.filename}",
                max_points=self.settings.max_points,
            )
        logger.info("added model %s to %s", model_id, self.settings.library)
        return self._read_library(extractor)

    def _remove(self, extractor: LearnedExtractor, model_id: str) -> Library:
        from catalign.library.index import remove

        remove(self.settings.library, [model_id])
        logger.info("removed model %s from %s", model_id, self.settings.library)
        return self._read_library(extractor)
