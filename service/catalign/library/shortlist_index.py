"""The shortlist's approximate nearest-neighbour index: a graph over the entries' descriptors,
one per category, persisted beside the catalogue, so that a query finds the entries nearest its
descriptor without scoring every entry (usearch's HNSW; ``docs/benchmarks.md`` compares it with
faiss and hnswlib).

The index is an accelerator, never the truth: the catalogue is. Each indexed key names an entry
and a digest of the descriptor it was built from, and a reader keeps only the keys whose entry
still holds that descriptor. Entries added or described again since the index was written are
*unindexed*: the shortlist scores them exactly beside the graph's neighbours, so an add or a
remove changes the answers at once and costs the index nothing; writing the index again
(:func:`write_index`, ``catalign library index``) folds them in, and an add does so itself once
more than :func:`stale_limit` entries wait (:func:`waiting_entries`). A missing or unreadable
index leaves the exact scan.

Layout: ``shortlist-index/index.json`` names one ``<category>-<token>.usearch`` file per
category, with the ids and descriptor digests of its keys. The graph files are written first
and the JSON last, by rename, so a reader sees one whole index or the one before it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from catalign.atomic import atomic_write_bytes, fsync_directory, fsync_file
from catalign.library.records import EntryRecord

if TYPE_CHECKING:  # imported where an index is read or written: 0.15 s a process otherwise
    from usearch.index import Index

logger = logging.getLogger(__name__)

INDEX_DIR = "shortlist-index"
INDEX_NAME = "index.json"
INDEX_FORMAT = 1
# The graph's shape (``bench/shortlist_index.py`` measured these): neighbours per node and the
# breadth of the search while building; a query's breadth follows the candidates it asks for.
CONNECTIVITY = 16
EXPANSION_ADD = 128
MIN_EXPANSION_SEARCH = 64
# Unindexed entries (or a tenth of the library, if more) past which an add writes the index
# again and a load warns: at 10^5 entries a write takes about 6 s, once per 10^4 adds.
STALE_INDEX_ENTRIES = 1_000


def stale_limit(entries: int) -> int:
    """How many of a library's ``entries`` may wait unindexed before the index is stale."""
    return max(STALE_INDEX_ENTRIES, entries // 10)


def waiting_entries(library_dir: Path, entries: int) -> int:
    """About how many of the library's ``entries`` its index lacks, from ``index.json``'s key
    count alone (cheap: no record is read; an entry replaced since is not counted): all of
    them without a readable index."""
    try:
        document = json.loads((library_dir / INDEX_DIR / INDEX_NAME).read_bytes())
        listed = sum(len(item["ids"]) for item in document["categories"].values())
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return entries
    return max(entries - listed, 0)


def descriptor_digest(descriptor: bytes) -> str:
    """What an index remembers of the descriptor it indexed (16 hex digits)."""
    return hashlib.blake2b(descriptor, digest_size=8).hexdigest()


@dataclass(frozen=True)
class IndexSummary:
    """What :func:`write_index` wrote: entries per category, and the time it took."""

    categories: dict[str, int]
    seconds: float

    @property
    def entries(self) -> int:
        return sum(self.categories.values())


def write_index(
    library_dir: Path,
    records: dict[str, EntryRecord],
    threads: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> IndexSummary:
    """Build the index of ``records`` (the catalogue's, by id) and make it the library's,
    replacing the one before; ``threads`` 0 uses every core. ``progress(done, total)`` is
    called after each category."""
    from usearch.index import Index

    started = time.perf_counter()
    folder = library_dir / INDEX_DIR
    folder.mkdir(parents=True, exist_ok=True)
    by_category: dict[str, list[str]] = {}
    for model_id in sorted(records):
        by_category.setdefault(records[model_id].category, []).append(model_id)
    total, done = len(records), 0
    listed = {}
    for category, ids in sorted(by_category.items()):
        vectors = unit_rows([records[i].descriptor for i in ids])
        if vectors.shape[1] == 0:  # entries without descriptors: the exact scan serves them
            continue
        graph = Index(
            ndim=vectors.shape[1],
            metric="ip",
            dtype="f32",
            connectivity=CONNECTIVITY,
            expansion_add=EXPANSION_ADD,
        )
        graph.add(np.arange(len(ids), dtype=np.uint64), vectors, threads=threads)
        name = f"{category}-{secrets.token_hex(6)}.usearch"
        graph.save(str(folder / name))
        fsync_file(folder / name)  # whole on disk before index.json names it
        listed[category] = {
            "file": name,
            "ids": ids,
            "digests": [descriptor_digest(records[i].descriptor) for i in ids],
        }
        done += len(ids)
        if progress is not None:
            progress(done, total)
    fsync_directory(folder)
    document = {"format": INDEX_FORMAT, "categories": listed}
    atomic_write_bytes(folder / INDEX_NAME, json.dumps(document).encode())
    kept = {INDEX_NAME} | {item["file"] for item in listed.values()}
    for path in folder.iterdir():  # the index this one replaced, and any half-written one
        if path.name not in kept and path.is_file():
            path.unlink(missing_ok=True)
    indexed = {c: len(item["ids"]) for c, item in listed.items()}
    return IndexSummary(indexed, time.perf_counter() - started)


def index_status(library_dir: Path, records: dict[str, EntryRecord]) -> str:
    """One line on the library's index for ``catalign library info``."""
    index = read_index(library_dir, sorted(records), records)
    if index is None:
        return f"none (write it with `catalign library index {library_dir}`)"
    line = f"{index.indexed} of {len(records)} entries"
    if index.unindexed:
        line += f"; {index.unindexed} scored exactly until `catalign library index {library_dir}`"
    return line


class ShortlistIndex:
    """A library's index as one reader sees it: the graphs memory-mapped (shared by every
    process that maps them), their keys turned into rows of the library's ids, and the rows
    no graph holds.

    Example::

        index = read_index(library_dir, library.ids, records)
        rows = index.candidates(query_descriptors, count=256, category="chair")
    """

    def __init__(
        self,
        graphs: dict[str, tuple[Index, np.ndarray]],
        unindexed: dict[str, np.ndarray],
    ) -> None:
        self._graphs = graphs
        self._unindexed = unindexed

    @property
    def indexed(self) -> int:
        """Entries a graph finds."""
        return sum(int(np.sum(rows >= 0)) for _, rows in self._graphs.values())

    @property
    def unindexed(self) -> int:
        """Entries scored exactly beside the graphs (added or described again since)."""
        return sum(len(rows) for rows in self._unindexed.values())

    def candidates(
        self, queries: np.ndarray, count: int, category: str | None = None
    ) -> np.ndarray:
        """Rows (sorted, unique) of the ``count`` entries nearest each query descriptor (V,K),
        by cosine, in the graph of ``category`` (None: of every category), and every
        unindexed row in that scope."""
        scope = (
            [category]
            if category is not None
            else sorted(self._graphs.keys() | self._unindexed.keys())
        )
        found = []
        queries = np.asarray(queries, dtype=np.float32).reshape(-1, np.shape(queries)[-1])
        norms = np.linalg.norm(queries, axis=1, keepdims=True)  # the graphs hold unit rows
        queries = np.ascontiguousarray(queries / np.maximum(norms, 1e-12), dtype=np.float32)
        for name in scope:
            if name in self._graphs:
                graph, rows = self._graphs[name]
                wanted = min(count, len(rows))
                if wanted > 0:
                    graph.expansion_search = max(MIN_EXPANSION_SEARCH, 2 * wanted)
                    matches = graph.search(queries, wanted, threads=1)
                    keys = np.asarray(matches.keys, dtype=np.int64).reshape(-1)
                    keys = keys[(keys >= 0) & (keys < len(rows))]
                    found.append(rows[keys])
            found.append(self._unindexed.get(name, np.zeros(0, dtype=np.int64)))
        every = np.concatenate(found) if found else np.zeros(0, dtype=np.int64)
        return np.unique(every[every >= 0])


def read_index(
    library_dir: Path, ids: Sequence[str], records: dict[str, EntryRecord]
) -> ShortlistIndex | None:
    """The library's index for a reader of ``ids`` (sorted) with these ``records``; None when
    the library has none, or one that cannot be read (logged: the exact scan serves)."""
    folder = library_dir / INDEX_DIR
    try:
        document = json.loads((folder / INDEX_NAME).read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        logger.warning("ignoring the shortlist index of %s: %s", library_dir, error)
        return None
    try:
        return _opened(folder, document, ids, records)
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as error:
        logger.warning(
            "ignoring the shortlist index of %s (%s); write it again with "
            "`catalign library index %s`",
            library_dir,
            error,
            library_dir,
        )
        return None


def _opened(
    folder: Path, document: dict, ids: Sequence[str], records: dict[str, EntryRecord]
) -> ShortlistIndex:
    from usearch.index import Index

    if document.get("format") != INDEX_FORMAT:
        raise ValueError(f"index format {document.get('format')!r}, expected {INDEX_FORMAT}")
    row_of = {model_id: row for row, model_id in enumerate(ids)}
    covered = np.zeros(len(ids), dtype=bool)
    graphs = {}
    for category, listed in document["categories"].items():
        keyed_ids, digests = listed["ids"], listed["digests"]
        if len(keyed_ids) != len(digests):
            raise ValueError(
                f"category {category!r} lists {len(keyed_ids)} ids but {len(digests)} digests"
            )
        rows = np.full(len(keyed_ids), -1, dtype=np.int64)
        for key, (model_id, digest) in enumerate(zip(keyed_ids, digests, strict=True)):
            record = records.get(model_id)
            if (
                record is not None
                and record.category == category
                and descriptor_digest(record.descriptor) == digest
            ):
                rows[key] = row_of[model_id]
        graph = Index.restore(str(folder / listed["file"]), view=True)
        if graph is None or len(graph) != len(keyed_ids):
            raise ValueError(
                f"the graph of category {category!r} does not hold its {len(keyed_ids)} keys"
            )
        graphs[category] = (graph, rows)
        covered[rows[rows >= 0]] = True
    unindexed: dict[str, list[int]] = {}
    for row in np.flatnonzero(~covered):
        unindexed.setdefault(records[ids[row]].category, []).append(int(row))
    return ShortlistIndex(graphs, {c: np.array(r, dtype=np.int64) for c, r in unindexed.items()})


def unit_rows(descriptors: Sequence[bytes]) -> np.ndarray:
    """Descriptors (float32 little-endian bytes) stacked as unit rows."""
    vectors = np.array([np.frombuffer(d, dtype="<f4") for d in descriptors], dtype=np.float32)
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.ascontiguousarray(vectors / np.maximum(norms, 1e-12), dtype=np.float32)
