from __future__ import annotations

import hashlib
import inspect
import io
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import catalign.library.catalogue as catalogue
import catalign.library.index as index
import catalign.library.loaded as loaded
import catalign.library.store as store
from catalign.errors import (
    LibraryChangedError,
    LibraryCorruptError,
    LibraryError,
    LibraryMismatchError,
)
from catalign.library import add, build, info, load, remove
from catalign.library.entry import describe_file
from catalign.library.npz import npz_arrays
from catalign.library.quantise import GRID_STEPS
from catalign.library.sources import SourceFile
from tests.library.conftest import earlier_layout_bytes


class Crash(BaseException):
    """Stands for the process dying: no ``except Exception`` clean-up runs."""


@pytest.fixture
def small_library(files, tmp_path, extractor):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1), files.cloud("b.npy", 2)], out, extractor, progress=False)
    return out


def unreferenced(library_dir) -> set[str]:
    referenced = {r.file for r in info(library_dir).entries.values()}
    leftovers = {f"entries/{p.name}" for p in (library_dir / "entries").iterdir()}
    leftovers |= {p.name for p in library_dir.glob(".catalogue.sqlite.*")}
    leftovers |= {p.name for p in library_dir.glob("*-journal")}
    return leftovers - referenced


def test_entry_files_are_byte_reproducible_and_read_back_equal(files, extractor):
    entry = describe_file(SourceFile("a", files.cloud("a.npy", 1)), extractor)
    assert store.entry_bytes(entry) == store.entry_bytes(entry)
    with np.load(io.BytesIO(store.entry_bytes(entry)), allow_pickle=False) as npz:
        assert str(npz["model_id"]) == "a"
        assert npz["surface_steps"].dtype == np.uint16 and npz["surface_steps"].shape[0] == 3
        assert npz["keypoint_steps"].dtype == np.uint16 and npz["feature_steps"].dtype == np.int8
        assert npz["grid_steps"].max() <= GRID_STEPS
    back = store.entry_from_arrays(npz_arrays(store.entry_bytes(entry)))
    for name in ("points", "keypoints", "features", "descriptor", "bbox_min", "size"):
        np.testing.assert_array_equal(getattr(back, name), getattr(entry, name), err_msg=name)
    np.testing.assert_array_equal(back.grid.values, entry.grid.values)


def test_an_entry_file_of_the_earlier_layout_reads_as_it_was_written(files, extractor):
    """Entries written before the surface, key points and grid were narrowed further (rows of
    point steps, float32 key points, 255 grid levels, deflated) are served without a rewrite."""
    entry = describe_file(SourceFile("a", files.cloud("a.npy", 1)), extractor)
    back = store.entry_from_arrays(npz_arrays(earlier_layout_bytes(entry)))
    sixteen_bits = (entry.bbox_max - entry.bbox_min) / 65_535  # the earlier layout's steps
    assert (
        np.abs(np.sort(back.points, axis=0) - np.sort(entry.points, axis=0)) < sixteen_bits
    ).all()
    for name in ("features", "descriptor"):
        np.testing.assert_array_equal(getattr(back, name), getattr(entry, name), err_msg=name)
    np.testing.assert_allclose(back.keypoints, entry.keypoints, atol=1e-6)
    np.testing.assert_array_equal(back.grid.values, entry.grid.values)


def test_an_entry_is_read_when_first_asked_for_and_then_kept(small_library, extractor):
    library = load(small_library, extractor.fingerprint)
    entry = library["a"]
    for array in (entry.points, entry.keypoints, entry.features, entry.grid.values):
        assert not array.flags.writeable
    (small_library / info(small_library).entries["a"].file).unlink()
    assert library["a"] is entry  # kept: no second read
    with pytest.raises(LibraryCorruptError, match=r"entry 'b'.*fails its checksum"):
        path = small_library / info(small_library).entries["b"].file
        path.write_bytes(path.read_bytes()[::-1])
        library["b"]


def test_an_entry_a_writer_removed_after_the_load_is_a_change_to_retry(small_library, extractor):
    library = load(small_library, extractor.fingerprint)
    remove(small_library, ["b"])
    with pytest.raises(LibraryChangedError, match=r"entry 'b' was replaced or removed.*retry"):
        library["b"]
    assert load(small_library, extractor.fingerprint).ids == ["a"]


