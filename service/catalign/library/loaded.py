"""A loaded library: :func:`load` checks the format version, the extractor fingerprint, every
record of the catalogue and that every entry file is there, and returns a :class:`Library` that
stacks the descriptors and sizes the catalogue holds for
:func:`~catalign.library.retrieval.shortlist`. An entry's file is read when the entry is first
needed (its checksum and arrays checked then) and kept in a small cache: a request reads only
the entries it shortlists, and a process holds no file open, so the library's size is bound
by disk and by the catalogue in memory, not by how many files or maps a process may hold.
Writing is :mod:`catalign.library.index`'s.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from catalign.errors import (
    InvalidInputError,
    LibraryChangedError,
    LibraryCorruptError,
    LibraryError,
    LibraryMismatchError,
    ModelNotFoundError,
)
from catalign.geometry.symmetry import YawSymmetry
from catalign.library.entry import LibraryEntry
from catalign.library.outline import Outline, outline_of
from catalign.library.shortlist_index import ShortlistIndex, read_index, stale_limit
from catalign.library.store import (
    ENTRIES_DIR,
    EntryRecord,
    Manifest,
    Stamp,
    manifest_stamp,
    read_entry,
    read_manifest_and_stamp,
    rebuild_hint,
)

logger = logging.getLogger(__name__)

# Entries read from disk that a process keeps (about half a megabyte each, read back): more
# than one request shortlists, fewer than a library of thousands holds.
CACHED_ENTRIES = 128
_LOAD_ATTEMPTS = 5  # a writer may commit and delete files while a reader checks the entries


class Library:
    """A loaded library: the catalogue's records and stacked arrays in memory, each entry read
    from disk when it is first asked for.

    Example::

        library = load("model_store/library", extractor.fingerprint)
        rows = shortlist(library, views, k=5, ...)  # over library.unit_descriptors
        model = library[library.ids[rows[0]]]  # LibraryEntry: points, keypoints, features, ...

    ``ids`` are sorted; ``descriptors`` (E,K) float32 (``unit_descriptors`` the same of unit
    length), ``sizes`` (E,3) float64 and ``categories`` (E,) follow them. ``index`` is the
    library's shortlist index (None when it has none, or for ``entries``). ``entries``, when
    given, are held in memory instead of read from ``path`` (a library made in a test).
    """

    def __init__(
        self,
        path: Path,
        manifest: Manifest,
        entries: Sequence[LibraryEntry] | None = None,
        stamp: Stamp | None = None,
    ) -> None:
        self.path = path
        self.manifest = manifest
        self.fingerprint = manifest.fingerprint
        self.voxel_size = manifest.voxel_size
        self._stamp = stamp
        self._held = {e.model_id: e for e in entries or ()}
        self.index: ShortlistIndex | None = None
        if entries is None:
            self.ids: list[str] = manifest.ids
            records = [manifest.entries[i] for i in self.ids]
            categories = [r.category for r in records]
            sizes = [r.size for r in records]
            vectors = [np.frombuffer(r.descriptor, dtype="<f4") for r in records]
            self.index = read_index(path, self.ids, manifest.entries)
        else:
            self.ids = sorted(self._held)
            held = [self._held[i] for i in self.ids]
            categories = [e.category for e in held]
            sizes = [e.size for e in held]
            vectors = [e.descriptor for e in held]
        self._rows = {model_id: row for row, model_id in enumerate(self.ids)}
        width = len(vectors[0]) if vectors else 0
        self.descriptors = np.array(vectors, dtype=np.float32).reshape(len(self.ids), width)
        self.sizes = np.array(sizes, dtype=np.float64).reshape(len(self.ids), 3)
        self.categories = np.array(categories, dtype=object)
        names, counts = np.unique(self.categories.astype(str), return_counts=True)
        self._counts = {str(n): int(c) for n, c in zip(names, counts, strict=True)}
        # each category's rows, found once: a query naming one reads its mask
        self._masks = {str(n): self.categories == n for n in names}
        for mask in self._masks.values():
            mask.flags.writeable = False
        self._only_category = str(names[0]) if len(names) == 1 else ""
        # Unit-length descriptors, so that a query's cosine with every entry is one product.
        norms = np.linalg.norm(self.descriptors, axis=1, keepdims=True)
        self.unit_descriptors = self.descriptors / np.maximum(norms, 1e-12)
        for array in (self.descriptors, self.sizes, self.unit_descriptors):
            array.flags.writeable = False
        self._cache: OrderedDict[str, LibraryEntry] = OrderedDict()
        self._made_outlines: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.ids)

    def category_counts(self) -> dict[str, int]:
        """How many entries each category holds, by name."""
        return dict(self._counts)

    def only_category(self) -> str:
        """The category of every entry, or "" when the library holds several (or none)."""
        return self._only_category

    def of_category(self, category: str | None) -> np.ndarray | None:
        """The rows (a mask over ``ids``) of ``category``'s entries; None for every entry
        (``category`` None). An unknown category raises InvalidInputError listing the
        library's."""
        if category is None:
            return None
        rows = self._masks.get(category)
        if rows is None:
            held = ", ".join(f"{n} ({c})" for n, c in self.category_counts().items())
            raise InvalidInputError(
                f"no model of category {category!r} in the library; it holds {held or 'no models'}"
            )
        return rows

    def record(self, model_id: str) -> EntryRecord:
        """What the catalogue says of an entry (no file is read)."""
        self._check_known(model_id)
        return self.manifest.entries[model_id]

    def symmetry(self, model_id: str) -> YawSymmetry:
        """The turns about its up under which an entry looks the same."""
        if model_id not in self._held:
            order = self.record(model_id).symmetry
            if order is not None:
                return YawSymmetry(order)
        return self[model_id].symmetry

    def outlines(self, rows: Sequence[int]) -> list[Outline]:
        """The outlines of the entries at ``rows`` (of ``ids``), for the shortlist: as their
        records hold them, or made from the entry's points (and kept) where a record written
        before outlines, or an entry held in memory, has none."""
        found = []
        for row in rows:
            model_id = self.ids[row]
            data = b"" if model_id in self._held else self.manifest.entries[model_id].outline
            if not data:
                data = self._made_outlines.get(model_id, b"")
            if not data:
                data = outline_of(self[model_id].points).to_bytes()
                with self._lock:
                    self._made_outlines[model_id] = data
            try:
                found.append(Outline.from_bytes(data))
            except ValueError as exc:
                raise LibraryCorruptError(
                    f"library entry {model_id!r} of {self.path} has a malformed outline ({exc}); "
                    f"describe it again or {rebuild_hint(self.path)}"
                ) from exc
        return found

    def in_memory(self) -> Library:
        """This library with every entry read into memory, to serve after its folder is gone
        (an evaluation's library, built in a temporary folder)."""
        return Library(self.path, self.manifest, list(self), stamp=self._stamp)

    def verify(self) -> None:
        """Read and check every entry's file (what serving does lazily), so that a damaged
        one is named now; raises LibraryCorruptError."""
        for model_id in self.ids:
            self._read(model_id)

    def __contains__(self, model_id: object) -> bool:
        return model_id in self._rows

    def __getitem__(self, model_id: str) -> LibraryEntry:
        self._check_known(model_id)
        held = self._held.get(model_id)
        if held is not None:
            return held
        with self._lock:
            cached = self._cache.get(model_id)
            if cached is not None:
                self._cache.move_to_end(model_id)
                return cached
        entry = self._read(model_id)
        with self._lock:
            self._cache[model_id] = entry
            while len(self._cache) > CACHED_ENTRIES:
                self._cache.popitem(last=False)
        return entry

    def __iter__(self) -> Iterator[LibraryEntry]:
        return (self[model_id] for model_id in self.ids)

    def __repr__(self) -> str:
        return f"Library({str(self.path)!r}, {len(self)} models, extractor {self.fingerprint!r})"

    def _check_known(self, model_id: str) -> None:
        if model_id not in self._rows:
            raise ModelNotFoundError(f"no model {model_id!r} in the library ({len(self)} models)")

    def _read(self, model_id: str) -> LibraryEntry:
        """An entry's file, read and checked. A file gone because a writer replaced or removed
        the entry since this library was loaded is a LibraryChangedError (worth a retry on the
        new state); gone while the catalogue still names it, corruption."""
        record = self.manifest.entries[model_id]
        try:
            return read_entry(self.path, model_id, record)
        except FileNotFoundError:
            if manifest_stamp(self.path) != self._stamp:
                raise LibraryChangedError(
                    f"library entry {model_id!r} was replaced or removed on disk while this "
                    "request ran; retry"
                ) from None
            raise _missing(self.path, model_id, record) from None


