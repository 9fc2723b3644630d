"""What a library's catalogue says about the library and each of its entries (no arrays).

Their own module because both the catalogue (:mod:`catalign.library.catalogue`, which stores
them) and the store (:mod:`catalign.library.store`, which writes the entry files they describe)
need them; the build journal keeps records as JSON lines (:meth:`EntryRecord.to_json`).
"""

from __future__ import annotations

import base64
import binascii
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from catalign.library.sources import CATEGORY_PATTERN, DEFAULT_CATEGORY

# 2: entries hold their surface's distance grid; 3: an SQLite catalogue; 4: small entries
# (narrowed arrays, compressed; entry_codec.py reads both of their layouts) and each entry's
# descriptor in the catalogue
FORMAT_VERSION = 4
MIGRATABLE_VERSIONS = (2, 3)  # ``catalign library migrate`` converts these
ENTRIES_DIR = "entries"
_SHA256 = re.compile(r"[0-9a-f]{64}")


def rebuild_hint(library_dir: Path) -> str:
    """The sentence that tells a user how to make a fresh library."""
    return f"rebuild it with `catalign library build SRC... --out {library_dir} --overwrite`"


def entry_file_name(model_id: str, sha256: str) -> str:
    """Relative path of an entry file: ``entries/<id>-<sha256[:12]>.npz``."""
    return f"{ENTRIES_DIR}/{model_id}-{sha256[:12]}.npz"


@dataclass(frozen=True)
class EntryRecord:
    """What the catalogue says about one entry (no arrays)."""

    file: str
    sha256: str
    source: str
    source_sha256: str
    units: str
    num_points: int
    num_keypoints: int
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    size: tuple[float, float, float]
    category: str = DEFAULT_CATEGORY
    symmetry: int | None = None
    """The entry's :class:`~catalign.geometry.symmetry.YawSymmetry` order; None in a record
    written before entries had one (found again from the entry's points when it is read)."""
    descriptor: bytes = b""
    """The entry's shortlisting descriptor, float32 little-endian: a served library stacks
    these from the catalogue without opening an entry file."""
    outline: bytes = b""
    """The entry's :class:`~catalign.library.outline.Outline` as bytes, which the shortlist
    re-ranks by; empty in a record written before entries had one (made again from the
    entry's points when it is needed)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "sha256": self.sha256,
            "source": self.source,
            "source_sha256": self.source_sha256,
            "units": self.units,
            "num_points": self.num_points,
            "num_keypoints": self.num_keypoints,
            "bbox_min": list(self.bbox_min),
            "bbox_max": list(self.bbox_max),
            "size": list(self.size),
            "category": self.category,
            "symmetry": self.symmetry,
            "descriptor": base64.b64encode(self.descriptor).decode(),
            "outline": base64.b64encode(self.outline).decode(),
        }

    @classmethod
    def from_json(
        cls, model_id: str, data: Any, default_category: str = DEFAULT_CATEGORY
    ) -> EntryRecord:
        """Parse and check one JSON record (one written before entries had categories is of
        ``default_category``); raises ValueError, KeyError or TypeError."""
        data = typed(data, dict)
        record = cls(
            file=typed(data["file"], str),
            sha256=typed(data["sha256"], str),
            source=typed(data["source"], str),
            source_sha256=typed(data["source_sha256"], str),
            units=typed(data["units"], str),
            num_points=typed(data["num_points"], int),
            num_keypoints=typed(data["num_keypoints"], int),
            bbox_min=vector(data["bbox_min"]),
            bbox_max=vector(data["bbox_max"]),
            size=vector(data["size"]),
            category=typed(data.get("category", default_category), str),
            symmetry=data.get("symmetry"),
            descriptor=_decoded(data.get("descriptor", "")),
            outline=_decoded(data.get("outline", "")),
        )
        record.check(model_id)
        return record

    def check(self, model_id: str) -> None:
        """Refuse values no writer stores (a record edited or damaged on disk), so that a bad
        one never names a file outside the library; raises ValueError."""
        if CATEGORY_PATTERN.fullmatch(self.category) is None:
            raise ValueError(f"category {self.category!r} is not a valid category")
        symmetry = self.symmetry
        if symmetry is not None and (type(symmetry) is not int or symmetry < 0):
            raise ValueError(f"symmetry {symmetry!r} is not an order (0, 1, 2...)")
        if type(self.descriptor) is not bytes or len(self.descriptor) % 4:
            raise ValueError("descriptor is not float32 bytes")
        if type(self.outline) is not bytes:
            raise ValueError("outline is not bytes")
        if not _SHA256.fullmatch(self.sha256):
            raise ValueError(f"sha256 {self.sha256!r} is not a hex sha256")
        if self.file != entry_file_name(model_id, self.sha256):
            raise ValueError(f"file {self.file!r} does not match the id and sha256")


@dataclass(frozen=True)
class Manifest:
    """A library's description as its catalogue holds it: extractor, timestamps and the entry
    records by id."""

    fingerprint: str
    voxel_size: float
    created: str
    updated: str
    entries: dict[str, EntryRecord] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION
    engine: dict[str, Any] = field(default_factory=dict)
    """Engine options the library is served with, over the defaults and under the service's
    own (:func:`~catalign.registration.config.served_config`); ``catalign library configure``
    sets them. Checked when a server applies them, so a bad one can still be cleared."""
    category: str = DEFAULT_CATEGORY
    """The category of an entry added without one (``library build --category`` sets it)."""

    @property
    def ids(self) -> list[str]:
        return sorted(self.entries)

    def categories(self) -> dict[str, int]:
        """How many entries each category holds, by name."""
        counts = Counter(record.category for record in self.entries.values())
        return dict(sorted(counts.items()))


def typed(value: Any, kind: Any) -> Any:
    """``value`` if it is a ``kind`` (never a bool standing for a number); else TypeError."""
    if not isinstance(value, kind) or isinstance(value, bool):
        raise TypeError(f"unexpected {type(value).__name__} {value!r}")
    return value


def vector(values: Any) -> tuple[float, float, float]:
    """Three numbers as a tuple of floats; TypeError or ValueError otherwise."""
    items = [float(typed(v, int | float)) for v in values]
    if len(items) != 3:
        raise ValueError(f"expected 3 numbers, got {len(items)}")
    return (items[0], items[1], items[2])


def _decoded(text: Any) -> bytes:
    try:
        return base64.b64decode(typed(text, str), validate=True)
    except binascii.Error as exc:
        raise ValueError(f"an array is not base64 ({exc})") from exc
