"""The library's on-disk format, its crash-safe writes and the lock that serialises writers.

A library is a directory::

    catalogue.sqlite                   format version, extractor, timestamps, one row per entry
                                       (its file, checksums, source, category...): catalogue.py
    entries/<id>-<sha256[:12]>.npz     one entry's arrays, narrowed and compressed (npz.py), read
                                       when the entry is first needed
    .lock                              flock(2)ed by writers
    .writing                           a writer's mark, there until its clean-up is done

Entry files are content-addressed and written to a temporary name, fsynced and renamed, so a
replaced entry never overwrites a file the catalogue references. Their folder is fsynced before
the transaction that names them commits (one transaction, writing only the rows that change);
only after it are the files it released deleted. A crash at any point therefore leaves the last
committed catalogue and every file it names intact; leftovers (temporary files, orphan entries)
are ignored by readers and swept by the next build, or by the next writer that finds an earlier
one's mark still there (a single add or remove does not list the entries folder otherwise).
Readers take no lock: what the catalogue references is never modified, only deleted after a
newer state committed.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import logging
import os
import zipfile
from collections.abc import Collection, Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from catalign.atomic import atomic_write_bytes, fsync_directory
from catalign.errors import LibraryCorruptError
from catalign.geometry.symmetry import YawSymmetry, find_yaw_symmetry
from catalign.library import catalogue
from catalign.library.catalogue import Stamp
from catalign.library.catalogue_db import CATALOGUE_NAME, LEGACY_MANIFEST_NAME, recover
from catalign.library.entry import LibraryEntry
from catalign.library.entry_codec import entry_bytes, entry_from_arrays
from catalign.library.npz import npz_arrays
from catalign.library.outline import outline_of
from catalign.library.records import (
    ENTRIES_DIR,
    FORMAT_VERSION,
    EntryRecord,
    Manifest,
    entry_file_name,
    rebuild_hint,
    vector,
)

__all__ = [
    "CATALOGUE_NAME",
    "ENTRIES_DIR",
    "FORMAT_VERSION",
    "EntryRecord",
    "Manifest",
    "Stamp",
    "entry_file_name",
    "rebuild_hint",
]

logger = logging.getLogger(__name__)

LOCK_NAME = ".lock"
WRITING_NAME = ".writing"
_SWEEP = b"sweep"  # what a writer's mark says when it found an earlier one's left


def utc_now() -> str:
    """The current time as an ISO 8601 UTC string (seconds)."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def has_manifest(library_dir: Path) -> bool:
    """Whether the folder holds a library, of this format or the one before (which
    :mod:`catalign.library.legacy` converts)."""
    return catalogue.exists(library_dir) or (library_dir / LEGACY_MANIFEST_NAME).is_file()


def manifest_stamp(library_dir: Path) -> Stamp | None:
    """What tells one committed state of the library from any other (the catalogue's id and
    generation); None without a readable catalogue. A server compares stamps to notice a change
    made by another process."""
    return catalogue.stamp(library_dir)


def read_manifest(library_dir: Path, ids: Collection[str] | None = None) -> Manifest:
    """Read the catalogue (no entry arrays are read); with ``ids``, only those entries'
    records, which is all that a writer changing a few entries needs of a large library."""
    return catalogue.read(library_dir, ids)[0]


def read_manifest_and_stamp(library_dir: Path, outlines: bool = True) -> tuple[Manifest, Stamp]:
    """The catalogue (its records' outlines left empty unless ``outlines``) and the stamp of
    that very state (a reader compares it to the current one to tell a file deleted by a newer
    write from a missing one)."""
    return catalogue.read(library_dir, outlines=outlines)


def count_entries(library_dir: Path) -> int:
    return catalogue.count(library_dir)


def list_ids(library_dir: Path) -> list[str]:
    return catalogue.ids(library_dir)


def category_counts(library_dir: Path) -> dict[str, int]:
    """How many entries each category holds (``Manifest.categories`` without the records)."""
    return catalogue.category_counts(library_dir)


