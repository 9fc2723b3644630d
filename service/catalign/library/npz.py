"""Entry archives: ``.npz`` files with each member compressed, byte-reproducible, read whole.

An entry is read when it is shortlisted, not mapped while the library is served, so its file is
small rather than mappable. The members named large are LZMA-compressed, the rest deflated: on
the narrowed arrays (:mod:`~catalign.library.quantise`) LZMA takes a fifth more off the surface
and the distance grid than deflate does, for about 1.5 ms more each to read, while on the
features it saves 3 % for as much time, and each LZMA member costs its decoder's set-up
(docs/benchmarks.md, "Entry size"). The files stay ordinary ``.npz`` archives (``np.load``
reads them, whatever each member's method); members get fixed timestamps, so the same arrays
give the same bytes and the same content address.
"""

from __future__ import annotations

import io
import lzma
import zipfile
import zlib
from collections.abc import Collection, Mapping

import numpy as np

_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: the same arrays give the same bytes
_NPY_SUFFIX = ".npy"


def npz_bytes(arrays: Mapping[str, np.ndarray], large: Collection[str] = ()) -> bytes:
    """``arrays`` as ``.npz`` bytes, the ``large`` ones LZMA-compressed and the others
    deflated (zlib's default level), the same bytes for the same arrays."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, array in arrays.items():
            member = zipfile.ZipInfo(name + _NPY_SUFFIX, date_time=_ZIP_TIME)
            member.compress_type = zipfile.ZIP_LZMA if name in large else zipfile.ZIP_DEFLATED
            with archive.open(member, "w") as handle:
                np.lib.format.write_array(handle, np.asarray(array), allow_pickle=False)
    return buffer.getvalue()


def npz_arrays(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of ``.npz`` bytes, by member name without ``.npy``.

    Raises ValueError, OSError or ``zipfile.BadZipFile`` for what is not such an archive (a
    truncated member, an array of Python objects).
    """
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    except (zlib.error, lzma.LZMAError) as exc:  # a damaged compressed stream
        raise ValueError(f"a member does not decompress ({exc})") from exc
