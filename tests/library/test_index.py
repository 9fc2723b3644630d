from __future__ import annotations

import hashlib
import threading

import numpy as np
import pytest
from scipy.spatial import cKDTree

import catalign.library as library_api
import catalign.library.shortlist_index as shortlist_index
from catalign.errors import InvalidInputError, LibraryError, ModelNotFoundError
from catalign.features.extractor import FPFHExtractor
from catalign.geometry.io import read_shape
from catalign.library import (
    Library,
    add,
    build,
    build_procedural,
    info,
    list_models,
    load,
    remove,
)
from catalign.library.entry import (
    DENSITY_DIAGONAL,
    MAX_SURFACE_POINTS,
    SURFACE_POINTS,
    describe_file,
    mesh_sha256,
)
from catalign.library.quantise import SURFACE_STEPS
from catalign.library.sources import SourceFile
from catalign.library.store import manifest_stamp
from tests.library.conftest import stored


def referenced_files(library_dir) -> set[str]:
    return {r.file.split("/")[1] for r in info(library_dir).entries.values()}


def entry_files(library_dir) -> set[str]:
    return {p.name for p in (library_dir / "entries").iterdir()}


def assert_same_entries(left: Library, right: Library) -> None:
    assert left.ids == right.ids
    for a, b in zip(left, right, strict=True):
        for name in ("points", "keypoints", "features", "descriptor", "bbox_min", "bbox_max"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert (a.source, a.source_sha256, a.units) == (b.source, b.source_sha256, b.units)
    np.testing.assert_array_equal(left.descriptors, right.descriptors)
    np.testing.assert_array_equal(left.sizes, right.sizes)


def test_exports_do_not_drift():
    assert library_api.__all__ == sorted(library_api.__all__, key=lambda n: (not n.isupper(), n))
    assert set(library_api.__all__) == {
        "FORMAT_VERSION",
        "MODEL_ID_PATTERN",
        "SURFACE_POINTS",
        "UNIT_FACTORS",
        "EntryRecord",
        "Library",
        "LibraryEntry",
        "Manifest",
        "add",
        "build",
        "build_procedural",
        "global_descriptor",
        "info",
        "list_models",
        "load",
        "remove",
        "retrieval_scores",
        "shortlist",
        "validate_model_id",
    }


def test_build_from_a_folder_of_mixed_formats(mixed_folder, tmp_path, extractor):
    out = tmp_path / "lib"
    manifest = build([mixed_folder], out, extractor, progress=False)
    meshes = {"box", "capsule", "cone", "cylinder", "sphere"}
    clouds = {"big", "points", "scan", "scan2"}
    assert manifest.ids == sorted(meshes | clouds)

    query = "SELECT format_version, fingerprint, voxel_size, created, updated FROM library"
    ((version, fingerprint, voxel_size, created, updated),) = stored(out, query)
    assert (version, fingerprint, voxel_size) == (4, "fake-v1", 0.05)
    assert created == updated and created.endswith("+00:00")

    lib = load(out, extractor.fingerprint)
    assert len(lib) == 9 and lib.ids == manifest.ids
    assert lib.descriptors.shape == (9, 8) and lib.descriptors.dtype == np.float32
    assert lib.sizes.shape == (9, 3)
    for entry in lib:
        record = manifest.entries[entry.model_id]
        source = next(mixed_folder.rglob(f"{entry.model_id}.*"))
        assert record.source == str(source.resolve()) == entry.source
        assert record.source_sha256 == hashlib.sha256(source.read_bytes()).hexdigest()
        assert record.file == f"entries/{entry.model_id}-{record.sha256[:12]}.npz"
        assert record.sha256 == hashlib.sha256((out / record.file).read_bytes()).hexdigest()
        expected = SURFACE_POINTS if entry.model_id in meshes | {"big"} else 600
        assert entry.points.shape == (expected, 3) and entry.points.dtype == np.float32
        assert record.num_points == expected and record.num_keypoints == len(entry.keypoints)
        assert entry.features.shape == (len(entry.keypoints), 4)
        assert entry.features.dtype == np.float32 and entry.descriptor.shape == (8,)
        full = read_shape(source).points
        np.testing.assert_allclose(entry.bbox_min, full.min(axis=0))
        np.testing.assert_allclose(entry.size, np.ptp(full, axis=0))
        assert list(record.size) == entry.size.tolist()
        assert not entry.points.flags.writeable  # shared between requests: read-only
    np.testing.assert_allclose(lib["box"].size, [0.5, 0.9, 0.5])


def test_sampling_is_deterministic(files, extractor):
    path = files.box("box.obj")
    first = describe_file(SourceFile("box", path), extractor)
    second = describe_file(SourceFile("box", path), extractor)
    np.testing.assert_array_equal(first.points, second.points)


def test_units_mm_scales_everything_to_metres(files, tmp_path, extractor):
    points_mm = files.random_cloud(5, count=500, scale=400.0)
    files.points("scan_mm.npy", points_mm)
    files.box("box_mm.stl", extents=(500.0, 900.0, 450.0))
    out = tmp_path / "lib"
    manifest = build([files.root], out, extractor, units="mm", progress=False)
    lib = load(out, extractor.fingerprint)
    _assert_narrowed(lib["scan_mm"].points, points_mm * 0.001)
    np.testing.assert_allclose(lib["box_mm"].size, [0.5, 0.9, 0.45])
    assert np.abs(lib["box_mm"].points).max() <= 0.45 + 1e-6
    assert {r.units for r in manifest.entries.values()} == {"mm"}
    assert lib["box_mm"].units == "mm"


def test_build_add_remove_reload_round_trip(files, tmp_path, extractor):
    out = tmp_path / "lib"
    first = build([files.cloud("a.npy", 1), files.box("b.obj")], out, extractor, progress=False)
    lib_before = load(out, extractor.fingerprint)

    added = add(out, [files.cloud("c.xyz", 3)], extractor, ids=["c-1"], progress=False)
    assert list(added) == ["c-1"]
    assert info(out).ids == ["a", "b", "c-1"] and info(out).created == first.created
    assert remove(out, ["a"]) == 2
    assert list_models(out) == ["b", "c-1"]
    assert info(out).entries == {"b": first.entries["b"], "c-1": added["c-1"]}  # as written
    assert entry_files(out) == referenced_files(out)  # a's file is gone

    lib = load(out, extractor.fingerprint)
    assert lib.ids == ["b", "c-1"] and "a" not in lib and "b" in lib
    again = load(out, extractor.fingerprint)
    assert_same_entries(lib, again)
    np.testing.assert_array_equal(lib["b"].points, lib_before["b"].points)
    fresh = describe_file(SourceFile("c-1", files.root / "c.xyz"), extractor)
    np.testing.assert_array_equal(lib["c-1"].keypoints, fresh.keypoints)
    np.testing.assert_array_equal(lib["c-1"].features, fresh.features)
    with pytest.raises(ModelNotFoundError, match="'a'"):
        lib["a"]


def test_an_add_writes_the_shortlist_index_again_once_too_many_entries_wait(
    files, tmp_path, extractor, monkeypatch
):
    monkeypatch.setattr(shortlist_index, "STALE_INDEX_ENTRIES", 2)  # instead of 1,000
    out = tmp_path / "lib"
    build([files.cloud(f"s{i}.npy", i) for i in range(3)], out, extractor, progress=False)
    add(out, [files.cloud("a.npy", 10), files.cloud("b.npy", 11)], extractor, progress=False)
    assert load(out, extractor.fingerprint).index.unindexed == 2  # as many as may wait
    stamp = manifest_stamp(out)
    add(out, [files.cloud("c.npy", 12)], extractor, progress=False)
    index = load(out, extractor.fingerprint).index
    assert (index.indexed, index.unindexed) == (6, 0)  # written again over every entry
    assert manifest_stamp(out) != stamp
    (out / "shortlist-index" / "index.json").unlink()  # a lost index: every entry waits
    add(out, [files.cloud("d.npy", 13)], extractor, progress=False)
    assert load(out, extractor.fingerprint).index.indexed == 7


def test_an_added_file_can_be_recorded_under_another_name(files, tmp_path, extractor):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1)], out, extractor, progress=False)
    path = files.cloud("tmp123.npy", 2)
    add(out, [path], extractor, ids=["c"], progress=False, source_name="upload:chair.npy")
    lib = load(out, extractor.fingerprint)
    assert lib["c"].source == "upload:chair.npy" and lib["a"].source == str(files.root / "a.npy")
    with pytest.raises(InvalidInputError, match="one file"):
        add(out, [files.cloud("d.npy", 3), files.cloud("e.npy", 4)], extractor, source_name="x")
    assert load(out, extractor.fingerprint).ids == ["a", "c"]


