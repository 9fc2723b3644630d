"""A loaded library: :func:`load` checks the format version, the extractor fingerprint and every
entry's checksum, and returns a :class:`Library` whose arrays view the entry files
(memory-mapped, shared between processes), with the descriptors and sizes stacked for
:func:`~catalign.library.retrieval.shortlist`. Writing is :mod:`catalign.library.index`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from catalign.errors import (
    InvalidInputError,
    LibraryCorruptError,
    LibraryError,
    LibraryMismatchError,
    ModelNotFoundError,
)
from catalign.geometry.symmetry import YawSymmetry
from catalign.library.entry import LibraryEntry
from catalign.library.store import (
    Manifest,
    Stamp,
    manifest_stamp,
    read_entry,
    read_manifest_and_stamp,
    rebuild_hint,
)
from catalign.limits import max_memory_maps, raise_open_files_limit

logger = logging.getLogger(__name__)

# Files a serving process opens besides its library's entries.
_SPARE_FILES = 512
_LOAD_ATTEMPTS = 5  # a writer may commit and delete files while a reader reads the entries


class Library:
    """A loaded library: every entry in memory, plus stacked arrays for shortlisting.

    Example::

        library = load("model_store/library", extractor.fingerprint)
        ids = shortlist(library, global_descriptor(query.features), np.ptp(points, axis=0), k=5)
        model = library[ids[0]]  # LibraryEntry: points, keypoints, features, ...

    ``ids`` are sorted; ``descriptors`` (E,K) float32 (``unit_descriptors`` the same of unit
    length), ``sizes`` (E,3) float64 and ``categories`` (E,) follow them.
    """

    def __init__(self, path: Path, manifest: Manifest, entries: Sequence[LibraryEntry]) -> None:
        self.path = path
        self.manifest = manifest
        self.fingerprint = manifest.fingerprint
        self.voxel_size = manifest.voxel_size
        ordered = sorted(entries, key=lambda e: e.model_id)
        self.ids: list[str] = [e.model_id for e in ordered]
        self._entries = {e.model_id: e for e in ordered}
        width = ordered[0].descriptor.shape[0] if ordered else 0
        self.descriptors = np.zeros((len(ordered), width), dtype=np.float32)
        self.sizes = np.zeros((len(ordered), 3), dtype=np.float64)
        self.categories = np.array([e.category for e in ordered], dtype=object)
        held = {e.category for e in ordered}
        self._only_category = held.pop() if len(held) == 1 else ""
        for row, entry in enumerate(ordered):
            self.descriptors[row] = entry.descriptor
            self.sizes[row] = entry.size
        # Unit-length descriptors, so that a query's cosine with every entry is one product.
        norms = np.linalg.norm(self.descriptors, axis=1, keepdims=True)
        self.unit_descriptors = self.descriptors / np.maximum(norms, 1e-12)
        for array in (self.descriptors, self.sizes, self.unit_descriptors):
            array.flags.writeable = False

    def __len__(self) -> int:
        return len(self.ids)

    def category_counts(self) -> dict[str, int]:
        """How many entries each category holds, by name."""
        names, counts = np.unique(self.categories.astype(str), return_counts=True)
        return {str(name): int(count) for name, count in zip(names, counts, strict=True)}

    def only_category(self) -> str:
        """The category of every entry, or "" when the library holds several (or none)."""
        return self._only_category

    def of_category(self, category: str | None) -> np.ndarray | None:
        """The rows (a mask over ``ids``) of ``category``'s entries; None for every entry
        (``category`` None). An unknown category raises InvalidInputError listing the
        library's."""
        if category is None:
            return None
        rows = self.categories == category
        if not rows.any():
            held = ", ".join(f"{n} ({c})" for n, c in self.category_counts().items())
            raise InvalidInputError(
                f"no model of category {category!r} in the library; it holds {held or 'no models'}"
            )
        return rows

    def symmetry(self, model_id: str) -> YawSymmetry:
        """The turns about its up under which an entry looks the same."""
        return self[model_id].symmetry

    def __contains__(self, model_id: object) -> bool:
        return model_id in self._entries

    def __getitem__(self, model_id: str) -> LibraryEntry:
        try:
            return self._entries[model_id]
        except KeyError:
            raise ModelNotFoundError(
                f"no model {model_id!r} in the library ({len(self)} models)"
            ) from None

    def __iter__(self) -> Iterator[LibraryEntry]:
        return iter(self._entries.values())

    def __repr__(self) -> str:
        return f"Library({str(self.path)!r}, {len(self)} models, extractor {self.fingerprint!r})"