@contextmanager
def writer_lock(library_dir: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on the library's lock file (threads and processes alike);
    roll back what a killed writer left in the catalogue, and have this writer's commit sweep
    the entries folder if an earlier writer's mark is still there (it died or failed before its
    clean-up)."""
    library_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(library_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            logger.info("waiting for another writer of %s", library_dir)
            fcntl.flock(fd, fcntl.LOCK_EX)
        recover(library_dir)
        mark = library_dir / WRITING_NAME
        if mark.exists():
            mark.write_bytes(_SWEEP)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def begin_write(library_dir: Path) -> None:
    """Mark a write begun, before its first entry file: a writer that dies before its
    clean-up leaves the mark, and the next writer's commit sweeps the entries folder."""
    mark = library_dir / WRITING_NAME
    if not mark.exists():  # else an earlier writer's, which the lock turned into a sweep
        mark.write_bytes(b"")


def write_entry(library_dir: Path, entry: LibraryEntry) -> EntryRecord:
    """Write one entry file (temporary name, fsync, rename) and return its record.

    The caller fsyncs the entries folder (see :func:`commit`) before referencing the file.
    """
    data = entry_bytes(entry)
    sha256 = hashlib.sha256(data).hexdigest()
    relative = entry_file_name(entry.model_id, sha256)
    # same bytes if the name already exists: entry files are content-addressed
    atomic_write_bytes(library_dir / relative, data, sync_directory=False)
    return EntryRecord(
        file=relative,
        sha256=sha256,
        source=entry.source,
        source_sha256=entry.source_sha256,
        units=entry.units,
        num_points=entry.num_points,
        num_keypoints=entry.num_keypoints,
        bbox_min=vector(entry.bbox_min),
        bbox_max=vector(entry.bbox_max),
        size=vector(entry.size),
        category=entry.category,
        symmetry=entry.symmetry.order,
        descriptor=descriptor_bytes(entry.descriptor),
        outline=outline_of(entry.points).to_bytes(),
    )


def descriptor_bytes(descriptor: np.ndarray) -> bytes:
    """A descriptor as its catalogue column holds it: float32, little-endian."""
    return np.ascontiguousarray(descriptor, dtype="<f4").tobytes()


def read_entry(library_dir: Path, model_id: str, record: EntryRecord) -> LibraryEntry:
    """Read one entry file and check it against its record (its checksum, its arrays, the
    descriptor the catalogue holds for it).

    A missing file raises FileNotFoundError (the caller may read the catalogue again: it may have
    changed meanwhile); any other problem raises LibraryCorruptError naming the entry.
    """
    data = (library_dir / record.file).read_bytes()

    def corrupt(problem: str) -> LibraryCorruptError:
        return LibraryCorruptError(
            f"library entry {model_id!r} ({library_dir / record.file}) {problem}; "
            f"restore the file, remove the entry or {rebuild_hint(library_dir)}"
        )

    actual = hashlib.sha256(data).hexdigest()
    if actual != record.sha256:
        raise corrupt(
            f"fails its checksum (sha256 {actual[:12]}..., expected {record.sha256[:12]}...)"
        )
    try:
        arrays = npz_arrays(data)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise corrupt(f"is not a readable .npz file ({exc})") from exc
    try:
        entry = entry_from_arrays(arrays)
    except (KeyError, TypeError, ValueError) as exc:
        raise corrupt(f"is malformed ({type(exc).__name__}: {exc})") from exc
    if entry.model_id != model_id:
        raise corrupt(f"holds model {entry.model_id!r}")
    if (entry.num_points, entry.num_keypoints) != (record.num_points, record.num_keypoints):
        raise corrupt("does not match the point counts in the catalogue")
    if descriptor_bytes(entry.descriptor) != record.descriptor:
        raise corrupt("does not match the descriptor in the catalogue")
    if record.symmetry is None:
        symmetry = find_yaw_symmetry(entry.points)
    else:
        symmetry = YawSymmetry(record.symmetry)
    return dataclasses.replace(entry, category=record.category, symmetry=symmetry)


