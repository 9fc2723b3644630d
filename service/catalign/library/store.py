"""The library's on-disk format, its crash-safe writes and the lock that serialises writers.

A library is a directory::

    manifest.json                      format version, extractor, timestamps, one record per entry
                                       (its file, checksums, source, category...)
    entries/<id>-<sha256[:12]>.npz     one entry's arrays, aligned to be memory-mapped (npz.py)
    .lock                              flock(2)ed by writers

Entry files are content-addressed and written to a temporary name, fsynced and renamed, so a
replaced entry never overwrites a file the current manifest references. The manifest is written
last, atomically; only then are unreferenced files deleted. A crash at any point therefore
leaves the previous manifest and every file it names intact; leftovers (temporary files, orphan
entries) are ignored by readers and removed by the next writer. Readers take no lock: what a
manifest references is never modified, only deleted after a newer manifest replaced it.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import re
import zipfile
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from catalign.atomic import atomic_write_bytes, fsync_directory
from catalign.errors import LibraryCorruptError, LibraryError
from catalign.geometry.symmetry import YawSymmetry, find_yaw_symmetry
from catalign.library.entry import LibraryEntry
from catalign.library.entry_codec import entry_bytes, entry_from_arrays
from catalign.library.npz import map_file, mapped_arrays
from catalign.library.sources import CATEGORY_PATTERN, DEFAULT_CATEGORY

logger = logging.getLogger(__name__)

FORMAT_VERSION = 2  # 2: entries hold their surface's distance grid
MANIFEST_NAME = "manifest.json"
ENTRIES_DIR = "entries"
LOCK_NAME = ".lock"
_SHA256 = re.compile(r"[0-9a-f]{64}")


def rebuild_hint(library_dir: Path) -> str:
    """The sentence that tells a user how to make a fresh library."""
    return f"rebuild it with `catalign library build SRC... --out {library_dir} --overwrite`"


@dataclass(frozen=True)
class EntryRecord:
    """What the manifest says about one entry (no arrays)."""

    file: str
    sha256: str
    source: str
    source_sha256: str
    units: str
    num_points: int
    num_keypoints: int
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    size: tuple[float, float, float]
    category: str = DEFAULT_CATEGORY
    symmetry: int | None = None
    """The entry's :class:`~catalign.geometry.symmetry.YawSymmetry` order; None in a manifest
    written before entries had one (found again from the entry's points when it is read)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "sha256": self.sha256,
            "source": self.source,
            "source_sha256": self.source_sha256,
            "units": self.units,
            "num_points": self.num_points,
            "num_keypoints": self.num_keypoints,
            "bbox_min": list(self.bbox_min),
            "bbox_max": list(self.bbox_max),
            "size": list(self.size),
            "category": self.category,
            "symmetry": self.symmetry,
        }

    @classmethod
    def from_json(
        cls, model_id: str, data: Any, default_category: str = DEFAULT_CATEGORY
    ) -> EntryRecord:
        """Parse and check one manifest record (one written before entries had categories is
        of ``default_category``); raises ValueError, KeyError or TypeError."""
        category = _typed(_typed(data, dict).get("category", default_category), str)
        if CATEGORY_PATTERN.fullmatch(category) is None:
            raise ValueError(f"category {category!r} is not a valid category")
        symmetry = data.get("symmetry")
        if symmetry is not None and (type(symmetry) is not int or symmetry < 0):
            raise ValueError(f"symmetry {symmetry!r} is not an order (0, 1, 2...)")
        record = cls(
            file=_typed(data["file"], str),
            sha256=_typed(data["sha256"], str),
            source=_typed(data["source"], str),
            source_sha256=_typed(data["source_sha256"], str),
            units=_typed(data["units"], str),
            num_points=_typed(data["num_points"], int),
            num_keypoints=_typed(data["num_keypoints"], int),
            bbox_min=_vector(data["bbox_min"]),
            bbox_max=_vector(data["bbox_max"]),
            size=_vector(data["size"]),
            category=category,
            symmetry=symmetry,
        )
        if not _SHA256.fullmatch(record.sha256):
            raise ValueError(f"sha256 {record.sha256!r} is not a hex sha256")
        if record.file != entry_file_name(model_id, record.sha256):
            raise ValueError(f"file {record.file!r} does not match the id and sha256")
        return record


