"""New shortlisting descriptors for a built library, from its own entries (``catalign library
redescribe DIR``).

A library's descriptors come from the retrieval encoders (:mod:`catalign.features.retrieval`),
which sit on the features; the features come from the network's weights. New encoders over the
same weights change only the descriptors, and an entry's descriptor is computed from exactly the
key points and features the entry keeps (:func:`~catalign.library.entry.describe_shape`). So a
library can take new encoders without its source files and without the network: every entry is
read, described again and written under its new content-addressed name beside the old file;
then one transaction points every row at its new file and sets the new fingerprint, and only
then are the old files deleted. Killed at any point, it leaves the old library whole (its
leftovers swept by the next write) or the new one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from catalign.errors import LibraryMismatchError
from catalign.library.records import Manifest, rebuild_hint
from catalign.library.retrieval import model_descriptor
from catalign.library.shortlist_index import write_index
from catalign.library.store import (
    begin_write,
    commit_changes,
    read_entry,
    read_manifest,
    utc_now,
    write_entry,
    writer_lock,
)

if TYPE_CHECKING:
    from catalign.features.extractor import FeatureExtractor


def redescribe(
    library_dir: str | Path,
    extractor: FeatureExtractor,
    progress: Callable[[int, int], None] | None = None,
) -> Manifest:
    """Describe every entry of ``library_dir`` again with ``extractor``'s retrieval encoders and
    return the library under ``extractor``'s fingerprint; one already under it is returned as
    it is. ``progress`` is called with (done, total) after each entry.

    Raises LibraryMismatchError where the library's features come from other weights than
    ``extractor``'s (then only a rebuild helps), LibraryCorruptError for an entry that cannot be
    read.
    """
    from catalign.features.extractor import features_fingerprint

    library_dir = Path(library_dir)
    with writer_lock(library_dir):
        old = read_manifest(library_dir)
        if old.fingerprint == extractor.fingerprint:
            return old
        if features_fingerprint(old.fingerprint) != features_fingerprint(extractor.fingerprint):
            raise LibraryMismatchError(
                f"the library at {library_dir} holds the features of extractor "
                f"{old.fingerprint!r}, not of {extractor.fingerprint!r}, and new descriptors "
                f"cannot make them comparable; {rebuild_hint(library_dir)}"
            )
        begin_write(library_dir)
        records = {}
        for done, model_id in enumerate(old.ids, start=1):
            entry = read_entry(library_dir, model_id, old.entries[model_id])
            described = model_descriptor(extractor, entry.keypoints, entry.features)
            records[model_id] = write_entry(library_dir, replace(entry, descriptor=described))
            if progress is not None:
                progress(done, len(old.entries))
        updated = utc_now()
        # one transaction: every row and the fingerprint; then the old files and the mark go
        write_index(library_dir, records)  # first: until the commit its keys match no record
        commit_changes(library_dir, put=records, fingerprint=extractor.fingerprint, updated=updated)
    return replace(old, fingerprint=extractor.fingerprint, updated=updated, entries=records)