def test_crash_before_the_catalogue_commits_keeps_the_old_library(
    small_library, files, extractor, snapshot, monkeypatch
):
    before = snapshot(small_library)

    def crash(*args, **kwargs):  # entry files are written; the catalogue never is
        raise Crash

    monkeypatch.setattr(catalogue, "update", crash)
    with pytest.raises(Crash):
        add(small_library, [files.cloud("c.npy", 3)], extractor, progress=False)
    with pytest.raises(Crash):
        add(small_library, [files.cloud("v2/a.npy", 4)], extractor, replace=True, progress=False)
    monkeypatch.undo()

    lib = load(small_library, extractor.fingerprint)
    assert lib.ids == ["a", "b"]
    orphans = unreferenced(small_library)
    assert len(orphans) == 2 and all(o.startswith("entries/") for o in orphans)
    assert {k: v for k, v in snapshot(small_library).items() if k not in orphans} == before

    add(small_library, [files.cloud("d.npy", 5)], extractor, progress=False)
    assert unreferenced(small_library) == set()
    assert load(small_library, extractor.fingerprint).ids == ["a", "b", "d"]


def test_a_failed_write_cleans_up_at_once(small_library, files, extractor, snapshot, monkeypatch):
    before = snapshot(small_library)

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(catalogue, "update", fail)
    with pytest.raises(OSError, match="disk full"):
        add(small_library, [files.cloud("c.npy", 3)], extractor, progress=False)
    assert snapshot(small_library) == before


def test_leftover_temporary_files_are_ignored_and_cleaned(small_library, files, extractor):
    """What a killed writer leaves is swept by the next writer, which finds its mark; a write
    after one that finished does not list the entries folder (10^5 files at scale)."""
    (small_library / "entries" / ".a-000000000000.npz.123.tmp").write_bytes(b"half")
    (small_library / ".catalogue.sqlite.123.tmp").write_bytes(b"half")
    assert load(small_library, extractor.fingerprint).ids == ["a", "b"]
    remove(small_library, ["b"])
    assert len(unreferenced(small_library)) == 2  # no mark: nobody died mid-write
    (small_library / ".writing").write_bytes(b"")  # the mark a killed writer leaves
    add(small_library, [files.root / "b.npy"], extractor, progress=False)
    assert unreferenced(small_library) == set()
    assert not (small_library / ".writing").exists()


_WRITER = """
import sys
from pathlib import Path

from collections import namedtuple

import numpy as np

from catalign.geometry.sampling import voxel_downsample
from catalign.library import add

Described = namedtuple("Described", "keypoints features")  # torch-free stand-in


{extractor}

library, sources = sys.argv[1], sorted(Path(sys.argv[2]).glob("*.npy"))
for number, source in enumerate(sources):
    add(library, [source], FakeExtractor(), progress=False)
    print(number, flush=True)
"""


