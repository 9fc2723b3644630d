from __future__ import annotations

import hashlib
import inspect
import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import catalign.library.index as index
import catalign.library.loaded as loaded
import catalign.library.store as store
from catalign.errors import LibraryCorruptError, LibraryError, LibraryMismatchError
from catalign.library import add, build, info, load, remove
from catalign.library.entry import describe_file
from catalign.library.sources import SourceFile


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
    leftovers |= {p.name for p in library_dir.glob(".manifest.json.*")}
    return leftovers - referenced


def test_entry_files_are_byte_reproducible(files, extractor):
    entry = describe_file(SourceFile("a", files.cloud("a.npy", 1)), extractor)
    assert store.entry_bytes(entry) == store.entry_bytes(entry)
    with np.load(io.BytesIO(store.entry_bytes(entry)), allow_pickle=False) as npz:
        assert str(npz["model_id"]) == "a"
        np.testing.assert_array_equal(npz["features"], entry.features)


def test_loaded_entries_view_their_files_so_processes_share_them(small_library, extractor):
    library = load(small_library, extractor.fingerprint)
    for entry in library:
        for array in (entry.points, entry.keypoints, entry.features, entry.grid.values):
            assert not array.flags.owndata  # a view of the file's map: no private copy
            assert not array.flags.writeable
    # the map outlives a newer library deleting the file (entries are never changed in place)
    entry = library["a"]
    expected = entry.features.copy()
    for path in (small_library / "entries").iterdir():
        path.unlink()
    np.testing.assert_array_equal(entry.features, expected)


def test_crash_before_the_manifest_keeps_the_old_library(
    small_library, files, extractor, snapshot, monkeypatch
):
    before = snapshot(small_library)

    real_write = store.atomic_write_bytes

    def crash(path, data, **kwargs):
        if path.name != "manifest.json":  # entry files are written; the manifest never is
            return real_write(path, data, **kwargs)
        raise Crash

    monkeypatch.setattr(store, "atomic_write_bytes", crash)
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

    real_write = store.atomic_write_bytes

    def fail(path, data, **kwargs):
        if path.name != "manifest.json":
            return real_write(path, data, **kwargs)
        raise OSError("disk full")

    monkeypatch.setattr(store, "atomic_write_bytes", fail)
    with pytest.raises(OSError, match="disk full"):
        add(small_library, [files.cloud("c.npy", 3)], extractor, progress=False)
    assert snapshot(small_library) == before


def test_leftover_temporary_files_are_ignored_and_cleaned(small_library, files, extractor):
    (small_library / "entries" / ".a-000000000000.npz.123.tmp").write_bytes(b"half")
    (small_library / ".manifest.json.123.tmp").write_bytes(b"{")
    assert load(small_library, extractor.fingerprint).ids == ["a", "b"]
    remove(small_library, ["b"])
    assert unreferenced(small_library) == set()


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
    with pytest.raises(LibraryCorruptError, match=r"entry 'b'.*fails its checksum"):
        load(small_library, extractor.fingerprint)


def test_a_missing_entry_file_is_named(small_library, extractor):
    (small_library / info(small_library).entries["a"].file).unlink()
    with pytest.raises(LibraryCorruptError, match=r"entry 'a'.*is missing"):
        load(small_library, extractor.fingerprint)


def _write_while_reading(monkeypatch, model_id, before_read, after_read=lambda: None):
    """Make a writer run ``before_read`` just before a reader reads ``model_id``'s file (the
    reader holds the manifest it read first) and ``after_read`` right after that read."""
    real_read = loaded.read_entry

    def racing_read(library_dir, wanted, record):
        if wanted != model_id or racing_read.done:
            return real_read(library_dir, wanted, record)
        racing_read.done = True
        before_read()
        try:
            return real_read(library_dir, wanted, record)
        finally:
            after_read()

    racing_read.done = False
    monkeypatch.setattr(loaded, "read_entry", racing_read)


