"""What every header check shares: the limits on reading, the file, its wording, its arithmetic.

A header check needs the same few things whatever the format: a bound on how much of a file it
reads, one way to say a file is unreadable (with the path and the suffix), the test that declared
counts fit in the bytes the file has and stay under the caller's limits, whole-number parsing that
refuses what would be costly to parse, text header lines read from a bounded prefix, and line
counting that streams a file in chunks for formats that declare nothing. They live here so that
each format's module holds only what that format declares.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from catalign.errors import ShapeReadError

HEADER_BYTES = 64 * 1024
"""The most bytes read to find a text header (PCD, PLY, OFF); a longer header is refused."""

CHUNK_BYTES = 1 << 20
"""Bytes read at a time when a file declares nothing and its lines must be counted."""

TEXT_VALUE_BYTES = 2
"""The fewest bytes a number takes in a text format: one digit and one separator."""

LZF_MAX_EXPANSION = 88
"""LZF (PCD ``binary_compressed``) turns at most 3 input bytes into 264 output bytes."""

GLTF_FILL_EXPANSION = 64
"""glTF accessors without data are filled with zeros: at most this many times the file size."""

_LINE_HEAD = 256  # bytes of a line kept across chunks: only a line's start is ever matched
_WHOLE = re.compile(r"[+-]?[0-9]{1,30}")  # longer numbers are refused, not parsed


@dataclass(frozen=True)
class Declared:
    """The counts a file declares (or holds, where it was counted); ``None``: not counted."""

    points: int | None
    faces: int | None


@dataclass(frozen=True)
class File:
    """A file under check: its path, its size on disk and the caller's limits."""

    path: Path
    size: int
    max_points: int | None
    max_faces: int | None

    def unreadable(self, why: str) -> ShapeReadError:
        """A file whose header is malformed or claims more than the file holds."""
        return ShapeReadError(f"{self.path}: not a readable {self.path.suffix.lower()} file: {why}")

    def room(self, available: int) -> str:
        """How many bytes the data may take, in words: the size, and what follows the header."""
        if available == self.size:
            return f"the file's {self.size} bytes"
        return f"the file's {self.size} bytes ({available} after the header)"

    def fits(self, items: Sequence[tuple[int, str, int]], available: int, text: bool) -> None:
        """Refuse unless ``(count, noun, fewest bytes each)`` items fit in ``available`` bytes.

        ``text``: the last value of a text file needs no separator, so one byte less will do.
        """
        slack = 1 if text else 0
        for count, noun, each in items:
            if each > 0 and count * each > available + slack:
                raise self.unreadable(
                    f"the header declares {count} {noun}, but {self.room(available)} "
                    f"can hold at most {(available + slack) // each}"
                )
        need = sum(count * each for count, _, each in items)
        if need > available + slack:
            listed = " and ".join(f"{count} {noun}" for count, noun, _ in items)
            raise self.unreadable(
                f"the header declares {listed}, which take at least {need} bytes, "
                f"but {self.room(available)} are fewer"
            )

    def within_limits(
        self, points: int | None, faces: int | None, *, how: str = "the header declares"
    ) -> Declared:
        """Refuse counts over ``max_points`` / ``max_faces``; return them as :class:`Declared`."""
        if self.max_points is not None and points is not None and points > self.max_points:
            raise ShapeReadError(
                f"{self.path}: {how} {points} points, more than the limit of "
                f"{self.max_points} points"
            )
        if self.max_faces is not None and faces is not None and faces > self.max_faces:
            raise ShapeReadError(
                f"{self.path}: {how} {faces} faces, more than the limit of {self.max_faces} faces"
            )
        return Declared(points=points, faces=faces)

    @property
    def limited(self) -> bool:
        return self.max_points is not None or self.max_faces is not None


def whole(f: File, text: str, what: str) -> int:
    """A header value that must be a whole number of at least zero."""
    if not _WHOLE.fullmatch(text):
        raise f.unreadable(f"the header's {what} {text!r} is not a whole number")
    value = int(text)
    if value < 0:
        raise f.unreadable(f"the header declares a negative {what} ({value})")
    return value


def header_lines(
    f: File, prefix: bytes, is_last: Callable[[list[str]], bool], last: str
) -> tuple[list[list[str]], int]:
    """Split a text header into lines of words, up to and including the line ``is_last`` picks.

    Returns the lines and the offset of the first byte after the header.
    """
    lines: list[list[str]] = []
    start = 0
    while start < len(prefix):
        end = prefix.find(b"\n", start)
        if end < 0:
            if len(prefix) == f.size:  # the header is the whole file and lacks a final newline
                end = len(prefix)
            else:
                break
        words = prefix[start:end].decode("latin-1").split()
        lines.append(words)
        start = end + 1
        if words and is_last(words):
            return lines, min(start, f.size)
    if len(prefix) < f.size:
        raise f.unreadable(f"the header does not end within its first {HEADER_BYTES} bytes")
    raise f.unreadable(f"the header has no {last} line")


def count_line_starts(
    path: Path, patterns: Sequence[re.Pattern[bytes]], stops: Sequence[int | None]
) -> list[int]:
    """Count the lines each pattern matches at their start, reading the file in chunks.

    Stops early once a count passes its stop value. Only the first bytes of a line are kept
    from one chunk to the next, so memory stays bounded whatever the line lengths.
    """
    counts = [0] * len(patterns)
    carry = b""
    with path.open("rb") as handle:
        while True:
            chunk = handle.read(CHUNK_BYTES)
            text = carry + chunk
            cut = len(text) if not chunk else text.rfind(b"\n") + 1
            body, carry = text[:cut], text[cut:][:_LINE_HEAD]
            for i, pattern in enumerate(patterns):
                counts[i] += len(pattern.findall(body))
            if any(s is not None and c > s for c, s in zip(counts, stops, strict=True)):
                return counts
            if not chunk:
                return counts
