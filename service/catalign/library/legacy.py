"""Libraries of format 2, whose catalogue was one JSON file (``manifest.json``), rewritten whole
at every change: :func:`migrate` converts one in place (``catalign library migrate DIR``).

Nothing else reads them: a reader or writer given one refuses it with the command that
converts it (:func:`~catalign.library.catalogue_db.no_catalogue`), never misreading it. The
entry files are the same in both formats and stay where they are, byte for byte; only the
catalogue is written, under a temporary name and renamed into place, so a conversion killed at
any point leaves the library of format 2 or of format 3, whole. The JSON file goes last.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from catalign.errors import LibraryCorruptError, LibraryError
from catalign.library import catalogue
from catalign.library.catalogue_db import LEGACY_MANIFEST_NAME, no_catalogue
from catalign.library.records import (
    FORMAT_VERSION,
    EntryRecord,
    Manifest,
    rebuild_hint,
    typed,
)
from catalign.library.sources import CATEGORY_PATTERN, DEFAULT_CATEGORY
from catalign.library.store import commit, read_manifest, writer_lock

LEGACY_VERSION = 2  # 1 held no distance grids: only a rebuild makes it a library again


def migrate(library_dir: str | Path) -> Manifest:
    """Convert the format-2 library in ``library_dir`` to this format, in place, and return
    it; a library already converted is returned as it is (the JSON file a conversion killed
    after its rename left is deleted). Raises LibraryError where there is no library, and
    LibraryCorruptError for a JSON file that cannot be read or names a missing entry file."""
    library_dir = Path(library_dir)
    if not (library_dir / LEGACY_MANIFEST_NAME).is_file() and not catalogue.exists(library_dir):
        raise no_catalogue(library_dir)
    with writer_lock(library_dir):
        if catalogue.exists(library_dir):
            (library_dir / LEGACY_MANIFEST_NAME).unlink(missing_ok=True)
            return read_manifest(library_dir)
        manifest = read_legacy(library_dir)
        for model_id, record in manifest.entries.items():
            if not (library_dir / record.file).is_file():
                raise LibraryCorruptError(
                    f"library entry {model_id!r}: its file {library_dir / record.file} is "
                    f"missing, so {library_dir} cannot be converted; restore the file or "
                    f"{rebuild_hint(library_dir)}"
                )
        converted = dataclasses.replace(manifest, format_version=FORMAT_VERSION)
        commit(library_dir, converted)  # the catalogue renamed into place, then the JSON goes
    return converted


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
    if type(version) is not int or version != LEGACY_VERSION:
        raise LibraryCorruptError(
            f"{where} has library format version {version!r}, which cannot be converted "
            f"(only version {LEGACY_VERSION} can); {rebuild_hint(library_dir)}"
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
            format_version=LEGACY_VERSION,
            engine=typed(raw.get("engine", {}), dict),
            category=default_category,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryCorruptError(
            f"{where} is malformed ({type(exc).__name__}: {exc}); {rebuild_hint(library_dir)}"
        ) from exc
