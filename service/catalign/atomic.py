"""Crash-safe file writes: write a temporary file, fsync it, rename it over the target.

A reader sees either the old file or the new one, never a half-written one, even if the
process is killed mid-write; the directory is fsynced too so the rename itself survives a crash.
"""

from __future__ import annotations

import os
from pathlib import Path


def fsync_directory(directory: Path) -> None:
    """Make a rename or unlink in ``directory`` durable."""
    fsync_file(directory)


def fsync_file(path: Path) -> None:
    """Make what was written to ``path`` durable (a file another library wrote and closed)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes, *, sync_directory: bool = True) -> None:
    """Replace ``path`` with ``data`` atomically; ``sync_directory=False`` leaves fsyncing the
    folder to a caller that writes many files and syncs the folder once."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    if sync_directory:
        fsync_directory(path.parent)