def load(
    library_dir: str | Path, extractor_fingerprint: str | None, *, outlines: bool = True
) -> Library:
    """Load and check a library for an extractor (``None`` skips the fingerprint check); the
    entries' files are checked as they are read (:meth:`Library.verify` reads them all).
    Without ``outlines`` the records' outlines are not read (a process that lists the models
    but registers nothing; :meth:`Library.outlines` would make them from the entries).

    Raises LibraryError if there is no library (or one of an older format, naming the command
    that converts it), LibraryCorruptError for a bad catalogue, an unknown format version or a
    missing entry file, LibraryMismatchError if it was built with another extractor.
    """
    library_dir = Path(library_dir)
    for _ in range(_LOAD_ATTEMPTS):
        manifest, stamp = read_manifest_and_stamp(library_dir, outlines)
        if extractor_fingerprint is not None:
            check_fingerprint(manifest, extractor_fingerprint, library_dir)
        if _files_present(library_dir, manifest, stamp):
            _check_descriptors(library_dir, manifest)
            library = Library(library_dir, manifest, stamp=stamp)
            _log_loaded(library)
            return library
    raise LibraryError(f"the library at {library_dir} kept changing while it was read; try again")


def _log_loaded(library: Library) -> None:
    """Say what was loaded, and when many entries wait for the index to be written again."""
    index = library.index
    indexed = "no shortlist index" if index is None else f"{index.indexed} in its index"
    logger.info("loaded library %s: %d models, %s", library.path, len(library), indexed)
    if index is not None and index.unindexed > stale_limit(len(library)):
        logger.warning(
            "%d entries of %s were added or changed since its shortlist index was written and "
            "are scored one by one; write it again with `catalign library index %s`",
            index.unindexed,
            library.path,
            library.path,
        )


