"""Describing many entries: on every core, and journalled so that a killed build resumes.

A build's slow part is describing each shape (sampling, features, symmetry, distance grid).
:func:`describe_all` runs the jobs in worker processes, one torch thread each, when there are
several cores and the extractor can be loaded again from its folder; each worker writes its
entry file itself (content-addressed, atomic) and hands back only the small record.

Every finished entry is appended to a journal in the library folder
(``.build-journal.jsonl``: a header that names what the entries depend on, then one record per
line, each flushed and fsynced). A build run again with the same sources, weights and options
reads it and skips each entry whose file is still there with its checksum and whose source file
has not changed; the journal goes once the catalogue that references the entries is committed.
A torn last line (the build killed mid-write) is ignored.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm import tqdm

from catalign.library.entry import LibraryEntry, file_sha256
from catalign.library.store import EntryRecord, write_entry

if TYPE_CHECKING:
    from catalign.features.extractor import FeatureExtractor

logger = logging.getLogger(__name__)

JOURNAL_NAME = ".build-journal.jsonl"
# Models a worker process must have to describe to be worth starting.
JOBS_PER_WORKER = 8


@dataclass(frozen=True)
class Job:
    """One entry to describe: its id, a label for messages (its source), the file it is read
    from (None for generated shapes), and the work, given an extractor."""

    model_id: str
    label: str
    path: Path | None
    describe: Callable[[FeatureExtractor], LibraryEntry]


class BuildJournal:
    """The entries a build has finished, kept beside them until the catalogue names them."""

    def __init__(self, library_dir: Path, depends_on: Mapping[str, Any]) -> None:
        self.path = library_dir / JOURNAL_NAME
        self.library_dir = library_dir
        self.header = {"journal": 1, **depends_on}
        self.finished: dict[str, tuple[str, EntryRecord]] = self._read()
        self._handle = None

    def reusable(self, job: Job) -> EntryRecord | None:
        """The record of ``job`` from an earlier run, if its file and source are unchanged."""
        label, record = self.finished.get(job.model_id, ("", None))
        if record is None or label != job.label:
            return None
        entry_file = self.library_dir / record.file
        if not entry_file.is_file() or file_sha256(entry_file) != record.sha256:
            return None
        if job.path is not None and (
            not job.path.is_file() or file_sha256(job.path) != record.source_sha256
        ):
            return None
        return record

    def append(self, job: Job, record: EntryRecord) -> None:
        if self._handle is None:
            fresh = not self.finished
            self._handle = open(self.path, "w" if fresh else "a")  # noqa: SIM115
            if fresh:
                self._write_line(self.header)
        line = {"model_id": job.model_id, "label": job.label, "record": record.to_json()}
        self._write_line(line)

    def done(self) -> None:
        """The catalogue holds every entry now: the journal is not needed any more."""
        self.close()
        self.path.unlink(missing_ok=True)

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def _write_line(self, data: Mapping[str, Any]) -> None:
        assert self._handle is not None
        self._handle.write(json.dumps(data) + "\n")
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def _read(self) -> dict[str, tuple[str, EntryRecord]]:
        if not self.path.is_file():
            return {}
        lines = self.path.read_text(errors="replace").splitlines()
        try:
            header = json.loads(lines[0]) if lines else None
        except json.JSONDecodeError:
            header = None
        if header != self.header:
            logger.info("%s is of another build: starting afresh", self.path)
            self.path.unlink()
            return {}
        finished = {}
        for line in lines[1:]:
            try:
                data = json.loads(line)
                model_id = data["model_id"]
                finished[model_id] = (
                    data["label"],
                    EntryRecord.from_json(model_id, data["record"]),
                )
            except (ValueError, KeyError, TypeError):
                continue  # a line torn by a kill: that entry is described again
        return finished


def describe_all(
    library_dir: Path,
    jobs: list[Job],
    extractor: FeatureExtractor,
    *,
    workers: int = 1,
    journal: BuildJournal | None = None,
    progress: bool = True,
) -> Iterator[tuple[Job, EntryRecord]]:
    """Describe ``jobs`` and write their entry files; yields each job with its record as it
    finishes (reused from ``journal`` where it can be), appending new ones to the journal."""
    todo = []
    for job in jobs:
        record = journal.reusable(job) if journal is not None else None
        if record is None:
            todo.append(job)
        else:
            yield job, record
    if len(jobs) > len(todo):
        logger.info(
            "resuming: %d of %d entries were finished before", len(jobs) - len(todo), len(jobs)
        )
    model_dir = getattr(extractor, "model_dir", None)
    # A worker process costs seconds to start (torch and the weights): few models stay here.
    workers = min(workers, len(todo) // JOBS_PER_WORKER) if model_dir is not None else 1
    workers = max(workers, 1)
    bar = tqdm(
        total=len(jobs),
        initial=len(jobs) - len(todo),
        desc=f"describing models for {library_dir.name}",
        unit="model",
        disable=not progress,
    )
    started = time.perf_counter()
    try:
        finished = (
            _in_processes(library_dir, todo, model_dir, workers)
            if workers > 1
            else ((job, write_entry(library_dir, job.describe(extractor))) for job in todo)
        )
        for job, record in finished:
            if journal is not None:
                journal.append(job, record)
            bar.set_postfix_str(job.model_id, refresh=False)
            bar.update()
            yield job, record
    finally:
        bar.close()
        if journal is not None:
            journal.close()
    elapsed = time.perf_counter() - started
    if todo:
        logger.info(
            "described %d models in %.1f s (%.2f per second, %d worker(s))",
            len(todo), elapsed, len(todo) / max(elapsed, 1e-9), workers,
        )  # fmt: skip


def depends_on(extractor: FeatureExtractor, **options: Any) -> dict[str, Any]:
    """What a journalled entry depends on besides its source: the weights and the options."""
    digest = hashlib.sha256(json.dumps(options, sort_keys=True, default=str).encode())
    return {"fingerprint": extractor.fingerprint, "options": digest.hexdigest()[:16]}


# A worker process's extractor, loaded once by _start_worker.
_worker_extractor: FeatureExtractor | None = None


def _start_worker(model_dir: Path) -> None:
    global _worker_extractor
    from catalign.features.extractor import LearnedExtractor

    _worker_extractor = LearnedExtractor(model_dir, threads=1)


def _describe_in_worker(library_dir: Path, job: Job) -> EntryRecord:
    assert _worker_extractor is not None
    return write_entry(library_dir, job.describe(_worker_extractor))


def _in_processes(
    library_dir: Path, jobs: list[Job], model_dir: Path, workers: int
) -> Iterator[tuple[Job, EntryRecord]]:
    """Jobs described by ``workers`` processes (spawned: torch and fork do not mix), at most
    two queued per worker so that an interrupted build wastes little."""
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, context, _start_worker, (model_dir,)) as pool:
        pending: dict[Future[EntryRecord], Job] = {}
        queue = iter(jobs)
        try:
            while True:
                while len(pending) < 2 * workers and (job := next(queue, None)) is not None:
                    pending[pool.submit(_describe_in_worker, library_dir, job)] = job
                if not pending:
                    return
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield pending.pop(future), future.result()
        finally:
            for future in pending:
                future.cancel()