@dataclass(frozen=True)
class Manifest:
    """The parsed ``manifest.json``: extractor, timestamps and entry records sorted by id."""

    fingerprint: str
    voxel_size: float
    created: str
    updated: str
    entries: dict[str, EntryRecord] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION
    engine: dict[str, Any] = field(default_factory=dict)
    """Engine options the library is served with, over the defaults and under the service's
    own (:func:`~catalign.registration.config.served_config`); ``catalign library configure``
    sets them. Checked when a server applies them, so a bad one can still be cleared."""
    category: str = DEFAULT_CATEGORY
    """The category of an entry added without one (``library build --category`` sets it)."""

    @property
    def ids(self) -> list[str]:
        return sorted(self.entries)

    def categories(self) -> dict[str, int]:
        """How many entries each category holds, by name."""
        counts = Counter(record.category for record in self.entries.values())
        return dict(sorted(counts.items()))

    def to_json(self) -> dict[str, Any]:
        return {
            "format_version": self.format_version,
            "extractor": {"fingerprint": self.fingerprint, "voxel_size": self.voxel_size},
            "created": self.created,
            "updated": self.updated,
            "entries": {i: self.entries[i].to_json() for i in self.ids},
            "engine": self.engine,
            "category": self.category,
        }

    def to_bytes(self) -> bytes:
        return (json.dumps(self.to_json(), indent=2) + "\n").encode()

    @classmethod
    def from_bytes(cls, data: bytes, library_dir: Path) -> Manifest:
        """Parse manifest bytes; anything malformed raises LibraryCorruptError."""
        where = library_dir / MANIFEST_NAME
        try:
            raw = json.loads(data)
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
        if type(version) is not int or version != FORMAT_VERSION:
            raise LibraryCorruptError(
                f"{where} has library format version {version!r}, but this catalign reads "
                f"version {FORMAT_VERSION}; {rebuild_hint(library_dir)}"
            )
        try:
            # a record written before entries had categories: the manifest's, else a chair
            default_category = _typed(raw.get("category", DEFAULT_CATEGORY), str)
            if CATEGORY_PATTERN.fullmatch(default_category) is None:
                raise ValueError(f"category {default_category!r} is not a valid category")
            entries = {
                _typed(model_id, str): EntryRecord.from_json(model_id, record, default_category)
                for model_id, record in _typed(raw["entries"], dict).items()
            }
            return cls(
                fingerprint=_typed(raw["extractor"]["fingerprint"], str),
                voxel_size=float(_typed(raw["extractor"]["voxel_size"], int | float)),
                created=_typed(raw["created"], str),
                updated=_typed(raw["updated"], str),
                entries=entries,
                engine=_typed(raw.get("engine", {}), dict),
                category=default_category,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise LibraryCorruptError(
                f"{where} is malformed ({type(exc).__name__}: {exc}); {rebuild_hint(library_dir)}"
            ) from exc


def utc_now() -> str:
    """The current time as an ISO 8601 UTC string (seconds)."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def entry_file_name(model_id: str, sha256: str) -> str:
    """Relative path of an entry file: ``entries/<id>-<sha256[:12]>.npz``."""
    return f"{ENTRIES_DIR}/{model_id}-{sha256[:12]}.npz"


def has_manifest(library_dir: Path) -> bool:
    return (library_dir / MANIFEST_NAME).is_file()


def manifest_stamp(library_dir: Path) -> tuple[int, int, int] | None:
    """What tells a rewritten manifest apart (it is replaced by rename, so the inode too); None
    without one. A server compares stamps to notice a change made by another process."""
    try:
        stat = (library_dir / MANIFEST_NAME).stat()
    except OSError:
        return None
    return stat.st_mtime_ns, stat.st_size, stat.st_ino


def read_manifest_bytes(library_dir: Path) -> bytes:
    """The manifest's raw bytes; LibraryError if the directory holds no library."""
    path = library_dir / MANIFEST_NAME
    try:
        return path.read_bytes()
    except FileNotFoundError:
        if library_dir.is_dir():
            reason = f"{library_dir} holds no {MANIFEST_NAME}, so it is not a catalign library"
        else:
            reason = f"there is no library at {library_dir}"
        raise LibraryError(
            f"{reason}; build one with `catalign library build SRC... --out {library_dir}`"
        ) from None
    except OSError as exc:
        raise LibraryError(f"cannot read {path}: {exc}") from exc


def read_manifest(library_dir: Path) -> Manifest:
    """Read and parse ``manifest.json`` (no entry arrays are read)."""
    return Manifest.from_bytes(read_manifest_bytes(library_dir), library_dir)


@contextmanager
def writer_lock(library_dir: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on the library's lock file (threads and processes alike)."""
    library_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(library_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            logger.info("waiting for another writer of %s", library_dir)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def write_entry(library_dir: Path, entry: LibraryEntry) -> EntryRecord:
    """Write one entry file (temporary name, fsync, rename) and return its manifest record.

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
        bbox_min=_vector(entry.bbox_min),
        bbox_max=_vector(entry.bbox_max),
        size=_vector(entry.size),
        category=entry.category,
        symmetry=entry.symmetry.order,
    )


def read_entry(library_dir: Path, model_id: str, record: EntryRecord) -> LibraryEntry:
    """Read one entry file and check it against its record; its arrays view a read-only map of
    the file, shared with every process that reads the same library.

    A missing file raises FileNotFoundError (the caller may re-read a manifest that changed
    meanwhile); any other problem raises LibraryCorruptError naming the entry.
    """
    data = map_file(library_dir / record.file)

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
        arrays = mapped_arrays(data)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise corrupt(f"is not a readable .npz file ({exc})") from exc
    try:
        entry = entry_from_arrays(arrays)
    except (KeyError, TypeError, ValueError) as exc:
        raise corrupt(f"is malformed ({type(exc).__name__}: {exc})") from exc
    if entry.model_id != model_id:
        raise corrupt(f"holds model {entry.model_id!r}")
    if (entry.num_points, entry.num_keypoints) != (record.num_points, record.num_keypoints):
        raise corrupt("does not match the point counts in the manifest")
    if record.symmetry is None:
        symmetry = find_yaw_symmetry(entry.points)
    else:
        symmetry = YawSymmetry(record.symmetry)
    return dataclasses.replace(entry, category=record.category, symmetry=symmetry)


def commit(library_dir: Path, manifest: Manifest) -> None:
    """Make ``manifest`` current: fsync the new entry files' folder, write the manifest
    atomically, then delete whatever it no longer references."""
    entries_dir = library_dir / ENTRIES_DIR
    entries_dir.mkdir(parents=True, exist_ok=True)
    fsync_directory(entries_dir)
    fsync_directory(library_dir)
    atomic_write_bytes(library_dir / MANIFEST_NAME, manifest.to_bytes())
    clean_unreferenced(library_dir, {r.file for r in manifest.entries.values()})


def clean_unreferenced(library_dir: Path, referenced: set[str]) -> None:
    """Delete entry files not in ``referenced`` and leftover temporary manifests."""
    entries_dir = library_dir / ENTRIES_DIR
    names = entries_dir.iterdir() if entries_dir.is_dir() else iter(())
    stale = [p for p in names if f"{ENTRIES_DIR}/{p.name}" not in referenced]
    stale += list(library_dir.glob(f".{MANIFEST_NAME}.*.tmp"))
    for path in stale:
        if path.is_file():
            path.unlink(missing_ok=True)
    if stale:
        logger.info("removed %d unreferenced file(s) from %s", len(stale), library_dir)
        if entries_dir.is_dir():
            fsync_directory(entries_dir)


def _typed(value: Any, kind: Any) -> Any:
    if not isinstance(value, kind) or isinstance(value, bool):
        raise TypeError(f"unexpected {type(value).__name__} {value!r}")
    return value


def _vector(values: Any) -> tuple[float, float, float]:
    items = [float(_typed(v, int | float)) for v in values]
    if len(items) != 3:
        raise ValueError(f"expected 3 numbers, got {len(items)}")
    return (items[0], items[1], items[2])
