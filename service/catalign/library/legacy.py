"""Libraries of formats 2 and 3, which :func:`migrate` converts in place (``catalign library
migrate DIR``) to this one: no feature is computed again, so no weights are needed.

Format 2 kept its catalogue in one JSON file (``manifest.json``) rewritten whole at every
change; format 3 in ``catalogue.sqlite`` without the entries' descriptors. Both stored entries
at full precision and uncompressed (about 0.8 MB a chair). A conversion rewrites every entry as
this format stores it (:mod:`~catalign.library.entry_codec`: narrowed, only the key points
matching reads, compressed), to new content-addressed names beside the old files, then renames a
new catalogue into place, and only then deletes the old files and the JSON file. Killed at any
point, it leaves the old library whole (with leftovers the next run rewrites or sweeps) or the
new one.

Nothing else reads these formats: a reader or writer given one refuses it with the command that
converts it, never misreading it.

A library of this format may hold entry files of the layout before
(:mod:`~catalign.library.entry_codec`: the surface as rows in sampling order, float32 key points,
the grid's 255 levels, deflated). They are served as they are; :func:`migrate` rewrites them in
the current layout, which takes about a third less room, in one transaction of their rows.
"""

from __future__ import annotations

import json
import sqlite3
import zipfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from catalign.errors import LibraryCorruptError, LibraryError
from catalign.geometry.distance_grid import DistanceGrid
from catalign.geometry.symmetry import YawSymmetry, find_yaw_symmetry
from catalign.library import catalogue
from catalign.library.catalogue_db import LEGACY_MANIFEST_NAME, no_catalogue, reading
from catalign.library.entry import LibraryEntry, narrowed_entry
from catalign.library.npz import npz_arrays
from catalign.library.outline import outline_of
from catalign.library.quantise import (
    STORED_KEYPOINTS,
    narrowed_features,
    narrowed_points,
    stored_rows,
)
from catalign.library.records import (
    FORMAT_VERSION,
    EntryRecord,
    Manifest,
    rebuild_hint,
    typed,
)
from catalign.library.shortlist_index import write_index
from catalign.library.sources import CATEGORY_PATTERN, DEFAULT_CATEGORY
from catalign.library.store import (
    WRITING_NAME,
    begin_write,
    clean_unreferenced,
    commit_changes,
    fsync_entries,
    read_entry,
    read_manifest,
    utc_now,
    write_entry,
    writer_lock,
)

JSON_VERSION = 2  # 1 held no distance grids: only a rebuild makes it a library again
SQLITE_VERSION = 3
_V3_COLUMNS = (
    "model_id, file, sha256, source, source_sha256, units, num_points, num_keypoints, "
    "bbox_min_x, bbox_min_y, bbox_min_z, bbox_max_x, bbox_max_y, bbox_max_z, "
    "size_x, size_y, size_z, category, symmetry"
)


def migrate(
    library_dir: str | Path, progress: Callable[[int, int], None] | None = None
) -> Manifest:
    """Convert the library of format 2 or 3 in ``library_dir`` to this format, in place, and
    return it; in a library already of this format, rewrite the entry files of the earlier
    layout and delete what a conversion killed after its rename left. ``progress`` is called
    with (done, total) after each entry.

    Raises LibraryError where there is no library, LibraryCorruptError for an old catalogue
    that cannot be read or an entry file that is missing or damaged.
    """
    library_dir = Path(library_dir)
    if not (library_dir / LEGACY_MANIFEST_NAME).is_file() and not catalogue.exists(library_dir):
        raise no_catalogue(library_dir)
    with writer_lock(library_dir):
        version = format_of(library_dir)
        if version == FORMAT_VERSION:
            return _rewrite_earlier_layout(library_dir, read_manifest(library_dir), progress)
        old = read_legacy(library_dir) if version == JSON_VERSION else read_sqlite(library_dir)
        begin_write(library_dir)
        records = {}
        for done, (model_id, record) in enumerate(sorted(old.entries.items()), start=1):
            records[model_id] = _converted(library_dir, model_id, record)
            if progress is not None:
                progress(done, len(old.entries))
        converted = Manifest(old.fingerprint, old.voxel_size, old.created, old.updated,
                             records, FORMAT_VERSION, old.engine, old.category)  # fmt: skip
        fsync_entries(library_dir)
        write_index(library_dir, records)
        catalogue.create(library_dir, converted)  # renamed over the old catalogue, if any
        clean_unreferenced(library_dir, {r.file for r in records.values()})
        (library_dir / WRITING_NAME).unlink(missing_ok=True)
    return converted


