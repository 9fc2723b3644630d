"""The catalogue: a library's description and one row per entry in one SQLite database
(``catalogue.sqlite``), so that adding or removing an entry writes its own row, not all of them.

Every write is one transaction in a rollback journal (``journal_mode=DELETE``,
``synchronous=FULL``): a writer killed at any point leaves the last committed state. Not WAL:
replicas may serve the library from a read-only volume, and a WAL reader writes the ``-shm``
file beside the database. Readers open the file read-only (``mode=ro``) and never write to the
library folder; how they read past a killed writer's journal is
:mod:`catalign.library.catalogue_db`'s.

The library row holds a generation, one more at every committed write, and an id drawn when
the catalogue is created: together they are the stamp (:func:`stamp`) by which servers notice
a change, one small query, where a file's mtime and size could stay the same over a write.
"""

from __future__ import annotations

import json
import os
import secrets
import sqlite3
from collections.abc import Collection, Iterator, Mapping
from contextlib import closing
from pathlib import Path
from typing import Any

from catalign.errors import LibraryCorruptError, LibraryError
from catalign.library.catalogue_db import (
    WRITE_TIMEOUT_S,
    catalogue_path,
    journal_path,
    journal_state,
    reading,
    set_pragmas,
    writing,
)
from catalign.library.records import (
    FORMAT_VERSION,
    MIGRATABLE_VERSIONS,
    EntryRecord,
    Manifest,
    rebuild_hint,
)
from catalign.library.sources import CATEGORY_PATTERN

APPLICATION_ID = 0x63617461  # "cata" in the header: tells a catalogue from other SQLite files
Stamp = tuple[str, int]
_CHUNK = 500  # ids per ``IN (...)``, well under SQLite's limit on parameters

_LIBRARY_COLUMNS = ("fingerprint", "voxel_size", "created", "updated", "category", "engine")
_ENTRY_COLUMNS = (
    "model_id", "file", "sha256", "source", "source_sha256", "units", "num_points",
    "num_keypoints", "bbox_min_x", "bbox_min_y", "bbox_min_z", "bbox_max_x", "bbox_max_y",
    "bbox_max_z", "size_x", "size_y", "size_z", "category", "symmetry", "descriptor", "outline",
)  # fmt: skip
# Added to format 4 after its first release: a catalogue without the column reads as entries
# without outlines, and the first write adds it.
_OUTLINE_COLUMN = "outline BLOB NOT NULL DEFAULT x''"
_SCHEMA = f"""
CREATE TABLE library (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    format_version INTEGER NOT NULL,
    fingerprint TEXT NOT NULL,
    voxel_size REAL NOT NULL,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    category TEXT NOT NULL,
    engine TEXT NOT NULL,
    uid TEXT NOT NULL,
    generation INTEGER NOT NULL
);
CREATE TABLE entries (
    model_id TEXT PRIMARY KEY,
    file TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    source TEXT NOT NULL,
    source_sha256 TEXT NOT NULL,
    units TEXT NOT NULL,
    num_points INTEGER NOT NULL,
    num_keypoints INTEGER NOT NULL,
    {", ".join(f"{c} REAL NOT NULL" for c in _ENTRY_COLUMNS[8:17])},
    category TEXT NOT NULL,
    symmetry INTEGER,
    descriptor BLOB NOT NULL,
    {_OUTLINE_COLUMN}
);
"""
_SELECT_ENTRIES = f"SELECT {', '.join(_ENTRY_COLUMNS)} FROM entries"
_SELECT_WITHOUT_OUTLINES = f"SELECT {', '.join(_ENTRY_COLUMNS[:-1])}, x'' FROM entries"
_PUT_ENTRY = (
    f"INSERT OR REPLACE INTO entries ({', '.join(_ENTRY_COLUMNS)}) "
    f"VALUES ({', '.join('?' * len(_ENTRY_COLUMNS))})"
)


def exists(library_dir: Path) -> bool:
    return catalogue_path(library_dir).is_file()


