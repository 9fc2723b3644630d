"""The shortlist's index: its neighbours against the exact scan, and a reader that trusts only
the keys whose entry still holds the descriptor it indexed (real files written and read)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

from catalign.library.records import EntryRecord
from catalign.library.shortlist_index import (
    INDEX_DIR,
    INDEX_NAME,
    read_index,
    unit_rows,
    write_index,
)

WIDTH = 32


def record(descriptor: np.ndarray, category: str = "chair") -> EntryRecord:
    return EntryRecord(
        file="entries/x.npz",
        sha256="0" * 64,
        source="test",
        source_sha256="0" * 64,
        units="m",
        num_points=1,
        num_keypoints=1,
        bbox_min=(0.0, 0.0, 0.0),
        bbox_max=(1.0, 1.0, 1.0),
        size=(1.0, 1.0, 1.0),
        category=category,
        descriptor=np.asarray(descriptor, dtype="<f4").tobytes(),
    )


def clustered(count: int, seed: int) -> np.ndarray:
    """Descriptors in clusters, as shapes of a kind are: the hard case for a graph."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(max(count // 20, 1), WIDTH))
    return centres[rng.integers(0, len(centres), count)] + 0.5 * rng.normal(size=(count, WIDTH))


def records_of(descriptors: np.ndarray, categories: list[str] | None = None) -> dict:
    categories = categories or ["chair"] * len(descriptors)
    return {
        f"m{i:05d}": record(d, c)
        for i, (d, c) in enumerate(zip(descriptors, categories, strict=True))
    }


def exact_nearest(records: dict, ids: list[str], queries: np.ndarray, count: int) -> list[set]:
    vectors = unit_rows([records[i].descriptor for i in ids])
    scores = unit_rows([q.astype("<f4").tobytes() for q in queries]) @ vectors.T
    return [set(np.argsort(-row)[:count]) for row in scores]


def test_the_neighbours_are_the_exact_scans(tmp_path: Path) -> None:
    records = records_of(clustered(3000, seed=0))
    ids = sorted(records)
    written = write_index(tmp_path, records)
    assert written.categories == {"chair": 3000}
    index = read_index(tmp_path, ids, records)
    assert index is not None and index.indexed == 3000 and index.unindexed == 0

    rng = np.random.default_rng(1)
    picked = np.array(
        [np.frombuffer(records[ids[i]].descriptor, "<f4") for i in rng.choice(3000, 50)]
    )
    queries = picked + 0.3 * rng.normal(size=picked.shape)
    expected = exact_nearest(records, ids, queries, 64)
    found = [set(index.candidates(unit_rows([q.astype("<f4").tobytes()]), 64)) for q in queries]
    recall = np.mean([len(f & e) / 64 for f, e in zip(found, expected, strict=True)])
    assert recall >= 0.97, recall
    # every heading's neighbours, in one call: the union of each one's
    both = index.candidates(unit_rows([q.astype("<f4").tobytes() for q in queries[:2]]), 64)
    assert set(both) == found[0] | found[1]


def test_entries_changed_since_the_index_are_scored_exactly_and_removed_ones_never_come_back(
    tmp_path: Path,
) -> None:
    records = records_of(clustered(400, seed=2))
    write_index(tmp_path, records)
    ids = sorted(records)
    removed, replaced, added = ids[0], ids[1], "new-entry"
    now = dict(records)
    del now[removed]
    now[replaced] = record(np.ones(WIDTH))  # the same id described again
    now[added] = record(-np.ones(WIDTH))
    now_ids = sorted(now)
    index = read_index(tmp_path, now_ids, now)
    assert index is not None and index.indexed == 398 and index.unindexed == 2

    rows = index.candidates(unit_rows([records[removed].descriptor]), 10)
    assert removed not in {now_ids[r] for r in rows}  # its key points at no entry now
    far = unit_rows([np.full(WIDTH, 0.5, dtype="<f4").tobytes()])
    listed = {now_ids[r] for r in index.candidates(far, 5)}
    assert {replaced, added} <= listed  # unindexed entries are always candidates
    assert 0 < len(listed - {replaced, added}) <= 5  # and the graph's nearest


def test_each_category_has_its_graph(tmp_path: Path) -> None:
    descriptors = clustered(300, seed=3)
    categories = ["chair"] * 200 + ["table"] * 100
    records = records_of(descriptors, categories)
    assert write_index(tmp_path, records).categories == {"chair": 200, "table": 100}
    ids = sorted(records)
    index = read_index(tmp_path, ids, records)
    query = unit_rows([records[ids[250]].descriptor])  # a table's own descriptor
    tables = index.candidates(query, 20, category="table")
    assert {records[ids[r]].category for r in tables} == {"table"} and 250 in tables
    chairs = index.candidates(query, 20, category="chair")
    assert {records[ids[r]].category for r in chairs} == {"chair"}
    assert set(index.candidates(query, 20)) == set(tables) | set(chairs)
    moved = dict(records)
    moved[ids[0]] = dataclasses.replace(records[ids[0]], category="table")  # now a table
    index = read_index(tmp_path, ids, moved)
    assert index.unindexed == 1 and 0 in index.candidates(query, 1, category="table")


def test_writing_again_replaces_the_graphs(tmp_path: Path) -> None:
    records = records_of(clustered(100, seed=4))
    write_index(tmp_path, records)
    first = set((tmp_path / INDEX_DIR).iterdir())
    write_index(tmp_path, records)
    second = set((tmp_path / INDEX_DIR).iterdir())
    assert len(second) == 2 and first != second  # the JSON and one new graph


@pytest.mark.parametrize("damage", ["json", "graph", "format"])
def test_a_damaged_index_is_ignored_with_a_warning(tmp_path: Path, caplog, damage: str) -> None:
    records = records_of(clustered(50, seed=5))
    write_index(tmp_path, records)
    named = tmp_path / INDEX_DIR / INDEX_NAME
    document = json.loads(named.read_text())
    if damage == "json":
        named.write_text("{not json")
    elif damage == "graph":
        (tmp_path / INDEX_DIR / document["categories"]["chair"]["file"]).write_bytes(b"x" * 10)
    else:
        named.write_text(json.dumps({**document, "format": 99}))
    with caplog.at_level(logging.WARNING):
        assert read_index(tmp_path, sorted(records), records) is None
    assert "ignoring the shortlist index" in caplog.text


def test_entries_without_descriptors_are_left_to_the_exact_scan(tmp_path: Path) -> None:
    records = records_of(clustered(20, seed=6))
    records["bare"] = dataclasses.replace(records["m00000"], category="sofa", descriptor=b"")
    assert write_index(tmp_path, records).categories == {"chair": 20}
    index = read_index(tmp_path, sorted(records), records)
    assert (index.indexed, index.unindexed) == (20, 1)


def test_a_library_without_an_index_has_none(tmp_path: Path) -> None:
    assert read_index(tmp_path, [], {}) is None