def test_a_reader_loads_the_new_manifest_when_a_writer_deleted_an_entry_under_it(
    small_library, extractor, monkeypatch
):
    _write_while_reading(monkeypatch, "b", lambda: remove(small_library, ["b"]))
    assert load(small_library, extractor.fingerprint).ids == ["a"]


def test_an_entry_removed_and_added_back_within_a_second_is_not_corruption(
    small_library, files, extractor, monkeypatch
):
    manifest = (small_library / "manifest.json").read_bytes()
    monkeypatch.setattr(index, "utc_now", lambda: info(small_library).updated)  # same second
    _write_while_reading(
        monkeypatch,
        "b",
        lambda: remove(small_library, ["b"]),
        lambda: add(small_library, [files.root / "b.npy"], extractor, progress=False),
    )
    assert load(small_library, extractor.fingerprint).ids == ["a", "b"]
    assert (small_library / "manifest.json").read_bytes() == manifest  # the very same bytes


def test_garbage_manifest(small_library, extractor):
    (small_library / "manifest.json").write_bytes(b"\x00\xffnot json")
    with pytest.raises(LibraryCorruptError, match=r"manifest.json is not valid JSON"):
        load(small_library, extractor.fingerprint)
    (small_library / "manifest.json").write_text("[1, 2]")
    with pytest.raises(LibraryCorruptError, match="not a catalign library manifest"):
        load(small_library, extractor.fingerprint)


def test_missing_manifest(tmp_path, extractor):
    with pytest.raises(LibraryError, match=r"no library at .*catalign library build"):
        load(tmp_path / "nowhere", extractor.fingerprint)
    with pytest.raises(LibraryError, match=r"holds no manifest.json"):
        load(tmp_path, extractor.fingerprint)


def _edit_manifest(library_dir, edit) -> None:
    path = library_dir / "manifest.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("version", [99, 1])
def test_unknown_format_version(small_library, extractor, version):
    """Version 1 (entries without distance grids) is refused like any other, with the
    command that rebuilds it."""
    _edit_manifest(small_library, lambda m: m.update(format_version=version))
    expected = rf"format version {version}.*reads version 2.*library build .* --overwrite"
    with pytest.raises(LibraryCorruptError, match=expected):
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
        arrays = {name: npz[name] for name in npz.files if name != "grid"}
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _replace_entry(small_library, "a", buffer.getvalue())
    with pytest.raises(LibraryCorruptError, match=r"'a'.*malformed.*grid"):
        load(small_library, extractor.fingerprint)


def _replace_entry(library_dir, model_id: str, data: bytes) -> None:
    """Write ``data`` over an entry's file and make the manifest's checksum match it."""
    record = info(library_dir).entries[model_id]
    (library_dir / record.file).write_bytes(data)
    sha256 = hashlib.sha256(data).hexdigest()
    new_file = store.entry_file_name(model_id, sha256)
    (library_dir / record.file).rename(library_dir / new_file)
    _edit_manifest(
        library_dir, lambda m: m["entries"][model_id].update(sha256=sha256, file=new_file)
    )


@pytest.mark.parametrize(
    "edit",
    [
        lambda m: m["entries"]["a"].update(file="../../etc/passwd"),
        lambda m: m["entries"]["a"].pop("sha256"),
        lambda m: m["entries"]["a"].update(num_points="many"),
        lambda m: m["extractor"].pop("fingerprint"),
        lambda m: m["entries"]["a"].update(num_points=7),
    ],
)
def test_tampered_manifest(small_library, extractor, edit):
    _edit_manifest(small_library, edit)
    with pytest.raises(LibraryCorruptError):
        load(small_library, extractor.fingerprint)


def test_other_extractor_weights(small_library, files, extractor):
    with pytest.raises(LibraryMismatchError, match=r"'fake-v1'.*'other'.*catalign library build"):
        load(small_library, "other")
    assert len(load(small_library, None)) == 2  # inspection without an extractor

    class Other(type(extractor)):
        fingerprint = "other"

    with pytest.raises(LibraryMismatchError):
        add(small_library, [files.cloud("c.npy", 3)], Other(), progress=False)