def read(
    library_dir: Path, ids: Collection[str] | None = None, outlines: bool = True
) -> tuple[Manifest, Stamp]:
    """The library's description with every entry's record (only those of ``ids`` that it
    holds, when given; their outlines empty unless ``outlines``), and the stamp of that state,
    from one read transaction."""
    with reading(library_dir) as connection:
        header = _header(connection, library_dir)
        select = _select_entries(connection) if outlines else _SELECT_WITHOUT_OUTLINES
        if ids is None:
            rows = connection.execute(select).fetchall()
        else:
            wanted, rows = list(ids), []
            for start in range(0, len(wanted), _CHUNK):
                chunk = wanted[start : start + _CHUNK]
                query = f"{select} WHERE model_id IN ({', '.join('?' * len(chunk))})"
                rows += connection.execute(query, chunk).fetchall()
        entries = dict(_records(rows, library_dir))
    fingerprint, voxel_size, created, updated, category, engine, uid, generation = header
    manifest = Manifest(fingerprint, voxel_size, created, updated, entries, FORMAT_VERSION,
                        engine, category)  # fmt: skip
    return manifest, (uid, generation)


def count(library_dir: Path) -> int:
    """How many entries the library holds, without reading their records."""
    with reading(library_dir) as connection:
        _header(connection, library_dir)
        return int(connection.execute("SELECT count(*) FROM entries").fetchone()[0])


def ids(library_dir: Path) -> list[str]:
    """The entries' ids, sorted, without reading their records."""
    with reading(library_dir) as connection:
        _header(connection, library_dir)
        return [i for (i,) in connection.execute("SELECT model_id FROM entries ORDER BY 1")]


def category_counts(library_dir: Path) -> dict[str, int]:
    """How many entries each category holds, by name, without reading their records."""
    with reading(library_dir) as connection:
        _header(connection, library_dir)
        query = "SELECT category, count(*) FROM entries GROUP BY 1 ORDER BY 1"
        return dict(connection.execute(query).fetchall())


def referenced_files(library_dir: Path) -> set[str]:
    """Every entry file a row names (what a sweep of the entries folder keeps)."""
    with reading(library_dir) as connection:
        _header(connection, library_dir)
        return {file for (file,) in connection.execute("SELECT file FROM entries")}


def stamp(library_dir: Path) -> Stamp | None:
    """The catalogue's id and generation; None when there is none, or it cannot be read.

    While a killed writer's journal waits to be rolled back, the stamp read from a rolled-back
    copy is kept for as long as the database and the journal stay as they were, so that each
    request of a server does not copy the catalogue again."""
    path = catalogue_path(library_dir)
    journal = journal_state(path)
    if journal is not None and _recovered_stamps.get(path, (None,))[0] == journal:
        return _recovered_stamps[path][1]
    try:
        with reading(library_dir) as connection:
            uid, generation = connection.execute("SELECT uid, generation FROM library").fetchone()
    except (LibraryError, sqlite3.Error, TypeError):
        return None
    if journal is not None and journal_state(path) == journal:
        _recovered_stamps[path] = (journal, (uid, generation))
    else:
        _recovered_stamps.pop(path, None)
    return uid, generation


# The stamp read from a rolled-back copy, by catalogue, with the state it was read in.
_recovered_stamps: dict[Path, tuple[tuple[Any, ...], Stamp]] = {}


def create(library_dir: Path, manifest: Manifest) -> None:
    """Write a new catalogue under a temporary name and rename it into place: a build killed
    before the rename leaves no library, as before it began. Only where there is none."""
    path = catalogue_path(library_dir)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    for leftover in (temporary, journal_path(temporary)):
        leftover.unlink(missing_ok=True)
    try:
        connection = sqlite3.connect(temporary, timeout=WRITE_TIMEOUT_S, isolation_level=None)
        with closing(connection):
            set_pragmas(connection)
            # executescript commits nothing it did not begin: the transaction stays open
            connection.executescript(
                f"BEGIN IMMEDIATE; PRAGMA application_id = {APPLICATION_ID}; {_SCHEMA}"
            )
            connection.execute(
                "INSERT INTO library (id, format_version, uid, generation, "
                f"{', '.join(_LIBRARY_COLUMNS)}) VALUES (1, ?, ?, 1, ?, ?, ?, ?, ?, ?)",
                (FORMAT_VERSION, secrets.token_hex(8), *_library_values(manifest)),
            )
            connection.executemany(_PUT_ENTRY, _rows(manifest.entries))
            connection.execute("COMMIT")  # synchronous=FULL: on disk before the rename
        # A journal without its database is nobody's; left, it would roll the new one back.
        journal_path(path).unlink(missing_ok=True)
        temporary.replace(path)
    finally:
        for leftover in (temporary, journal_path(temporary)):
            leftover.unlink(missing_ok=True)