def test_adding_an_existing_id_without_replace_changes_nothing(
    files, tmp_path, extractor, snapshot
):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1)], out, extractor, progress=False)
    before = snapshot(out)
    other = files.cloud("other/a.npy", 2)
    with pytest.raises(InvalidInputError, match=r"'a'.*already in the library.*--replace"):
        add(out, [other], extractor, progress=False)
    assert snapshot(out) == before


def test_replace_swaps_the_entry_and_deletes_its_old_file(files, tmp_path, extractor):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1), files.cloud("b.npy", 2)], out, extractor, progress=False)
    old = info(out).entries["a"]
    new_source = files.cloud("v2/a.npy", 7)
    record = add(out, [new_source], extractor, replace=True, progress=False)["a"]
    assert info(out).entries["a"] == record
    assert record.file != old.file and not (out / old.file).exists()
    assert record.source_sha256 == hashlib.sha256(new_source.read_bytes()).hexdigest()
    assert entry_files(out) == referenced_files(out)
    lib = load(out, extractor.fingerprint)
    _assert_narrowed(lib["a"].points, np.load(new_source))


def test_build_refuses_an_existing_library_unless_overwrite(files, tmp_path, extractor):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1)], out, extractor, progress=False)
    old_files = entry_files(out)
    with pytest.raises(LibraryError, match="already holds a library"):
        build([files.cloud("x/b.npy", 2)], out, extractor, progress=False)
    assert list_models(out) == ["a"]
    build([files.root / "x" / "b.npy"], out, extractor, overwrite=True, progress=False)
    assert list_models(out) == ["b"] and not old_files & entry_files(out)