@pytest.mark.parametrize("delay", [0.0, 0.05, 0.15])
def test_a_writer_killed_mid_write_leaves_a_consistent_library(
    small_library, files, tmp_path, extractor, delay
):
    many = tmp_path / "many"
    many.mkdir()
    for i in range(120):
        np.save(many / f"m{i:03d}.npy", files.random_cloud(100 + i, count=3000))
    before = load(small_library, extractor.fingerprint)
    script = _WRITER.format(extractor=textwrap.dedent(inspect.getsource(type(extractor))))
    writer = subprocess.Popen(
        [sys.executable, "-c", script, str(small_library), str(many)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = writer.stdout.readline()  # one add done: the writer is in its loop
        assert first.strip() == "0", writer.stderr.read()
        time.sleep(delay)
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait()
    assert writer.returncode == -signal.SIGKILL

    after = load(small_library, extractor.fingerprint)
    added = after.ids[2:]
    assert after.ids[:2] == ["a", "b"] and 1 <= len(added) < 120
    assert added == [f"m{i:03d}" for i in range(len(added))]  # a prefix: old or new, never torn
    for model_id in before.ids:
        np.testing.assert_array_equal(after[model_id].features, before[model_id].features)

    remove(small_library, [added[-1]])  # the next write tidies whatever the kill left
    assert unreferenced(small_library) == set()


def test_flipped_bytes_name_the_entry(small_library, extractor):
    record = info(small_library).entries["b"]
    path = small_library / record.file
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    library = load(small_library, extractor.fingerprint)  # files are checked when read
    with pytest.raises(LibraryCorruptError, match=r"entry 'b'.*fails its checksum"):
        library.verify()


def test_a_missing_entry_file_is_named(small_library, extractor):
    (small_library / info(small_library).entries["a"].file).unlink()
    with pytest.raises(LibraryCorruptError, match=r"entry 'a'.*is missing"):
        load(small_library, extractor.fingerprint)


def _write_while_reading(monkeypatch, before_read, after_read=lambda: None):
    """Make a writer run ``before_read`` just before a reader lists the entry files (the
    reader holds the catalogue it read first) and ``after_read`` right after that listing."""
    real_names = loaded._entry_names

    def racing_names(folder):
        if racing_names.done:
            return real_names(folder)
        racing_names.done = True
        before_read()
        try:
            return real_names(folder)
        finally:
            after_read()

    racing_names.done = False
    monkeypatch.setattr(loaded, "_entry_names", racing_names)


def test_a_reader_loads_the_new_manifest_when_a_writer_deleted_an_entry_under_it(
    small_library, extractor, monkeypatch
):
    _write_while_reading(monkeypatch, lambda: remove(small_library, ["b"]))
    assert load(small_library, extractor.fingerprint).ids == ["a"]


def test_an_entry_removed_and_added_back_within_a_second_is_not_corruption(
    small_library, files, extractor, monkeypatch
):
    manifest, stamp = info(small_library), store.manifest_stamp(small_library)
    monkeypatch.setattr(index, "utc_now", lambda: info(small_library).updated)  # same second
    _write_while_reading(
        monkeypatch,
        lambda: remove(small_library, ["b"]),
        lambda: add(small_library, [files.root / "b.npy"], extractor, progress=False),
    )
    assert load(small_library, extractor.fingerprint).ids == ["a", "b"]
    assert info(small_library) == manifest  # the very same records and dates
    assert store.manifest_stamp(small_library) != stamp  # two writes later


def test_missing_catalogue(tmp_path, extractor):
    with pytest.raises(LibraryError, match=r"no library at .*catalign library build"):
        load(tmp_path / "nowhere", extractor.fingerprint)
    with pytest.raises(LibraryError, match=r"holds no catalogue.sqlite"):
        load(tmp_path, extractor.fingerprint)


def _edit_catalogue(library_dir, statement: str, *parameters) -> None:
    """Change the catalogue by hand, as a user with the sqlite3 shell could."""
    connection = sqlite3.connect(library_dir / "catalogue.sqlite")
    with connection:
        connection.execute(statement, parameters)
    connection.close()


@pytest.mark.parametrize("version", [99, 1])
def test_unknown_format_version(small_library, extractor, version):
    """Any other version is refused, with the command that rebuilds it."""
    _edit_catalogue(small_library, "UPDATE library SET format_version = ?", version)
    expected = rf"format version {version}.*reads version 4.*library build .* --overwrite"
    with pytest.raises(LibraryCorruptError, match=expected):
        load(small_library, extractor.fingerprint)


@pytest.mark.parametrize("version", [2, 3])
def test_a_format_that_converts_is_refused_with_the_command(small_library, extractor, version):
    _edit_catalogue(small_library, "UPDATE library SET format_version = ?", version)
    with pytest.raises(LibraryError, match=rf"format {version}.*catalign library migrate"):
        load(small_library, extractor.fingerprint)


def test_an_entry_round_trips_with_its_distance_grid(small_library, files, extractor):
    fresh = describe_file(SourceFile("a", files.cloud("a.npy", 1)), extractor)
    loaded = load(small_library, extractor.fingerprint)["a"].grid
    assert loaded.values.dtype == np.uint8 and not loaded.values.flags.writeable
    np.testing.assert_array_equal(loaded.values, fresh.grid.values)
    np.testing.assert_array_equal(loaded.origin, fresh.grid.origin)
    assert (loaded.cell, loaded.step) == (fresh.grid.cell, fresh.grid.step)
    # half a voxel a cell, three voxels of truncation
    assert loaded.cell == extractor.voxel_size / 2
    assert loaded.truncation == pytest.approx(3 * extractor.voxel_size)
    # the grid reaches the truncation past the bounding box on every side
    assert np.all(loaded.origin <= fresh.bbox_min - loaded.truncation + 1e-12)
    far_corner = loaded.origin + loaded.cell * (np.array(loaded.values.shape) - 1)
    assert np.all(far_corner >= fresh.bbox_max + loaded.truncation - 1e-12)


def test_an_entry_without_a_grid_is_corrupt(small_library, extractor):
    record = info(small_library).entries["a"]
    path = small_library / record.file
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files if name not in ("grid", "grid_steps")}
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _replace_entry(small_library, "a", buffer.getvalue())
    with pytest.raises(LibraryCorruptError, match=r"'a'.*malformed.*grid"):
        load(small_library, extractor.fingerprint)["a"]


def _replace_entry(library_dir, model_id: str, data: bytes) -> None:
    """Write ``data`` over an entry's file and make the catalogue's checksum match it."""
    record = info(library_dir).entries[model_id]
    (library_dir / record.file).write_bytes(data)
    sha256 = hashlib.sha256(data).hexdigest()
    new_file = store.entry_file_name(model_id, sha256)
    (library_dir / record.file).rename(library_dir / new_file)
    _edit_catalogue(
        library_dir,
        "UPDATE entries SET sha256 = ?, file = ? WHERE model_id = ?",
        sha256,
        new_file,
        model_id,
    )


@pytest.mark.parametrize(
    ("statement", "problem"),
    [
        ("UPDATE entries SET file = '../../etc/passwd' WHERE model_id = 'a'", "does not match"),
        ("UPDATE entries SET sha256 = 'cafe' WHERE model_id = 'a'", "not a hex sha256"),
        ("UPDATE entries SET num_points = 'many' WHERE model_id = 'a'", "num_points is str"),
        ("UPDATE entries SET size_y = NULL WHERE model_id = 'a'", "NOT NULL"),
        ("UPDATE entries SET category = 'Chairs!' WHERE model_id = 'a'", "not a valid category"),
        ("UPDATE entries SET symmetry = -2 WHERE model_id = 'a'", "not an order"),
        ("UPDATE library SET fingerprint = x'07'", "unexpected bytes"),
        ("UPDATE library SET engine = '[1, 2]'", "unexpected list"),
        ("DROP TABLE entries", "no such table"),
        ("UPDATE entries SET descriptor = 'x' WHERE model_id = 'a'", "descriptor is str"),
        ("UPDATE entries SET descriptor = x'00' WHERE model_id = 'a'", "not float32 bytes"),
        ("UPDATE entries SET descriptor = x'' WHERE model_id = 'a'", "different lengths"),
        ("UPDATE entries SET num_points = 7 WHERE model_id = 'a'", "point counts"),
        ("UPDATE entries SET descriptor = zeroblob(16) WHERE model_id = 'b'", "descriptor"),
    ],
)
def test_tampered_catalogue(small_library, extractor, statement, problem):
    try:
        _edit_catalogue(small_library, statement)
    except sqlite3.IntegrityError as refused:  # SQLite itself keeps some rules
        assert problem in str(refused)
        return
    with pytest.raises(LibraryCorruptError, match=problem):
        load(small_library, extractor.fingerprint).verify()  # the files are checked when read


def test_other_extractor_weights(small_library, files, extractor):
    with pytest.raises(LibraryMismatchError, match=r"'fake-v1'.*'other'.*catalign library build"):
        load(small_library, "other")
    assert len(load(small_library, None)) == 2  # inspection without an extractor

    class Other(type(extractor)):
        fingerprint = "other"

    with pytest.raises(LibraryMismatchError):
        add(small_library, [files.cloud("c.npy", 3)], Other(), progress=False)