def commit(library_dir: Path, manifest: Manifest) -> None:
    """Make ``manifest`` the library's state (a build): fsync the new entry files' folder,
    write the rows that differ in one transaction (a new catalogue renamed into place where
    there was none), then delete whatever it no longer references."""
    fsync_entries(library_dir)
    if catalogue.exists(library_dir):
        released = catalogue.replace(library_dir, manifest)
    else:
        catalogue.create(library_dir, manifest)
        released = []
    _tidy(library_dir, released, {r.file for r in manifest.entries.values()})


def commit_changes(
    library_dir: Path,
    *,
    put: Mapping[str, EntryRecord] | None = None,
    drop: Collection[str] = (),
    **library: Any,
) -> None:
    """Change a few entries (an add, a remove) in one transaction that writes only their rows
    and the library row's ``library`` fields (``updated``, ``engine``...), after fsyncing the
    folder of the new entry files; then delete the files of the entries replaced or removed."""
    if put:
        fsync_entries(library_dir)
    released = catalogue.update(library_dir, put=put or {}, drop=drop, library=library)
    _tidy(library_dir, released)


def sweep(library_dir: Path) -> None:
    """Delete every file the committed catalogue does not reference (a failed or killed
    write's leftovers) and the writer's mark that asked for it."""
    clean_unreferenced(library_dir, catalogue.referenced_files(library_dir))
    (library_dir / WRITING_NAME).unlink(missing_ok=True)


def clean_unreferenced(library_dir: Path, referenced: set[str]) -> None:
    """Delete entry files not in ``referenced``, leftover temporary catalogues and the
    format-2 manifest a committed catalogue replaced."""
    entries_dir = library_dir / ENTRIES_DIR
    names = os.listdir(entries_dir) if entries_dir.is_dir() else []
    stale = [entries_dir / name for name in names if f"{ENTRIES_DIR}/{name}" not in referenced]
    stale += list(library_dir.glob(f".{CATALOGUE_NAME}.*"))
    stale += list(library_dir.glob(f".{LEGACY_MANIFEST_NAME}.*.tmp"))
    if catalogue.exists(library_dir):
        stale.append(library_dir / LEGACY_MANIFEST_NAME)
    stale = [path for path in stale if path.is_file()]
    for path in stale:
        path.unlink(missing_ok=True)
    if stale:
        logger.info("removed %d unreferenced file(s) from %s", len(stale), library_dir)
        if entries_dir.is_dir():
            fsync_directory(entries_dir)
        fsync_directory(library_dir)


def fsync_entries(library_dir: Path) -> None:
    """Make the new entry files' names durable before a row names them."""
    entries_dir = library_dir / ENTRIES_DIR
    entries_dir.mkdir(parents=True, exist_ok=True)
    fsync_directory(entries_dir)
    fsync_directory(library_dir)


def _tidy(library_dir: Path, released: list[str], referenced: set[str] | None = None) -> None:
    """After a commit: delete the files it released, sweep the entries folder for a build
    (``referenced``) or when an earlier writer's leftovers wait (its mark), drop the mark.

    The library folder is fsynced first: in DELETE mode the journal's deletion is the commit,
    and a commit lost to a power cut must not leave the older state naming deleted files."""
    fsync_directory(library_dir)
    for name in released:
        (library_dir / name).unlink(missing_ok=True)
    mark = library_dir / WRITING_NAME
    if referenced is None and _reads(mark) == _SWEEP:
        referenced = catalogue.referenced_files(library_dir)
    if referenced is not None:
        clean_unreferenced(library_dir, referenced)
    elif released:
        fsync_directory(library_dir / ENTRIES_DIR)
    mark.unlink(missing_ok=True)


def _reads(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None
