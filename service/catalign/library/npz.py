"""Entry archives: uncompressed ``.npz`` files whose arrays are read as views of a memory map.

``np.load`` copies every array of an ``.npz`` into the reading process's own memory, so each
worker process of a server held a private copy of the whole library. :func:`npz_bytes` writes
each member so that its array data starts on a 64-byte boundary of the file (the member's local
header carries a padding record in its extra field, under the id Android's ``zipalign`` uses),
and :func:`mapped_arrays` returns read-only arrays that view one shared, read-only map of the
file: every process that loads the same library reads the same pages of the page cache. The
files stay ordinary ``.npz`` archives (``np.load`` and ``unzip`` read them). An array whose data
is not aligned for its type (files written before the padding) is copied instead of viewed.

Entry files are never modified in place (they are content-addressed and replaced by rename), so
a map stays valid while the server runs, even after a newer library deleted the file.
"""

from __future__ import annotations

import io
import math
import mmap
import struct
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

ALIGN = 64  # bytes: numpy pads a .npy header to this, so a member aligned here has aligned data
_PADDING_EXTRA_ID = 0xD935  # the extra-field id zipalign's padding records use
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: the same arrays give the same bytes
_LOCAL_HEADER = struct.Struct("<4s22xHH")  # signature, ..., file name length, extra length
_LOCAL_SIGNATURE = b"PK\x03\x04"
_ZIP64_EXTRA = 20  # bytes zipfile appends to a local header written with force_zip64
_NPY_SUFFIX = ".npy"


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """``arrays`` as uncompressed ``.npz`` bytes, byte-reproducible, each array's data aligned
    to :data:`ALIGN` bytes from the start of the file."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, array in arrays.items():
            member = zipfile.ZipInfo(name + _NPY_SUFFIX, date_time=_ZIP_TIME)
            header = _LOCAL_HEADER.size + len(member.filename.encode()) + _ZIP64_EXTRA
            member.extra = _padding(buffer.tell() + header)
            with archive.open(member, "w", force_zip64=True) as handle:
                np.lib.format.write_array(handle, np.asarray(array), allow_pickle=False)
    return buffer.getvalue()


def map_file(path: Path) -> mmap.mmap | bytes:
    """A read-only map of the file at ``path`` (``b""`` for an empty file, which cannot be
    mapped); FileNotFoundError when it is missing."""
    with open(path, "rb") as handle:
        if not handle.seek(0, io.SEEK_END):
            return b""
        return mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)


def mapped_arrays(mapped: mmap.mmap) -> dict[str, np.ndarray]:
    """The arrays of an uncompressed ``.npz`` file mapped by :func:`map_file`, by member name
    without ``.npy``; read-only views of the map where aligned, copies elsewhere.

    Raises ValueError or ``zipfile.BadZipFile`` for what is not such an archive (a compressed
    member, a truncated array, an array of Python objects).
    """
    arrays = {}
    with zipfile.ZipFile(mapped) as archive:
        for member in archive.infolist():
            name = member.filename.removesuffix(_NPY_SUFFIX)
            if member.compress_type != zipfile.ZIP_STORED:
                raise ValueError(f"member {member.filename!r} is compressed")
            arrays[name] = _member_array(mapped, member)
    return arrays


def _member_array(mapped: mmap.mmap, member: zipfile.ZipInfo) -> np.ndarray:
    signature, name_length, extra_length = _LOCAL_HEADER.unpack_from(mapped, member.header_offset)
    if signature != _LOCAL_SIGNATURE:
        raise ValueError(f"member {member.filename!r} has no local header")
    start = member.header_offset + _LOCAL_HEADER.size + name_length + extra_length
    mapped.seek(start)
    version = np.lib.format.read_magic(mapped)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(mapped)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(mapped)
    else:
        raise ValueError(f"member {member.filename!r} has .npy format {version}")
    if dtype.hasobject:
        raise ValueError(f"member {member.filename!r} holds Python objects")
    count, offset = math.prod(shape), mapped.tell()
    if offset + count * dtype.itemsize > start + member.file_size:
        raise ValueError(f"member {member.filename!r} is truncated")
    if count == 0:
        return np.empty(shape, dtype)
    order = "F" if fortran else "C"
    array = np.frombuffer(mapped, dtype, count=count, offset=offset).reshape(shape, order=order)
    return array if offset % dtype.alignment == 0 else array.copy(order="K")


def _padding(start: int) -> bytes:
    """An extra field that moves a local header's data from offset ``start`` to the next
    multiple of :data:`ALIGN` (empty when it is one already; a record needs 4 bytes at least)."""
    pad = -start % ALIGN
    if 0 < pad < 4:
        pad += ALIGN
    if pad == 0:
        return b""
    return struct.pack("<HH", _PADDING_EXTRA_ID, pad - 4) + bytes(pad - 4)