def test_add_and_remove_need_an_existing_library(files, tmp_path, extractor):
    with pytest.raises(LibraryError, match=r"no library at .*catalign library build"):
        add(tmp_path / "nowhere", [files.cloud("a.npy")], extractor, progress=False)
    assert not (tmp_path / "nowhere").exists()
    with pytest.raises(LibraryError, match="no library"):
        remove(tmp_path / "nowhere", ["a"])


def test_remove_unknown_id(files, tmp_path, extractor, snapshot):
    out = tmp_path / "lib"
    build([files.cloud("a.npy", 1), files.cloud("b.npy", 2)], out, extractor, progress=False)
    before = snapshot(out)
    with pytest.raises(ModelNotFoundError, match="'zzz'"):
        remove(out, ["a", "zzz"])
    assert snapshot(out) == before


def test_a_shape_without_key_points_is_refused(files, tmp_path):
    files.cloud("a.npy", 1)
    with pytest.raises(InvalidInputError, match=r"a.npy: the extractor found no key points"):
        build([files.root], tmp_path / "lib", _EmptyExtractor(), progress=False)
    assert not (tmp_path / "lib" / "catalogue.sqlite").exists()


class _EmptyExtractor:
    voxel_size = 0.05
    fingerprint = "empty"

    def describe(self, points):
        from catalign.features.extractor import Described

        return Described(np.zeros((0, 3)), np.zeros((0, 4), dtype=np.float32))


def test_concurrent_writers_in_one_process_are_serialised(files, tmp_path, extractor):
    out = tmp_path / "lib"
    build([files.cloud("base.npy", 0)], out, extractor, progress=False)
    sources = [files.cloud(f"t{i}.npy", i + 1) for i in range(6)]
    errors: list[BaseException] = []

    def worker(path):
        try:
            add(out, [path], extractor, progress=False)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(p,)) for p in sources]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert list_models(out) == ["base"] + [f"t{i}" for i in range(6)]
    assert len(load(out, extractor.fingerprint)) == 7