def load(library_dir: str | Path, extractor_fingerprint: str | None) -> Library:
    """Load and verify a library for an extractor (``None`` skips the fingerprint check).

    Raises LibraryError if there is no library (or one of an older format, naming the command
    that converts it), LibraryCorruptError for a bad catalogue, an unknown format version or an
    entry that fails its checks, LibraryMismatchError if it was built with another extractor.
    """
    library_dir = Path(library_dir)
    for _ in range(_LOAD_ATTEMPTS):
        manifest, stamp = read_manifest_and_stamp(library_dir)
        if extractor_fingerprint is not None:
            check_fingerprint(manifest, extractor_fingerprint, library_dir)
        _check_process_limits(len(manifest.entries), library_dir)
        entries = _read_entries(library_dir, manifest, stamp)
        if entries is not None:
            _check_descriptors(library_dir, entries)
            logger.info("loaded library %s: %d models", library_dir, len(entries))
            return Library(library_dir, manifest, entries)
    raise LibraryError(f"the library at {library_dir} kept changing while it was read; try again")


def _check_process_limits(count: int, library_dir: Path) -> None:
    """Every entry keeps its file open and mapped while it is served, twice over while a
    changed library replaces the old: raise the open-files limit to match, or say plainly why
    the library cannot be served by this process (instead of failing half-way through it)."""
    wanted = 2 * count + _SPARE_FILES
    allowed = raise_open_files_limit(wanted)
    maps = max_memory_maps()
    if allowed < wanted or (maps is not None and maps < wanted):
        limit = (
            f"may open {allowed} files (ulimit -n)"
            if allowed < wanted
            else f"may hold {maps} memory maps (vm.max_map_count)"
        )
        raise LibraryError(
            f"the library at {library_dir} holds {count} models, each kept open and mapped "
            f"while served (twice while a changed library replaces it): this process {limit}, "
            f"and {wanted} are needed; raise that limit or split the library by category"
        )


def check_fingerprint(manifest: Manifest, fingerprint: str, library_dir: Path) -> None:
    if manifest.fingerprint != fingerprint:
        raise LibraryMismatchError(
            f"the library at {library_dir} was built with feature extractor "
            f"{manifest.fingerprint!r}, but this one is {fingerprint!r}, so their features are "
            f"not comparable; {rebuild_hint(library_dir)} (with the current extractor)"
        )


def _read_entries(library_dir: Path, manifest: Manifest, stamp: Stamp) -> list[LibraryEntry] | None:
    """Every entry of ``manifest``; None if a file vanished because a writer committed since.

    A missing file is corruption only while the state that names it is still current (its
    stamp) and the file is still missing: a writer that removed the entry and added it back
    meanwhile wrote the very same record, and the file exists again.
    """
    entries = []
    for model_id in manifest.ids:
        record = manifest.entries[model_id]
        try:
            entries.append(read_entry(library_dir, model_id, record))
        except FileNotFoundError:
            if manifest_stamp(library_dir) != stamp or (library_dir / record.file).is_file():
                return None
            raise LibraryCorruptError(
                f"library entry {model_id!r}: its file {library_dir / record.file} is missing; "
                f"remove the entry or {rebuild_hint(library_dir)}"
            ) from None
    return entries


def _check_descriptors(library_dir: Path, entries: Sequence[LibraryEntry]) -> None:
    widths = {e.descriptor.shape[0] for e in entries}
    if len(widths) > 1:
        raise LibraryCorruptError(
            f"the entries of {library_dir} have descriptors of different lengths "
            f"({sorted(widths)}); {rebuild_hint(library_dir)}"
        )
