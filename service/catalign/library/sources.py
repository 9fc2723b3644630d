"""Which files a library is built from, and the model id and units each one gets.

Callers name files and folders; this module expands folders (recursively, by supported suffix),
assigns model ids (the file stem unless ids are given) and categories (the one given, else the
sub-folder a file sits in under a named folder, ``SRC/table/a.ply`` -> ``table``, else
:data:`DEFAULT_CATEGORY`), checks every id and category against a strict pattern (ids become
file names, so no slashes, no leading dot, no path traversal) and refuses duplicates with a
message that names both files. It reads no geometry, so every mistake in the arguments is
reported before any slow work starts.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from catalign.errors import InvalidInputError, ShapeReadError
from catalign.geometry.io import SUPPORTED_SUFFIXES

MODEL_ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
# A category: a short lower-case name, as a detector's label (``chair``, ``table``, ``bin_2``).
CATEGORY_PATTERN = re.compile(r"[a-z][a-z0-9_-]{0,31}")
# The category of an entry whose source names none, and of every entry of a library written
# before entries had categories (its manifest may name another).
DEFAULT_CATEGORY = "chair"
UNIT_FACTORS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}


@dataclass(frozen=True)
class SourceFile:
    """One shape file, and the model id and category it will have in the library."""

    model_id: str
    path: Path
    category: str = DEFAULT_CATEGORY


def validate_model_id(model_id: str, origin: str | None = None) -> str:
    """Return ``model_id`` if it matches :data:`MODEL_ID_PATTERN`, else raise InvalidInputError."""
    if not isinstance(model_id, str) or MODEL_ID_PATTERN.fullmatch(model_id) is None:
        where = f" (from {origin})" if origin else ""
        raise InvalidInputError(
            f"{model_id!r}{where} is not a valid model id: use 1 to 128 letters, digits, '.', '_' "
            "or '-', starting with a letter or digit; rename the file or give an explicit id"
        )
    return model_id


def validate_category(category: str, origin: str | None = None) -> str:
    """Return ``category`` if it matches :data:`CATEGORY_PATTERN`, else raise
    InvalidInputError."""
    if not isinstance(category, str) or CATEGORY_PATTERN.fullmatch(category) is None:
        where = f" (from {origin})" if origin else ""
        raise InvalidInputError(
            f"{category!r}{where} is not a valid category: use 1 to 32 lower-case letters, "
            "digits, '_' or '-', starting with a letter (e.g. chair, table)"
        )
    return category


def unit_factor(units: str) -> float:
    """Metres per source unit: 1 for ``m``, 0.01 for ``cm``, 0.001 for ``mm``."""
    try:
        return UNIT_FACTORS[units]
    except (KeyError, TypeError):
        raise InvalidInputError(
            f"unknown units {units!r}; use one of {', '.join(UNIT_FACTORS)}"
        ) from None


def collect_sources(
    sources: Sequence[str | Path],
    ids: Sequence[str] | None = None,
    category: str | None = None,
    default: str = DEFAULT_CATEGORY,
) -> list[SourceFile]:
    """Expand ``sources`` into shape files with validated, unique model ids and categories.

    Folders are searched recursively for supported suffixes (sorted, so the order is stable).
    ``ids``, when given, names each source in turn; every source must then be a file.
    ``category`` is every file's category; without it, a file in a sub-folder of a named folder
    takes the sub-folder's name (``SRC/table/ikea/a.ply`` -> ``table``), any other file
    ``default`` (the library's default category).
    """
    if category is not None:
        validate_category(category)
    if isinstance(sources, str | Path):
        sources = [sources]
    if not sources:
        raise InvalidInputError("no sources given: name at least one shape file or folder")
    if ids is not None:
        if isinstance(ids, str):
            ids = [ids]
        if len(ids) != len(sources):
            raise InvalidInputError(
                f"{len(ids)} ids given for {len(sources)} sources; give one id per source file"
            )
    found: list[SourceFile] = []
    for index, source in enumerate(sources):
        path = Path(source)
        if path.is_dir():
            if ids is not None:
                raise InvalidInputError(
                    f"{path} is a folder, but explicit ids name single files; "
                    "list the files instead or leave the ids out"
                )
            files = _files_in(path)
            if not files:
                raise InvalidInputError(
                    f"{path} holds no supported shape files "
                    f"({' '.join(sorted(SUPPORTED_SUFFIXES))})"
                )
            found.extend(
                SourceFile(
                    validate_model_id(f.stem, str(f)),
                    f,
                    category or _folder_category(path, f, default),
                )
                for f in files
            )
        elif path.is_file():
            _check_suffix(path)
            model_id = path.stem if ids is None else ids[index]
            model_id = validate_model_id(model_id, str(path))
            found.append(SourceFile(model_id, path, category or default))
        else:
            raise ShapeReadError(f"{path}: no such file or folder")
    check_unique(found)
    return found


def check_unique(found: Sequence[SourceFile]) -> None:
    """Raise InvalidInputError if two sources share a model id, naming both files."""
    seen: dict[str, Path] = {}
    for item in found:
        first = seen.setdefault(item.model_id, item.path)
        if first is item.path:
            continue
        if first.resolve() == item.path.resolve():
            raise InvalidInputError(f"{item.path} is listed twice (model id {item.model_id!r})")
        raise InvalidInputError(
            f"model id {item.model_id!r} comes from two files, {first} and {item.path}; "
            "rename one of them or give explicit ids"
        )


def _folder_category(folder: Path, file: Path, default: str) -> str:
    """The category a file found in ``folder`` gets from the sub-folder it sits in
    (``default`` directly in ``folder``)."""
    parts = file.relative_to(folder).parts
    if len(parts) == 1:
        return default
    where = f"the sub-folder {folder / parts[0]}; rename it or pass a category (--category)"
    return validate_category(parts[0], where)


def _files_in(folder: Path) -> list[Path]:
    return sorted(
        p for p in folder.rglob("*") if p.suffix.lower() in SUPPORTED_SUFFIXES and p.is_file()
    )


def _check_suffix(path: Path) -> None:
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise InvalidInputError(
            f"{path}: unsupported file type {path.suffix or '(none)'}; "
            f"supported: {' '.join(sorted(SUPPORTED_SUFFIXES))}"
        )