def test_build_procedural_with_fpfh(tmp_path):
    extractor = FPFHExtractor(voxel_size=0.05)
    manifest = build_procedural(tmp_path / "lib", extractor, 3, first_seed=4, progress=False)
    assert manifest.ids == ["proc-0004", "proc-0005", "proc-0006"]
    assert manifest.fingerprint == "fpfh-v1-0.05"
    lib = load(tmp_path / "lib", extractor.fingerprint)
    entry = lib["proc-0005"]
    assert entry.source == "procedural:5" and entry.units == "m"
    from catalign.data.procedural import generate_chair
    from catalign.geometry.io import MeshData

    chair = generate_chair(5)
    assert entry.source_sha256 == mesh_sha256(MeshData(chair.vertices, chair.faces))
    np.testing.assert_allclose(entry.size, chair.extents)
    assert entry.points.shape == (SURFACE_POINTS, 3) and entry.features.shape[1] == 33
    assert lib.descriptors.shape == (3, 66)
    # reproducible: the same chairs give byte-identical entry files
    again = build_procedural(tmp_path / "again", extractor, 3, first_seed=4, progress=False)
    assert {i: r.sha256 for i, r in again.entries.items()} == {
        i: r.sha256 for i, r in manifest.entries.items()
    }
    with pytest.raises(InvalidInputError, match="at least one chair"):
        build_procedural(tmp_path / "none", extractor, 0)


def test_mesh_with_zero_area_is_a_read_error(files, tmp_path, extractor):
    from catalign.errors import ShapeReadError

    path = files.root / "flat.obj"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(ShapeReadError, match=r"flat.obj"):
        build([path], tmp_path / "lib", extractor, progress=False)


def test_a_model_larger_than_a_chair_keeps_a_chairs_sample_density(files, extractor):
    # A 3 m sofa-sized box has 1.5 times the diagonal of DENSITY_DIAGONAL: 2.25 times the area
    # to cover, so 2.25 times the points; a chair-sized box keeps SURFACE_POINTS, and a point
    # cloud cannot give more points than it has.
    sofa = describe_file(SourceFile("sofa", files.box("sofa.ply", (2.6, 0.9, 1.2))), extractor)
    diagonal = float(np.linalg.norm([2.6, 0.9, 1.2]))
    assert diagonal > DENSITY_DIAGONAL
    expected = round(SURFACE_POINTS * (diagonal / DENSITY_DIAGONAL) ** 2)
    assert len(sofa.points) == expected
    chair = describe_file(SourceFile("chair", files.box("chair.ply")), extractor)
    assert len(chair.points) == SURFACE_POINTS
    cloud = files.points("scan.npy", files.random_cloud(5, count=12_000, scale=1.5))
    assert len(describe_file(SourceFile("scan", cloud), extractor).points) == 12_000
    # a room-sized box would need more than the most points an entry keeps
    room = (3.0, 1.5, 3.0)
    assert SURFACE_POINTS * (np.linalg.norm(room) / DENSITY_DIAGONAL) ** 2 > MAX_SURFACE_POINTS
    huge = describe_file(SourceFile("room", files.box("room.ply", room)), extractor)
    assert len(huge.points) == MAX_SURFACE_POINTS


def _assert_narrowed(stored: np.ndarray, points: np.ndarray) -> None:
    """``stored`` holds ``points``, in its own order, each to within half a 12-bit step of
    their bounding box (and half a 16-bit one: the steps features are computed from)."""
    span = np.ptp(points, axis=0)
    reach = span / SURFACE_STEPS / 2 + span / 65_535 / 2 + 1e-7
    assert len(stored) == len(points)
    _, nearest = cKDTree(stored).query(points)
    assert len(set(nearest)) == len(points)  # one stored point for each point
    assert np.all(np.abs(stored[nearest] - points) <= reach)