def update(
    library_dir: Path,
    *,
    put: Mapping[str, EntryRecord],
    drop: Collection[str],
    library: Mapping[str, Any],
) -> list[str]:
    """One transaction: the rows of ``put`` inserted or replaced, those of ``drop`` deleted,
    the library row's ``library`` columns (a :class:`Manifest`'s field names) set, and one
    generation more. Returns the entry files no row names any more, to delete once committed."""
    unknown = set(library) - set(_LIBRARY_COLUMNS)
    if unknown:
        raise ValueError(f"no library column {sorted(unknown)}")
    with writing(library_dir) as connection:
        _header(connection, library_dir)
        _add_outline_column(connection)
        released = [f for i in drop if (f := _file_of(connection, i)) is not None]
        connection.executemany("DELETE FROM entries WHERE model_id = ?", [(i,) for i in drop])
        for model_id, record in put.items():
            old = _file_of(connection, model_id)
            if old is not None and old != record.file:
                released.append(old)
        connection.executemany(_PUT_ENTRY, _rows(put))
        values = {k: json.dumps(v) if k == "engine" else v for k, v in library.items()}
        assignments = "".join(f"{column} = ?, " for column in values)
        connection.execute(
            f"UPDATE library SET {assignments}generation = generation + 1",
            list(values.values()),
        )
    return released


def replace(library_dir: Path, manifest: Manifest) -> list[str]:
    """Make the catalogue say ``manifest`` in one transaction that writes only the rows that
    differ (a build over an existing library); returns the entry files released."""
    with writing(library_dir) as connection:
        _header(connection, library_dir)
        _add_outline_column(connection)
        current = {row[0]: row for row in connection.execute(_SELECT_ENTRIES)}
        wanted = dict(zip(manifest.entries, _rows(manifest.entries), strict=True))
        drop = [(i,) for i in current if i not in wanted]
        put = [row for i, row in wanted.items() if current.get(i) != row]
        released = [current[i][1] for (i,) in drop]
        released += [current[row[0]][1] for row in put if row[0] in current]
        connection.executemany("DELETE FROM entries WHERE model_id = ?", drop)
        connection.executemany(_PUT_ENTRY, put)
        assignments = "".join(f"{column} = ?, " for column in _LIBRARY_COLUMNS)
        connection.execute(
            f"UPDATE library SET {assignments}generation = generation + 1",
            _library_values(manifest),
        )
    kept = {record.file for record in manifest.entries.values()}
    return [file for file in released if file not in kept]


def _header(connection: sqlite3.Connection, library_dir: Path) -> tuple[Any, ...]:
    """The library row, checked: this application's file, this format, sound values."""
    path = catalogue_path(library_dir)
    (application,) = connection.execute("PRAGMA application_id").fetchone()
    if application != APPLICATION_ID:
        raise LibraryCorruptError(
            f"{path} is an SQLite database but not a catalign catalogue; "
            f"{rebuild_hint(library_dir)}"
        )
    version = format_version(connection)
    if version in MIGRATABLE_VERSIONS:
        raise LibraryError(
            f"{path} holds a library of format {version}, which this catalign converts but no "
            f"longer reads; convert it in place with `catalign library migrate {library_dir}` "
            f"or {rebuild_hint(library_dir)}"
        )
    if version != FORMAT_VERSION:
        raise LibraryCorruptError(
            f"{path} has library format version {version!r}, but this catalign reads "
            f"version {FORMAT_VERSION}; {rebuild_hint(library_dir)}"
        )
    columns = ", ".join((*_LIBRARY_COLUMNS, "uid", "generation"))
    row = connection.execute(f"SELECT {columns} FROM library").fetchone()
    try:
        fingerprint, voxel_size, created, updated, category, engine, uid, generation = row
        for value in (fingerprint, created, updated, category, engine, uid):
            _check_type(value, str)
        _check_type(voxel_size, float)
        _check_type(generation, int)
        engine = json.loads(engine)
        _check_type(engine, dict)
        if CATEGORY_PATTERN.fullmatch(category) is None:
            raise ValueError(f"category {category!r} is not a valid category")
    except (TypeError, ValueError) as exc:
        raise _malformed(library_dir, exc) from exc
    return fingerprint, voxel_size, created, updated, category, engine, uid, generation