def _rewrite_earlier_layout(
    library_dir: Path, current: Manifest, progress: Callable[[int, int], None] | None
) -> Manifest:
    """Rewrite the entries of a library of this format whose files are of the earlier layout
    (:mod:`~catalign.library.entry_codec`: they are read as they are, and take a third more
    room), give the records written before outlines theirs
    (:mod:`~catalign.library.outline`), then delete what an earlier conversion killed after
    its rename left."""
    earlier = {i for i in current.ids if _of_earlier_layout(library_dir, current.entries[i])}
    behind = [i for i in current.ids if i in earlier or not current.entries[i].outline]
    if behind:
        begin_write(library_dir)
        records = {}
        for done, model_id in enumerate(behind, start=1):
            record = current.entries[model_id]
            try:
                entry = read_entry(library_dir, model_id, record)
            except FileNotFoundError:
                raise _missing(library_dir, model_id, record) from None
            if model_id in earlier:
                records[model_id] = write_entry(library_dir, narrowed_entry(entry))
            else:
                records[model_id] = replace(record, outline=outline_of(entry.points).to_bytes())
            if progress is not None:
                progress(done, len(behind))
        updated = utc_now()
        commit_changes(library_dir, put=records, updated=updated)  # the descriptors as they were
        current = replace(current, updated=updated, entries={**current.entries, **records})
    clean_unreferenced(library_dir, {r.file for r in current.entries.values()})
    (library_dir / WRITING_NAME).unlink(missing_ok=True)
    return current


def _of_earlier_layout(library_dir: Path, record: EntryRecord) -> bool:
    """Whether an entry's file holds the surface as rows (read from its zip directory alone);
    a file that cannot be opened is left to the read that names what is wrong with it."""
    try:
        with zipfile.ZipFile(library_dir / record.file) as archive:
            return "point_steps.npy" in archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return True


def _missing(library_dir: Path, model_id: str, record: EntryRecord) -> LibraryCorruptError:
    return LibraryCorruptError(
        f"library entry {model_id!r}: its file {library_dir / record.file} is missing, so "
        f"{library_dir} cannot be converted; restore the file or {rebuild_hint(library_dir)}"
    )


def format_of(library_dir: Path) -> int:
    """The library's format: the catalogue's, else the JSON file's (format 2); a format no
    conversion reads raises LibraryCorruptError."""
    if not catalogue.exists(library_dir):
        return JSON_VERSION
    with reading(library_dir) as connection:
        try:
            version = catalogue.format_version(connection)
        except sqlite3.Error as exc:
            raise LibraryCorruptError(
                f"{library_dir} has a catalogue that cannot be read ({exc}); "
                f"{rebuild_hint(library_dir)}"
            ) from exc
    if version not in (SQLITE_VERSION, FORMAT_VERSION):
        raise LibraryCorruptError(
            f"{library_dir} has library format version {version!r}, which cannot be converted "
            f"(versions {JSON_VERSION} and {SQLITE_VERSION} can); {rebuild_hint(library_dir)}"
        )
    return version


def _converted(library_dir: Path, model_id: str, record: EntryRecord) -> EntryRecord:
    """One old entry file rewritten as this format stores it; its new record."""
    path = library_dir / record.file
    try:
        arrays = npz_arrays(path.read_bytes())
        entry = _old_entry(arrays, record)
    except FileNotFoundError:
        raise _missing(library_dir, model_id, record) from None
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise LibraryCorruptError(
            f"library entry {model_id!r} ({path}) cannot be read ({exc}), so {library_dir} "
            f"cannot be converted; remove the entry or {rebuild_hint(library_dir)}"
        ) from exc
    if entry.model_id != model_id:
        raise LibraryCorruptError(f"library entry {model_id!r} ({path}) holds {entry.model_id!r}")
    return write_entry(library_dir, entry)


