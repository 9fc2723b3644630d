"""Entry archives: members LZMA-compressed or deflated, byte-reproducible, checked against
``np.load`` (the reference reader of the format) and ``zipfile``."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from catalign.library.npz import npz_arrays, npz_bytes


@pytest.fixture
def arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "model_id": np.array("proc-0001"),  # a 0-d string, as entries hold
        "point_steps": rng.integers(0, 65_535, size=(1001, 3), dtype=np.uint16),
        "keypoints": rng.normal(size=(77, 3)).astype(np.float32),
        "grid": np.full((40, 50, 30), 255, dtype=np.uint8),  # far from a surface: one value
        "fortran": np.asfortranarray(rng.normal(size=(6, 4))),
        "empty": np.zeros((0, 3), np.float32),
    }


def test_written_archives_are_plain_npz_with_the_large_members_in_lzma(arrays):
    data = npz_bytes(arrays, large=("grid", "point_steps"))
    assert data == npz_bytes(arrays, large=("grid", "point_steps"))  # the same content address
    with np.load(io.BytesIO(data), allow_pickle=False) as reference:
        assert sorted(reference.files) == sorted(arrays)
        for name, array in arrays.items():
            np.testing.assert_array_equal(reference[name], array)
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        methods = {m.filename: m.compress_type for m in archive.infolist()}
        assert methods.pop("grid.npy") == methods.pop("point_steps.npy") == zipfile.ZIP_LZMA
        assert set(methods.values()) == {zipfile.ZIP_DEFLATED}
        grid = archive.getinfo("grid.npy")
        assert grid.compress_size < grid.file_size / 50  # a uniform grid all but vanishes


def test_arrays_read_back_equal(arrays):
    read = npz_arrays(npz_bytes(arrays))
    assert sorted(read) == sorted(arrays)
    for name, array in arrays.items():
        np.testing.assert_array_equal(read[name], array)
        assert read[name].dtype == array.dtype and read[name].shape == array.shape
    assert read["fortran"].flags.f_contiguous


def test_an_archive_of_python_objects_is_refused():
    buffer = io.BytesIO()
    np.savez(buffer, thing=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="pickle"):
        npz_arrays(buffer.getvalue())


@pytest.mark.parametrize("damage", ["truncated", "flipped"])
def test_a_damaged_archive_is_refused(arrays, damage):
    data = bytearray(npz_bytes(arrays, large=("grid", "point_steps")))
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:  # inside the LZMA member of random steps: its stream or its CRC no longer holds
        data[len(data) // 2] ^= 0xFF
    with pytest.raises((ValueError, OSError, EOFError, zipfile.BadZipFile)):
        npz_arrays(bytes(data))


def test_archives_of_deflated_members_are_still_read(arrays):
    """Entries written before members were LZMA-compressed were deflated: they read as ever."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    read = npz_arrays(buffer.getvalue())
    for name, array in arrays.items():
        np.testing.assert_array_equal(read[name], array)
