"""The SQLite catalogue: every record field round-trips, an add or a remove writes only its own
rows, the stamp changes at every commit and only then, a writer killed at any point of a write
leaves the last committed state readable (readers writing nothing, even past a hot journal), a
library of format 2 is refused until converted, and a damaged catalogue is named in a sentence."""

from __future__ import annotations

import dataclasses
import inspect
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from catalign.errors import (
    InvalidInputError,
    LibraryCorruptError,
    LibraryError,
    ModelNotFoundError,
    ShapeReadError,
)
from catalign.library import add, build, info, load, remove
from catalign.library.index import configure
from catalign.library.legacy import migrate
from catalign.library.records import EntryRecord, Manifest, entry_file_name
from catalign.library.store import commit, commit_changes, manifest_stamp, read_manifest
from tests.library.conftest import (
    as_earlier_layout,
    as_format_2,
    as_format_3,
    stored,
    without_outlines,
    write_format_2,
)


@pytest.fixture
def library(files, tmp_path, extractor) -> Path:
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1), files.cloud("b.npy", 2)], out, extractor, progress=False)
    return out


def everything(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``, hidden ones too, and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def unreferenced(library_dir: Path) -> set[str]:
    referenced = {r.file for r in info(library_dir).entries.values()}
    present = {f"entries/{p.name}" for p in (library_dir / "entries").iterdir()}
    present |= {p.name for p in library_dir.glob(".catalogue.sqlite.*")}
    present |= {p.name for p in library_dir.glob("*-journal")}
    return present - referenced


def _record(model_id: str, seed: int, **fields) -> EntryRecord:
    sha256 = f"{seed:064x}"
    values = dict(
        file=entry_file_name(model_id, sha256),
        sha256=sha256,
        source=f"/cad/{model_id}.ply",
        source_sha256=f"{seed + 1:064x}",
        units="m",
        num_points=10_000,
        num_keypoints=2_000 + seed,
        bbox_min=(-0.3, -0.5, -0.25),
        bbox_max=(0.3, 0.5, 0.25),
        size=(0.6, 1.0, 0.5),
    )
    return EntryRecord(**(values | fields))


def test_every_field_of_the_library_and_its_records_round_trips(tmp_path) -> None:
    entries = {
        "plain": _record("plain", 1),
        "odd": _record(
            "odd",
            2,
            source="upload:Stühle (2) ✓.ply",
            units="mm",
            num_points=2**40,
            bbox_min=(0.1 + 0.2, -1e-300, 7.0),
            bbox_max=(1 / 3, 2.0**-1074, 1e300),
            size=(np.nextafter(1.0, 2.0), 0.0, 12345.678901234567),
            category="bin_2",
            symmetry=0,
        ),
        "unknown-symmetry": _record("unknown-symmetry", 3, category="table", symmetry=None),
        "half-turn": _record("half-turn", 4, symmetry=2),
    }
    manifest = Manifest(
        fingerprint="f" * 64,
        voxel_size=0.025,
        created="2026-01-02T03:04:05+00:00",
        updated="2026-06-07T08:09:10+00:00",
        entries=entries,
        engine={"top_k": 5, "icp": {"poses": 2, "iterations": 20}, "note": "ü"},
        category="table",
    )
    out = tmp_path / "lib"
    commit(out, manifest)
    assert read_manifest(out) == manifest  # every field, exactly (floats bit for bit)
    assert read_manifest(out, ids=["odd", "missing"]).entries == {"odd": entries["odd"]}
    assert read_manifest(out, ids=()).entries == {} and read_manifest(out, ids=()).engine
    changed = {**entries, "plain": dataclasses.replace(entries["plain"], symmetry=4)}
    del changed["half-turn"]
    again = dataclasses.replace(manifest, entries=changed, updated="2027-01-01T00:00:00+00:00")
    commit(out, again)
    assert read_manifest(out) == again


def _log_writes(library_dir: Path) -> None:
    """Triggers that note every row written to the entries table, and which."""
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection:
        connection.executescript(
            """
            CREATE TABLE written (operation TEXT, model_id TEXT);
            CREATE TRIGGER on_insert AFTER INSERT ON entries
                BEGIN INSERT INTO written VALUES ('insert', NEW.model_id); END;
            CREATE TRIGGER on_update AFTER UPDATE ON entries
                BEGIN INSERT INTO written VALUES ('update', NEW.model_id); END;
            CREATE TRIGGER on_delete AFTER DELETE ON entries
                BEGIN INSERT INTO written VALUES ('delete', OLD.model_id); END;
            """
        )


def _written(library_dir: Path) -> list[tuple[str, str]]:
    rows = stored(library_dir, "SELECT operation, model_id FROM written ORDER BY rowid")
    with closing(sqlite3.connect(library_dir / "catalogue.sqlite")) as connection, connection:
        connection.execute("DELETE FROM written")
    return rows


def test_an_add_or_a_remove_writes_only_its_own_rows(files, tmp_path, extractor) -> None:
    out = tmp_path / "lib"
    sources = [files.cloud(f"m{i}.npy", i) for i in range(12)]
    build(sources, out, extractor, progress=False)
    _log_writes(out)
    add(out, [files.cloud("new.npy", 40)], extractor, progress=False)
    assert _written(out) == [("insert", "new")]
    add(out, [files.cloud("v2/m3.npy", 41)], extractor, replace=True, progress=False)
    assert _written(out) == [("insert", "m3")]  # INSERT OR REPLACE: the one row
    assert remove(out, ["m7", "m9"]) == 11
    assert sorted(_written(out)) == [("delete", "m7"), ("delete", "m9")]
    configure(out, {"top_k": 3})
    assert _written(out) == []
    # a build over the library writes only the rows that differ from the new state: m3 back
    # to its first source, m5 from a new one, the others gone; m0, m1, m2 and m4 untouched
    rebuilt = [*sources[:5], files.cloud("v3/m5.npy", 42)]
    build(rebuilt, out, extractor, overwrite=True, progress=False)
    assert sorted(_written(out)) == sorted(
        [("delete", i) for i in ("m6", "m8", "m10", "m11", "new")]
        + [("insert", "m3"), ("insert", "m5")]
    )
    assert load(out, extractor.fingerprint).ids == [f"m{i}" for i in range(6)]


def test_the_stamp_changes_at_every_commit_and_only_then(library, files, extractor) -> None:
    stamps = [manifest_stamp(library)]
    load(library, extractor.fingerprint)
    info(library)
    with pytest.raises(InvalidInputError, match="already in the library"):
        add(library, [files.cloud("x/a.npy", 5)], extractor, progress=False)
    with pytest.raises(ModelNotFoundError, match="no model 'ghost'"):
        remove(library, ["ghost"])
    (files.root / "broken.npy").write_bytes(b"not a numpy file")
    with pytest.raises(ShapeReadError):
        add(library, [files.root / "broken.npy"], extractor, progress=False)
    assert manifest_stamp(library) == stamps[0]  # reads and refused writes commit nothing

    size = (library / "catalogue.sqlite").stat().st_size
    for _ in range(2):  # the same options twice: a write in place of the very same size
        configure(library, {"top_k": 4})
        stamps.append(manifest_stamp(library))
    assert (library / "catalogue.sqlite").stat().st_size == size
    add(library, [files.cloud("c.npy", 3)], extractor, progress=False)
    stamps.append(manifest_stamp(library))
    remove(library, ["c"])
    stamps.append(manifest_stamp(library))
    build([files.root / "a.npy"], library, extractor, overwrite=True, progress=False)
    stamps.append(manifest_stamp(library))
    shutil.rmtree(library)  # a new library in the same folder: a new catalogue id
    build([files.root / "a.npy"], library, extractor, progress=False)
    stamps.append(manifest_stamp(library))
    assert len(set(stamps)) == len(stamps) == 7
    assert manifest_stamp(library.parent / "nowhere") is None


_KILLED_WRITER = """
import os
import signal
import sys
from collections import namedtuple
from contextlib import contextmanager
from pathlib import Path

import numpy as np

import catalign.library.catalogue as catalogue
import catalign.library.store as store
from catalign.geometry.sampling import voxel_downsample
from catalign.library import add

Described = namedtuple("Described", "keypoints features")  # torch-free stand-in


{extractor}


def die(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)


library, point = sys.argv[1], sys.argv[2]
if point == "entry files written":  # written and fsynced, no transaction begun
    catalogue.update = die
elif point == "mid-transaction":  # rows written, the database partly overwritten, no COMMIT
    real_writing = catalogue.writing

    @contextmanager
    def writing(library_dir):
        with real_writing(library_dir) as connection:
            yield connection
            connection.execute("PRAGMA cache_size = 1")  # spill pages into the database file
            connection.execute(
                "CREATE TABLE filler AS WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL "
                "SELECT i + 1 FROM n WHERE i < 2000) SELECT zeroblob(4000) AS b FROM n"
            )
            die()

    catalogue.writing = writing
elif point == "committed":  # the replaced file not yet deleted
    store._tidy = die
add(library, sys.argv[3:], FakeExtractor(), replace=True, progress=False)
"""


@pytest.mark.parametrize("point", ["entry files written", "mid-transaction", "committed"])
def test_a_writer_killed_at_any_point_of_a_write_leaves_a_committed_state(
    library, files, extractor, point, monkeypatch, tmp_path
) -> None:
    before, stamp = load(library, extractor.fingerprint), manifest_stamp(library)
    database = (library / "catalogue.sqlite").read_bytes()
    sources = [files.cloud("v2/a.npy", 7), files.cloud("c.npy", 3)]  # a replaced, c new
    script = _KILLED_WRITER.format(extractor=textwrap.dedent(inspect.getsource(type(extractor))))
    writer = subprocess.run(
        [sys.executable, "-c", script, str(library), point, *map(str, sources)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert writer.returncode == -signal.SIGKILL, writer.stderr

    journal = library / "catalogue.sqlite-journal"
    if point == "mid-transaction":  # the hard case: a hot journal, a torn database
        assert journal.is_file() and (library / "catalogue.sqlite").read_bytes() != database
        with monkeypatch.context() as patched:  # the private copy needs a temporary folder
            patched.setattr(tempfile, "tempdir", str(tmp_path / "no-such-folder"))
            with pytest.raises(LibraryError, match="writable temporary folder"):
                load(library, extractor.fingerprint)
    on_disk = everything(library)
    after = load(library, extractor.fingerprint)
    if point == "committed":
        assert after.ids == ["a", "b", "c"] and manifest_stamp(library) != stamp
        assert not np.array_equal(after["a"].points, before["a"].points)
    else:
        assert after.ids == ["a", "b"] and manifest_stamp(library) == stamp
        for model_id in before.ids:
            np.testing.assert_array_equal(after[model_id].features, before[model_id].features)
    assert manifest_stamp(library) == manifest_stamp(library)  # steady while nothing commits
    assert everything(library) == on_disk  # readers wrote nothing, not even past the journal
    assert len(unreferenced(library) - {journal.name}) >= 1  # what the kill left

    assert remove(library, ["b"]) == len(after.ids) - 1  # the next writer rolls back and tidies
    assert not journal.exists() and unreferenced(library) == set()
    assert stored(library, "SELECT name FROM sqlite_master WHERE name = 'filler'") == []
    assert load(library, extractor.fingerprint).ids == [i for i in after.ids if i != "b"]


def test_a_library_of_format_2_is_refused_until_converted(library, files, extractor) -> None:
    entries = {p.name: p.read_bytes() for p in (library / "entries").iterdir()}
    records = info(library).entries
    as_format_2(library)
    on_disk = everything(library)
    attempts = [
        lambda: load(library, extractor.fingerprint),
        lambda: info(library),
        lambda: add(library, [files.cloud("c.npy", 3)], extractor, progress=False),
        lambda: remove(library, ["a"]),
        lambda: configure(library, {"top_k": 2}),
        lambda: build([files.root / "c.npy"], library, extractor, progress=False),
    ]
    for attempt in attempts:
        with pytest.raises(LibraryError, match=r"older format|already holds a library") as e:
            attempt()
        assert "catalign library migrate" in str(e.value) or "--overwrite" in str(e.value)
    assert everything(library) == on_disk  # refused without a change

    assert migrate(library).entries == records
    assert not (library / "manifest.json").exists()
    assert {p.name: p.read_bytes() for p in (library / "entries").iterdir()} == entries
    assert migrate(library).entries == records  # again: nothing left to do
    assert load(library, extractor.fingerprint).ids == ["a", "b"]


def test_a_library_of_format_3_is_converted_to_small_entries(library, extractor) -> None:
    records, entries = info(library).entries, everything(library / "entries")
    as_format_3(library)  # full entries, no descriptors in the catalogue
    full = sum(len(data) for data in everything(library / "entries").values())
    with pytest.raises(LibraryError, match=r"format 3.*catalign library migrate"):
        load(library, extractor.fingerprint)
    assert migrate(library).entries == records  # the same records, descriptors included
    assert everything(library / "entries") == entries  # the same bytes as a fresh build
    assert sum(len(data) for data in entries.values()) < full * 0.7
    assert load(library, extractor.fingerprint).ids == ["a", "b"]


def test_entries_of_the_earlier_layout_are_served_then_rewritten(library, extractor) -> None:
    records, entries = info(library).entries, everything(library / "entries")
    fresh = load(library, extractor.fingerprint)["a"]
    as_earlier_layout(library)
    larger = sum(len(data) for data in everything(library / "entries").values())
    served = load(library, extractor.fingerprint)["a"]  # read as it is, no migration asked
    sixteen_bits = (fresh.bbox_max - fresh.bbox_min) / 65_535  # the earlier layout's steps
    gaps = np.abs(np.sort(served.points, axis=0) - np.sort(fresh.points, axis=0))
    assert (gaps < sixteen_bits).all()
    stamp = manifest_stamp(library)
    assert migrate(library).entries == records  # the same records, descriptors included
    assert everything(library / "entries") == entries  # the same bytes as a fresh build
    assert sum(len(data) for data in entries.values()) < larger
    rewritten = manifest_stamp(library)
    assert rewritten != stamp  # serving processes load the rewritten files
    assert migrate(library).entries == records  # again: nothing left to do, nothing committed
    assert manifest_stamp(library) == rewritten


def test_a_catalogue_written_before_outlines_is_served_then_given_them(
    library, extractor, files
) -> None:
    records = info(library).entries
    without_outlines(library)
    served = load(library, extractor.fingerprint)
    assert not any(served.record(i).outline for i in served.ids)
    made = served.outlines(range(len(served)))  # made from the entries' points meanwhile
    assert [o.to_bytes() for o in made] == [records[i].outline for i in served.ids]
    add(library, [files.cloud("c.npy", 3)], extractor)  # a write gives the catalogue the column
    after = info(library).entries
    assert after["c"].outline and not after["a"].outline
    stamp = manifest_stamp(library)
    assert {i: r for i, r in migrate(library).entries.items() if i != "c"} == records
    assert manifest_stamp(library) != stamp  # serving processes load the outlines
    assert stored(library, "SELECT count(*) FROM entries WHERE length(outline) > 0") == [(3,)]


def test_a_process_that_registers_nothing_may_leave_the_outlines_unread(library, extractor) -> None:
    records = info(library).entries
    listed = load(library, extractor.fingerprint, outlines=False)
    assert not any(listed.record(i).outline for i in listed.ids)
    assert listed.ids == sorted(records) and all(records[i].outline for i in listed.ids)
    made = [o.to_bytes() for o in listed.outlines(range(len(listed)))]  # from the entries
    assert made == [records[i].outline for i in listed.ids]


def test_a_damaged_outline_is_named_when_it_is_read(library, extractor) -> None:
    with closing(sqlite3.connect(library / "catalogue.sqlite")) as connection, connection:
        connection.execute("UPDATE entries SET outline = x'00ff' WHERE model_id = 'b'")
    served = load(library, extractor.fingerprint)
    assert served.outlines([0])[0].levels.size > 0  # the sound one
    with pytest.raises(LibraryCorruptError, match=r"entry 'b' .* malformed outline"):
        served.outlines([1])


def test_a_conversion_killed_before_or_after_its_rename_is_whole(library, extractor) -> None:
    records = info(library).entries
    catalogue = (library / "catalogue.sqlite").read_bytes()
    raw = as_format_2(library)
    (library / ".catalogue.sqlite.999.tmp").write_bytes(catalogue[: len(catalogue) // 2])
    with pytest.raises(LibraryError, match="older format"):  # before: still format 2
        load(library, extractor.fingerprint)
    assert migrate(library).entries == records
    assert not list(library.glob(".catalogue.sqlite.*"))  # the killed one's leftover swept
    write_format_2(library, raw)  # after: both files, the catalogue wins
    assert load(library, extractor.fingerprint).ids == ["a", "b"]
    migrate(library)
    assert not (library / "manifest.json").exists()


def test_what_cannot_be_converted_is_refused_in_a_sentence(library, extractor) -> None:
    raw = as_format_2(library)
    write_format_2(library, {**raw, "format_version": 1})
    with pytest.raises(LibraryCorruptError, match=r"version 1, which cannot be converted.*build"):
        migrate(library)
    (library / info_file(raw, "a")).unlink()
    write_format_2(library, raw)
    with pytest.raises(LibraryCorruptError, match=r"entry 'a'.*is missing.*cannot be converted"):
        migrate(library)
    assert (library / "manifest.json").is_file() and not (library / "catalogue.sqlite").exists()
    with pytest.raises(LibraryError, match="no library"):
        migrate(library.parent / "nowhere")


def info_file(raw: dict, model_id: str) -> str:
    return raw["entries"][model_id]["file"]


def test_a_build_over_a_library_of_format_2_replaces_it(library, files, extractor) -> None:
    as_format_2(library)
    build([files.cloud("c.npy", 3)], library, extractor, overwrite=True, progress=False)
    assert not (library / "manifest.json").exists()
    assert load(library, extractor.fingerprint).ids == ["c"]
    assert unreferenced(library) == set()


@pytest.mark.parametrize(
    ("damage", "problem"),
    [
        (lambda data: b"\x00\xffnot a database at all" * 100, "not a readable catalign catalogue"),
        (lambda data: data[: len(data) // 2], "not a readable catalign catalogue"),
        (lambda data: b"", "not a catalign catalogue"),
        (lambda data: b'{"format_version": 2}', "not a readable catalign catalogue"),
    ],
    ids=["garbage", "truncated", "empty", "json"],
)
def test_a_damaged_catalogue_is_named_with_the_command_that_rebuilds_it(
    library, extractor, damage, problem
) -> None:
    path = library / "catalogue.sqlite"
    path.write_bytes(damage(path.read_bytes()))
    rebuild = f"rebuild it with `catalign library build SRC... --out {library} --overwrite`"
    expected = rf"^{re.escape(str(path))} (is|has) .*{problem}.*; {re.escape(rebuild)}$"
    with pytest.raises(LibraryCorruptError, match=expected):
        load(library, extractor.fingerprint)
    with pytest.raises(LibraryCorruptError, match=expected):
        info(library)
    manifest_stamp(library)  # a server polling it is not stopped by the damage


def test_another_applications_database_is_not_a_catalogue(library, extractor) -> None:
    path = library / "catalogue.sqlite"
    path.unlink()
    with closing(sqlite3.connect(path)) as connection, connection:
        connection.execute("CREATE TABLE library (format_version INTEGER)")
        connection.execute("INSERT INTO library VALUES (3)")
    with pytest.raises(LibraryCorruptError, match=r"catalogue.sqlite is an SQLite database but"):
        load(library, extractor.fingerprint)


def test_a_change_of_a_few_entries_keeps_every_other_record(library, files, extractor) -> None:
    """The store's own change: put and drop by id, the library row's fields by name."""
    before = info(library)
    record = dataclasses.replace(before.entries["a"], source="renamed")
    commit_changes(library, put={"a": record}, updated="2030-01-01T00:00:00+00:00")
    after = info(library)
    assert after.entries == {**before.entries, "a": record}
    assert after.updated == "2030-01-01T00:00:00+00:00" and after.created == before.created
    with pytest.raises(ValueError, match="no library column"):
        commit_changes(library, entries={})
    assert os.listdir(library / "entries")  # nothing deleted: the file is the same
