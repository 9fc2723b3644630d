"""Opening a library's catalogue database: read-only connections, write transactions, and
SQLite's errors in the library's words (what the rows mean is :mod:`catalign.library.catalogue`'s).

A writer killed mid-transaction leaves a hot journal beside the database, which only a writer
may roll back (the next one does as it takes the lock: :func:`recover`). A read-only reader
cannot, so until then it copies the database and the journal into a temporary folder and lets
SQLite roll the copy back there: readers never write to the library folder, which may be a
read-only volume.
"""

from __future__ import annotations

import os
import sqlite3
import tempfile
from collections.abc import Iterator
from contextlib import closing, contextmanager
from pathlib import Path
from typing import Any

from catalign.errors import LibraryCorruptError, LibraryError
from catalign.library.records import rebuild_hint

CATALOGUE_NAME = "catalogue.sqlite"
LEGACY_MANIFEST_NAME = "manifest.json"  # format 2's catalogue: one JSON file
READ_TIMEOUT_S = 30.0  # a writer holds its exclusive lock only while it commits
WRITE_TIMEOUT_S = 120.0  # a reader holds its shared lock while it reads every row
_COPY_ATTEMPTS = 10  # each failed one means a writer rolled the journal back meanwhile


def catalogue_path(library_dir: Path) -> Path:
    return library_dir / CATALOGUE_NAME


def journal_path(database: Path) -> Path:
    return database.with_name(database.name + "-journal")


@contextmanager
def reading(library_dir: Path) -> Iterator[sqlite3.Connection]:
    """A read-only connection in a read transaction: to the catalogue, or, while a killed
    writer's journal waits for the next writer, to a private copy rolled back."""
    path = catalogue_path(library_dir)
    if not path.is_file():
        raise no_catalogue(library_dir)
    with translated(library_dir):
        copy: tempfile.TemporaryDirectory[str] | None = None
        for _ in range(_COPY_ATTEMPTS):
            connection = sqlite3.connect(
                _uri(path, "ro"), uri=True, timeout=READ_TIMEOUT_S, isolation_level=None
            )
            try:
                connection.execute("BEGIN")
                connection.execute("PRAGMA application_id").fetchone()  # takes the shared lock
                break
            except sqlite3.OperationalError as error:
                connection.close()
                if error.sqlite_errorname != "SQLITE_READONLY_ROLLBACK":
                    raise
            try:
                found = _rolled_back_copy(path)
            except OSError as error:
                raise LibraryError(
                    f"{path} was left mid-write by a killed writer, and the private copy a "
                    f"reader rolls back until the next writer does could not be made ({error}); "
                    "give this process a writable temporary folder (TMPDIR), or run any "
                    "library write to roll it back"
                ) from error
            if found is not None:
                connection, copy = found
                break
        else:
            raise LibraryError(f"{path} kept changing while it was read; try again")
        try:
            yield connection
        finally:
            connection.close()
            if copy is not None:
                copy.cleanup()


@contextmanager
def writing(library_dir: Path) -> Iterator[sqlite3.Connection]:
    """A connection in a write transaction (``BEGIN IMMEDIATE``), committed when the block
    ends, rolled back if it raises; the caller holds the writer lock."""
    path = catalogue_path(library_dir)
    if not path.is_file():
        raise no_catalogue(library_dir)
    with translated(library_dir):
        connection = sqlite3.connect(
            _uri(path, "rw"), uri=True, timeout=WRITE_TIMEOUT_S, isolation_level=None
        )
        with closing(connection):
            set_pragmas(connection)
            connection.execute("BEGIN IMMEDIATE")
            try:
                yield connection
                connection.execute("COMMIT")
            finally:
                if connection.in_transaction:
                    connection.execute("ROLLBACK")


def set_pragmas(connection: sqlite3.Connection) -> None:
    """A writer's settings: a rollback journal deleted at commit, every commit fsynced, and
    no temporary files (a writer may run on a read-only root)."""
    connection.execute("PRAGMA journal_mode = DELETE").fetchone()
    connection.execute("PRAGMA synchronous = FULL")
    connection.execute("PRAGMA temp_store = MEMORY")