def _old_entry(arrays: dict[str, np.ndarray], record: EntryRecord) -> LibraryEntry:
    """An entry of formats 2 and 3 (every key point, float arrays) as this format keeps it.
    Its features were computed from the points before they were narrowed, which moves them
    less than the narrowing of the features does."""
    low, high = arrays["bbox_min"].astype(np.float64), arrays["bbox_max"].astype(np.float64)
    points = narrowed_points(arrays["points"], low, high)
    keypoints, features = arrays["keypoints"], arrays["features"]
    if keypoints.ndim != 2 or len(keypoints) == 0 or len(features) != len(keypoints):
        raise ValueError(f"{len(keypoints)} key points and {len(features)} features")
    kept = stored_rows(len(keypoints), STORED_KEYPOINTS)
    cell, step = arrays["grid_cell_step"].astype(np.float64)
    symmetry = record.symmetry
    entry = LibraryEntry(
        model_id=str(arrays["model_id"][()]),
        points=points,
        keypoints=keypoints[kept].astype(np.float64),
        features=narrowed_features(features[kept]),
        descriptor=arrays["descriptor"].astype(np.float32),
        bbox_min=low,
        bbox_max=high,
        size=arrays["size"].astype(np.float64),
        grid=DistanceGrid(arrays["grid"], arrays["grid_origin"], float(cell), float(step)),
        source=record.source,
        source_sha256=record.source_sha256,
        units=record.units,
        category=record.category,
        symmetry=find_yaw_symmetry(points) if symmetry is None else YawSymmetry(symmetry),
    )
    return narrowed_entry(entry)


def read_sqlite(library_dir: Path) -> Manifest:
    """Parse a format-3 catalogue (its entries have no descriptors yet)."""
    with reading(library_dir) as connection:
        try:
            header = connection.execute(
                "SELECT fingerprint, voxel_size, created, updated, category, engine FROM library"
            ).fetchone()
            rows = connection.execute(f"SELECT {_V3_COLUMNS} FROM entries").fetchall()
            fingerprint, voxel_size, created, updated, category, engine = header
            entries = {}
            for row in rows:
                record = EntryRecord(*row[1:8], row[8:11], row[11:14], row[14:17], *row[17:])
                record.check(row[0])
                entries[row[0]] = record
            return Manifest(fingerprint, float(voxel_size), created, updated, entries,
                            SQLITE_VERSION, json.loads(engine), category)  # fmt: skip
        except (sqlite3.Error, TypeError, ValueError) as exc:
            raise LibraryCorruptError(
                f"{library_dir}'s catalogue of format {SQLITE_VERSION} is malformed ({exc}); "
                f"{rebuild_hint(library_dir)}"
            ) from exc


def read_legacy(library_dir: Path) -> Manifest:
    """Parse a format-2 ``manifest.json``; anything else raises LibraryCorruptError."""
    where = library_dir / LEGACY_MANIFEST_NAME
    try:
        raw = json.loads(where.read_bytes())
    except OSError as exc:
        raise LibraryError(f"cannot read {where}: {exc}") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LibraryCorruptError(
            f"{where} is not valid JSON ({exc}); {rebuild_hint(library_dir)}"
        ) from exc
    if not isinstance(raw, dict) or "format_version" not in raw:
        raise LibraryCorruptError(
            f"{where} is not a catalign library manifest (no format_version); "
            f"{rebuild_hint(library_dir)}"
        )
    version = raw["format_version"]
    if type(version) is not int or version != JSON_VERSION:
        raise LibraryCorruptError(
            f"{where} has library format version {version!r}, which cannot be converted "
            f"(only version {JSON_VERSION} can); {rebuild_hint(library_dir)}"
        )
    try:
        # a record written before entries had categories: the manifest's, else a chair
        default_category = typed(raw.get("category", DEFAULT_CATEGORY), str)
        if CATEGORY_PATTERN.fullmatch(default_category) is None:
            raise ValueError(f"category {default_category!r} is not a valid category")
        entries = {
            typed(model_id, str): EntryRecord.from_json(model_id, record, default_category)
            for model_id, record in typed(raw["entries"], dict).items()
        }
        return Manifest(
            fingerprint=typed(raw["extractor"]["fingerprint"], str),
            voxel_size=float(typed(raw["extractor"]["voxel_size"], int | float)),
            created=typed(raw["created"], str),
            updated=typed(raw["updated"], str),
            entries=entries,
            format_version=JSON_VERSION,
            engine=typed(raw.get("engine", {}), dict),
            category=default_category,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryCorruptError(
            f"{where} is malformed ({type(exc).__name__}: {exc}); {rebuild_hint(library_dir)}"
        ) from exc