def check_fingerprint(manifest: Manifest, fingerprint: str, library_dir: Path) -> None:
    """Refuse a library whose features or descriptors another extractor made, saying what
    mends it: new descriptors alone, or a rebuild."""
    from catalign.features.extractor import features_fingerprint  # torch: only when needed

    if manifest.fingerprint == fingerprint:
        return
    if features_fingerprint(manifest.fingerprint) == features_fingerprint(fingerprint):
        raise LibraryMismatchError(
            f"the library at {library_dir} was shortlisted by other retrieval encoders "
            f"({manifest.fingerprint!r}) than this extractor's ({fingerprint!r}); describe it "
            f"again from its entries with `catalign library redescribe {library_dir}`"
        )
    raise LibraryMismatchError(
        f"the library at {library_dir} was built with feature extractor "
        f"{manifest.fingerprint!r}, but this one is {fingerprint!r}, so their features are "
        f"not comparable; {rebuild_hint(library_dir)} (with the current extractor)"
    )


def _files_present(library_dir: Path, manifest: Manifest, stamp: Stamp) -> bool:
    """Whether every file ``manifest`` names is there (one listing of the entries folder);
    False if one vanished because a writer committed since.

    A missing file is corruption only while the state that names it is still current (its
    stamp) and the file is still missing: a writer that removed the entry and added it back
    meanwhile wrote the very same record, and the file exists again.
    """
    present = _entry_names(library_dir / ENTRIES_DIR)
    prefix = len(ENTRIES_DIR) + 1
    for model_id in manifest.ids:
        record = manifest.entries[model_id]
        if record.file[prefix:] in present:
            continue
        if manifest_stamp(library_dir) != stamp or (library_dir / record.file).is_file():
            return False
        raise _missing(library_dir, model_id, record)
    return True


def _entry_names(folder: Path) -> set[str]:
    return set(os.listdir(folder)) if folder.is_dir() else set()


def _missing(library_dir: Path, model_id: str, record: EntryRecord) -> LibraryCorruptError:
    return LibraryCorruptError(
        f"library entry {model_id!r}: its file {library_dir / record.file} is missing; "
        f"remove the entry or {rebuild_hint(library_dir)}"
    )


def _check_descriptors(library_dir: Path, manifest: Manifest) -> None:
    widths = {len(record.descriptor) // 4 for record in manifest.entries.values()}
    if len(widths) > 1 or 0 in widths:
        raise LibraryCorruptError(
            f"the entries of {library_dir} have descriptors of different lengths "
            f"({sorted(widths)}); {rebuild_hint(library_dir)}"
        )
