"""The CAD library index: build, add, remove, configure and inspect a library directory
(reading it is :mod:`catalign.library.loaded`'s).

Writers describe their shapes under the library's lock and stream each entry to its own file,
then commit: a build its whole catalogue, an add or a remove only the rows it changes, so that
neither reads nor writes the other entries of a large library (see
:mod:`catalign.library.store` for why a crash never leaves a half-written library);
:func:`configure` sets the engine options the library is served with.

Poses found against an entry map the entry's stored coordinates, i.e. its *source coordinates
converted to metres* (``source * unit_factor(units)``), into the observation.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from catalign.data.shapes import procedural_id
from catalign.errors import (
    InvalidInputError,
    LibraryError,
    ModelNotFoundError,
)
from catalign.library.builder import BuildJournal, Job, depends_on, describe_all
from catalign.library.entry import SURFACE_POINTS, describe_file, describe_procedural
from catalign.library.loaded import check_fingerprint
from catalign.library.shortlist_index import (
    IndexSummary,
    stale_limit,
    waiting_entries,
    write_index,
)
from catalign.library.sources import DEFAULT_CATEGORY, collect_sources, unit_factor
from catalign.library.store import (
    EntryRecord,
    Manifest,
    begin_write,
    commit,
    commit_changes,
    count_entries,
    has_manifest,
    list_ids,
    read_manifest,
    sweep,
    utc_now,
    writer_lock,
)

if TYPE_CHECKING:  # the extractor module imports torch; the index only needs its interface
    from catalign.features.extractor import FeatureExtractor

logger = logging.getLogger(__name__)
T = TypeVar("T")


def build(
    sources: Sequence[str | Path],
    out_dir: str | Path,
    extractor: FeatureExtractor,
    *,
    units: str = "m",
    ids: Sequence[str] | None = None,
    category: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    num_points: int = SURFACE_POINTS,
    workers: int = 1,
) -> Manifest:
    """Build a library in ``out_dir`` from shape files and folders (folders recursively).

    Every entry is of ``category``; without it, of the sub-folder it sits in under a named
    folder, else a chair (:func:`~catalign.library.sources.collect_sources`). Refuses a
    directory that already holds a library (of this format or the one before) unless
    ``overwrite``; the old library stays usable until the new catalogue is committed.
    ``workers`` processes describe the shapes; a build killed half-way and run again resumes
    (:mod:`catalign.library.builder`).
    """
    unit_factor(units)
    found = collect_sources(sources, ids, category)
    jobs = [
        Job(
            s.model_id,
            str(s.path),
            s.path,
            partial(describe_file, s, units=units, num_points=num_points),
        )
        for s in found
    ]
    return _build(
        Path(out_dir),
        extractor,
        jobs,
        overwrite=overwrite,
        progress=progress,
        category=category or DEFAULT_CATEGORY,
        workers=workers,
        depends=depends_on(extractor, units=units, category=category, num_points=num_points),
    )


def build_procedural(
    out_dir: str | Path,
    extractor: FeatureExtractor,
    count: int,
    first_seed: int = 0,
    *,
    overwrite: bool = False,
    progress: bool = True,
    num_points: int = SURFACE_POINTS,
    workers: int = 1,
) -> Manifest:
    """Build a library of ``count`` procedural chairs (ids ``proc-NNNN``, source
    ``procedural:<seed>``), as shipped in ``model_store/library``."""
    if count < 1:
        raise InvalidInputError(f"a procedural library needs at least one chair, got {count}")
    jobs = [
        Job(
            procedural_id(seed),
            f"procedural:{seed}",
            None,
            partial(describe_procedural, seed, num_points=num_points),
        )
        for seed in range(first_seed, first_seed + count)
    ]
    return _build(
        Path(out_dir),
        extractor,
        jobs,
        overwrite=overwrite,
        progress=progress,
        category=DEFAULT_CATEGORY,
        workers=workers,
        depends=depends_on(extractor, procedural=True, num_points=num_points),
    )


def add(
    library_dir: str | Path,
    sources: Sequence[str | Path],
    extractor: FeatureExtractor,
    *,
    units: str = "m",
    ids: Sequence[str] | None = None,
    category: str | None = None,
    replace: bool = False,
    progress: bool = True,
    num_points: int = SURFACE_POINTS,
    source_name: str | None = None,
    max_points: int | None = None,
) -> dict[str, EntryRecord]:
    """Add entries to an existing library, or with ``replace`` replace those whose id exists;
    returns the records written, by id (not the whole library: at 10^5 entries reading every
    record costs more than the add).

    ``category`` is as :func:`build`'s; without it, a file not in a category's sub-folder gets
    the library's default category (its catalogue's ``category``). Adding an id the library
    already holds without ``replace`` raises InvalidInputError and changes nothing.
    ``source_name`` is recorded as the source of a single added file instead of its path (the
    service names uploads so, not by their temporary files); files with more than
    ``max_points`` points or vertices are refused (the service's upload limit).
    """
    library_dir = Path(library_dir)
    unit_factor(units)
    header = read_manifest(library_dir, ids=())  # no library: fail before the lock creates a file
    found = collect_sources(sources, ids, category, default=header.category)
    if source_name is not None and len(found) != 1:
        raise InvalidInputError(f"source_name names one file, but {len(found)} were given")
    jobs = [
        Job(
            s.model_id,
            str(s.path),
            s.path,
            partial(
                describe_file,
                s,
                units=units,
                num_points=num_points,
                source_name=source_name,
                max_points=max_points,
            ),
        )
        for s in found
    ]
    with writer_lock(library_dir):
        current = read_manifest(library_dir, ids=[job.model_id for job in jobs])
        check_fingerprint(current, extractor.fingerprint, library_dir)
        _check_new_ids(current, jobs, replace, library_dir)
        now = utc_now()

        def commit_added(records: dict[str, EntryRecord]) -> dict[str, EntryRecord]:
            commit_changes(library_dir, put=records, updated=now)
            return records

        records = _describe(library_dir, extractor, jobs, commit_added, progress=progress)
        _index_again_if_stale(library_dir)
    logger.info("wrote %d model(s) to %s", len(records), library_dir)
    return records


def _index_again_if_stale(library_dir: Path) -> None:
    """After an add, under its lock: write the shortlist's index again once more entries wait
    for it than :func:`~catalign.library.shortlist_index.stale_limit` allows (logged)."""
    entries = count_entries(library_dir)
    waiting = waiting_entries(library_dir, entries)
    if waiting <= stale_limit(entries):
        return
    logger.info("%d of %d entries wait for the shortlist index: writing it", waiting, entries)
    write_index(library_dir, read_manifest(library_dir).entries)
    commit_changes(library_dir)  # serving processes load the library again, with the index


def remove(library_dir: str | Path, ids: Sequence[str]) -> int:
    """Remove entries by id and return how many are left; an unknown id raises
    ModelNotFoundError and changes nothing."""
    library_dir = Path(library_dir)
    ids = list(dict.fromkeys([ids] if isinstance(ids, str) else ids))
    if not ids:
        raise InvalidInputError("no model ids given to remove")
    read_manifest(library_dir, ids=())  # no library: fail before the lock creates a file
    with writer_lock(library_dir):
        current = read_manifest(library_dir, ids=ids)
        missing = [i for i in ids if i not in current.entries]
        if missing:
            raise ModelNotFoundError(
                f"no model {missing[0]!r} in the library ({count_entries(library_dir)} models)"
            )
        commit_changes(library_dir, drop=ids, updated=utc_now())
        left = count_entries(library_dir)
    logger.info("removed %d model(s) from %s; %d left", len(ids), library_dir, left)
    return left


def reindex(
    library_dir: str | Path,
    threads: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> IndexSummary:
    """Write the shortlist's index anew over every entry (``threads`` 0: every core), then
    commit one generation more so that serving processes load the library again, with it.
    Adds and removes wait meanwhile (about 6 s at 10^5 entries on 2 cores)."""
    library_dir = Path(library_dir)
    read_manifest(library_dir, ids=())  # no library: fail before the lock creates a file
    with writer_lock(library_dir):
        written = write_index(library_dir, read_manifest(library_dir).entries, threads, progress)
        commit_changes(library_dir)
    return written


def configure(
    library_dir: str | Path,
    options: Mapping[str, Any],
    *,
    clear: bool = False,
    combine: Callable[[dict[str, Any], Mapping[str, Any]], dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Set engine options the library is served with (``clear``: drop the ones it had first)
    and return those it now has; the entries are untouched. The library stores the options as
    plain data; ``combine``, given the options it has and the new ones, returns those to store
    or refuses bad ones before anything is written (the command line merges and checks them as
    the engine's configuration, which this layer does not import; without it the new ones
    replace the old key by key)."""
    library_dir = Path(library_dir)
    read_manifest(library_dir, ids=())  # no library: fail before the lock creates a file
    with writer_lock(library_dir):
        current = read_manifest(library_dir, ids=())
        had = {} if clear else dict(current.engine)
        engine = had | dict(options) if combine is None else combine(had, options)
        commit_changes(library_dir, updated=utc_now(), engine=engine)
    logger.info("library %s served with engine options %s", library_dir, engine or "(defaults)")
    return engine


def info(library_dir: str | Path) -> Manifest:
    """The catalogue (extractor, timestamps, one record per entry) without reading any
    array."""
    return read_manifest(Path(library_dir))


def list_models(library_dir: str | Path) -> list[str]:
    """Sorted model ids of a library, from its catalogue alone."""
    return list_ids(Path(library_dir))


def _build(
    library_dir: Path,
    extractor: FeatureExtractor,
    jobs: list[Job],
    *,
    overwrite: bool,
    progress: bool,
    category: str,
    workers: int,
    depends: dict[str, Any],
) -> Manifest:
    """Describe ``jobs`` into a new library whose entries added later without a category are
    of ``category``, journalled by what its entries depend on (``depends``), so that a killed
    build resumes."""
    with writer_lock(library_dir):
        if has_manifest(library_dir) and not overwrite:
            raise LibraryError(
                f"{library_dir} already holds a library; pass overwrite=True (--overwrite) "
                "to replace it, or add to it with `catalign library add`"
            )
        now = utc_now()
        journal = BuildJournal(library_dir, depends)

        def commit_all(records: dict[str, EntryRecord]) -> Manifest:
            manifest = Manifest(
                fingerprint=extractor.fingerprint,
                voxel_size=float(extractor.voxel_size),
                created=now,
                updated=now,
                entries=records,
                category=category,
            )
            # the index first: a reader between the two scores the new entries exactly
            write_index(library_dir, records, threads=workers)
            commit(library_dir, manifest)
            return manifest

        manifest = _describe(
            library_dir, extractor, jobs, commit_all, progress, workers=workers, journal=journal
        )
        journal.done()
    logger.info("wrote %d model(s) to %s", len(jobs), library_dir)
    return manifest


def _describe(
    library_dir: Path,
    extractor: FeatureExtractor,
    jobs: list[Job],
    then: Callable[[dict[str, EntryRecord]], T],
    progress: bool,
    *,
    workers: int = 1,
    journal: BuildJournal | None = None,
) -> T:
    """Describe ``jobs``, write their entry files and hand their records to ``then``, which
    commits them; a failure that is not journalled tidies at once what it wrote."""
    written: set[str] = set()
    records: dict[str, EntryRecord] = {}
    begin_write(library_dir)
    try:
        described = describe_all(
            library_dir, jobs, extractor, workers=workers, journal=journal, progress=progress
        )
        for job, record in described:
            written.add(record.file)
            records[job.model_id] = record
            logger.debug("described %s from %s", job.model_id, job.label)
        return then(records)
    except Exception:
        if journal is None:  # a journalled build keeps its entries for the next run
            _clean_after_failure(library_dir, written)
        raise


def _check_new_ids(
    manifest: Manifest, jobs: Sequence[Job], replace: bool, library_dir: Path
) -> None:
    if replace:
        return
    for job in jobs:
        if job.model_id in manifest.entries:
            raise InvalidInputError(
                f"model {job.model_id!r} (from {job.label}) is already in the library at "
                f"{library_dir} (from {manifest.entries[job.model_id].source}); "
                "pass replace=True (--replace) to replace it, or give it another id"
            )


def _clean_after_failure(library_dir: Path, written: set[str]) -> None:
    """Best effort: drop files a failed write left, keeping all the committed catalogue uses."""
    try:
        try:
            sweep(library_dir)
        except LibraryError:  # no (usable) catalogue: only delete what this write created
            for name in written:
                (library_dir / name).unlink(missing_ok=True)
    except OSError as exc:
        logger.warning("could not clean up after a failed write to %s: %s", library_dir, exc)