def _has_outlines(connection: sqlite3.Connection) -> bool:
    columns = connection.execute("PRAGMA table_info(entries)").fetchall()
    return any(column[1] == "outline" for column in columns)


def _select_entries(connection: sqlite3.Connection) -> str:
    """The query of every entry's row, outlines empty in a catalogue without their column."""
    return _SELECT_ENTRIES if _has_outlines(connection) else _SELECT_WITHOUT_OUTLINES


def _add_outline_column(connection: sqlite3.Connection) -> None:
    """Give a catalogue written before entries had outlines their column (in the writer's
    transaction: rolled back with it)."""
    if not _has_outlines(connection):
        connection.execute(f"ALTER TABLE entries ADD COLUMN {_OUTLINE_COLUMN}")


def format_version(connection: sqlite3.Connection) -> Any:
    """The library row's format version (None without one)."""
    row = connection.execute("SELECT format_version FROM library").fetchone()
    return None if row is None else row[0]


def _records(rows: list[Any], library_dir: Path) -> Iterator[tuple[str, EntryRecord]]:
    """Each row as a checked record: SQLite keeps any type in any column, and a row edited by
    hand must not name a file outside the library."""
    for row in rows:
        try:
            types = tuple(map(type, row))
            if types[:-3] + types[-2:] != _ROW_TYPES or types[-3] not in _SYMMETRY_TYPES:
                raise TypeError(_wrong_types(row))
            record = EntryRecord(*row[1:8], row[8:11], row[11:14], row[14:17], *row[17:])
            record.check(row[0])
        except (TypeError, ValueError) as exc:
            raise _malformed(library_dir, f"entry {row[0]!r}: {exc}") from exc
        yield row[0], record


_ROW_TYPES = (str, str, str, str, str, str, int, int, *(float,) * 9, str, bytes, bytes)
_SYMMETRY_TYPES = (int, type(None))


def _wrong_types(row: tuple[Any, ...]) -> str:
    kinds = [(kind,) for kind in _ROW_TYPES]
    kinds.insert(-2, _SYMMETRY_TYPES)
    bad = [(c, v) for c, v, k in zip(_ENTRY_COLUMNS, row, kinds, strict=True) if type(v) not in k]
    column, value = bad[0]
    return f"{column} is {type(value).__name__} {value!r}"


def _rows(entries: Mapping[str, EntryRecord]) -> list[tuple[Any, ...]]:
    return [
        (model_id, r.file, r.sha256, r.source, r.source_sha256, r.units, r.num_points,
         r.num_keypoints, *map(float, (*r.bbox_min, *r.bbox_max, *r.size)), r.category,
         r.symmetry, r.descriptor, r.outline)
        for model_id, r in entries.items()
    ]  # fmt: skip


def _library_values(manifest: Manifest) -> tuple[Any, ...]:
    return (manifest.fingerprint, float(manifest.voxel_size), manifest.created,
            manifest.updated, manifest.category, json.dumps(manifest.engine))  # fmt: skip


def _file_of(connection: sqlite3.Connection, model_id: str) -> str | None:
    row = connection.execute("SELECT file FROM entries WHERE model_id = ?", (model_id,))
    found = row.fetchone()
    return None if found is None else found[0]


def _check_type(value: Any, kind: type) -> None:
    if type(value) is not kind:
        raise TypeError(f"unexpected {type(value).__name__} {value!r}")


def _malformed(library_dir: Path, problem: object) -> LibraryCorruptError:
    return LibraryCorruptError(
        f"{catalogue_path(library_dir)} is malformed ({problem}); {rebuild_hint(library_dir)}"
    )
