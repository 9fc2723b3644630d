"""Entry archives: aligned on write, viewed through a memory map on read, checked against
``np.load`` (the reference reader of the format)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from catalign.library.npz import ALIGN, map_file, mapped_arrays, npz_bytes


@pytest.fixture
def arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "model_id": np.array("proc-0001"),  # a 0-d string, as entries hold
        "points": rng.normal(size=(1001, 3)).astype(np.float32),
        "keypoints": rng.normal(size=(77, 3)),
        "grid": rng.integers(0, 255, size=(5, 7, 3), dtype=np.uint8),
        "fortran": np.asfortranarray(rng.normal(size=(6, 4))),
        "empty": np.zeros((0, 3), np.float32),
    }


def _written(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "entry.npz"
    path.write_bytes(data)
    return path


def test_written_archives_are_plain_npz_with_aligned_arrays(tmp_path, arrays):
    data = npz_bytes(arrays)
    assert data == npz_bytes(arrays)  # byte-reproducible
    with np.load(io.BytesIO(data), allow_pickle=False) as reference:
        assert sorted(reference.files) == sorted(arrays)
        for name, array in arrays.items():
            np.testing.assert_array_equal(reference[name], array)
    # every array's bytes start on an ALIGN boundary of the file (found independently)
    for name in ("points", "keypoints", "grid"):
        assert data.find(arrays[name].tobytes()) % ALIGN == 0, name


def test_mapped_arrays_view_the_file_read_only(tmp_path, arrays):
    mapped = mapped_arrays(map_file(_written(tmp_path, npz_bytes(arrays))))
    assert sorted(mapped) == sorted(arrays)
    for name, array in arrays.items():
        np.testing.assert_array_equal(mapped[name], array)
        assert mapped[name].dtype == array.dtype and mapped[name].shape == array.shape
    for name in ("points", "keypoints", "grid", "fortran"):
        assert not mapped[name].flags.owndata, name  # a view of the map, not a copy
        assert not mapped[name].flags.writeable, name
    assert mapped["fortran"].flags.f_contiguous
    with pytest.raises(ValueError, match="read-only"):
        mapped["points"][0, 0] = 1.0


def test_unaligned_archives_from_np_savez_are_read_by_copying(tmp_path, arrays):
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # no padding: members start wherever the zip puts them
    mapped = mapped_arrays(map_file(_written(tmp_path, buffer.getvalue())))
    for name, array in arrays.items():
        np.testing.assert_array_equal(mapped[name], array)
        assert mapped[name].flags.aligned, name


@pytest.mark.parametrize(
    ("make", "problem"),
    [
        (lambda a, out: np.savez_compressed(out, **a), "compressed"),
        (lambda a, out: np.savez(out, thing=np.array([{"a": 1}], dtype=object)), "objects"),
    ],
)
def test_archives_it_cannot_map_are_refused(tmp_path, arrays, make, problem):
    buffer = io.BytesIO()
    make(arrays, buffer)
    with pytest.raises(ValueError, match=problem):
        mapped_arrays(map_file(_written(tmp_path, buffer.getvalue())))


def test_a_truncated_archive_is_refused(tmp_path, arrays):
    data = npz_bytes(arrays)
    with pytest.raises((ValueError, zipfile.BadZipFile)):
        mapped_arrays(map_file(_written(tmp_path, data[: len(data) // 2])))


def test_an_empty_file_maps_to_no_bytes_and_a_missing_one_is_not_found(tmp_path):
    assert map_file(_written(tmp_path, b"")) == b""
    with pytest.raises(FileNotFoundError):
        map_file(tmp_path / "missing.npz")