def recover(library_dir: Path) -> None:
    """Roll back what a killed writer left (a writer's first read does it), so that readers
    read the catalogue itself again; the caller holds the writer lock."""
    path = catalogue_path(library_dir)
    if not path.is_file():
        # A journal without its database is nobody's; left, it would be taken for the
        # journal of the catalogue a build renames into place next, and roll it back.
        journal_path(path).unlink(missing_ok=True)
        return
    try:
        connection = sqlite3.connect(_uri(path, "rw"), uri=True, timeout=WRITE_TIMEOUT_S)
        with closing(connection):
            connection.execute("PRAGMA application_id").fetchone()  # rolls a hot journal back
    except sqlite3.Error:
        pass  # not a catalogue: the read that follows says so


def journal_state(path: Path) -> tuple[Any, ...] | None:
    """What tells a journal and its database from any later ones (a journal's header holds a
    nonce drawn for each transaction); None without a journal."""
    try:
        journal, database = os.stat(journal_path(path)), os.stat(path)
        with open(journal_path(path), "rb") as handle:  # SQLite locks databases, never journals
            header = handle.read(28)
    except OSError:
        return None
    return (header, journal.st_ino, journal.st_size, journal.st_mtime_ns,
            database.st_ino, database.st_size, database.st_mtime_ns)  # fmt: skip


def _rolled_back_copy(
    path: Path,
) -> tuple[sqlite3.Connection, tempfile.TemporaryDirectory[str]] | None:
    """A connection to the catalogue as it was before a killed writer's transaction: the
    database copied (through SQLite, ignoring locks, so that no descriptor of it is closed
    under this process's own locks) and its journal beside it in a temporary folder, rolled
    back there. None if the journal changed meanwhile (a writer rolled it back): read the
    catalogue again.

    Copying while the same journal stays is safe at any moment: rolling back writes the
    journal's original pages over whatever the killed writer wrote."""
    journal = journal_path(path)
    try:
        before = journal.read_bytes()
    except FileNotFoundError:
        return None
    folder = tempfile.TemporaryDirectory(prefix="catalign-catalogue-")
    try:
        copy = Path(folder.name) / CATALOGUE_NAME
        source = sqlite3.connect(_uri(path, "ro&immutable=1"), uri=True)
        target = sqlite3.connect(copy)
        with closing(source), closing(target):
            source.backup(target)
        try:
            unchanged = journal.read_bytes() == before
        except FileNotFoundError:
            unchanged = False
        if not unchanged:
            folder.cleanup()
            return None
        journal_path(copy).write_bytes(before)
        connection = sqlite3.connect(copy, timeout=READ_TIMEOUT_S, isolation_level=None)
        connection.execute("BEGIN")
        connection.execute("PRAGMA application_id").fetchone()  # rolls the copy back
    except BaseException:
        folder.cleanup()
        raise
    return connection, folder


def _uri(path: Path, mode: str) -> str:
    return f"{path.absolute().as_uri()}?mode={mode}"


def no_catalogue(library_dir: Path) -> LibraryError:
    """The error for a folder without a catalogue: an old-format library, or none at all."""
    if (library_dir / LEGACY_MANIFEST_NAME).is_file():
        return LibraryError(
            f"{library_dir} holds a library of an older format ({LEGACY_MANIFEST_NAME}) that "
            f"this catalign no longer reads; convert it in place with `catalign library "
            f"migrate {library_dir}` (its entry files are kept) or {rebuild_hint(library_dir)}"
        )
    if library_dir.is_dir():
        reason = f"{library_dir} holds no {CATALOGUE_NAME}, so it is not a catalign library"
    else:
        reason = f"there is no library at {library_dir}"
    return LibraryError(
        f"{reason}; build one with `catalign library build SRC... --out {library_dir}`"
    )


@contextmanager
def translated(library_dir: Path) -> Iterator[None]:
    """SQLite's errors as the library's: one sentence naming the file and what to do."""
    path = catalogue_path(library_dir)
    try:
        yield
    except sqlite3.Error as error:
        name = getattr(error, "sqlite_errorname", "")
        if name in ("SQLITE_BUSY", "SQLITE_LOCKED"):
            raise LibraryError(f"{path} stayed locked by another process; try again") from error
        if name.startswith(("SQLITE_CANTOPEN", "SQLITE_IOERR", "SQLITE_PERM", "SQLITE_FULL")):
            raise LibraryError(f"cannot use {path}: {error}") from error
        if name.startswith("SQLITE_READONLY"):
            raise LibraryError(f"cannot write {path}: {error}") from error
        raise LibraryCorruptError(
            f"{path} is not a readable catalign catalogue ({error}); {rebuild_hint(library_dir)}"
        ) from error
