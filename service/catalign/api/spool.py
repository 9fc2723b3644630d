"""Where uploaded files wait while a request reads them, and the clean-up after a crash.

Readers need uploads as files on disk. Each server process spools them in a folder of its own,
``<spool root>/<host>-<pid>-<random>/``, and holds an exclusive ``flock`` on that folder's
``.lock`` for as long as it runs. A process killed mid-upload leaves its folder behind, but the
kernel drops its lock; so at start-up every sibling folder whose lock can be taken belongs to a
dead process and is removed, while the folders of live processes (other replicas sharing the
library folder) stay locked and untouched. The root is the library's ``.spool`` folder, which
the library's own clean-up never touches, unless settings name another or the library cannot be
written (a read-only mount): then the system's temporary folder.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

logger = logging.getLogger(__name__)

LOCK_NAME = ".lock"
LIBRARY_SPOOL = ".spool"


def default_spool_root(library: Path) -> Path:
    """The library's ``.spool`` folder when it can be created there, else the system's."""
    root = library / LIBRARY_SPOOL
    try:
        root.mkdir(exist_ok=True)
        if os.access(root, os.W_OK | os.X_OK):
            return root
    except OSError:
        pass
    return Path(tempfile.gettempdir()) / "catalign-spool"


class Spool:
    """This process's spool folder under ``root`` (None: :func:`default_spool_root` of
    ``library``, found at :meth:`open`, which also clears the folders of dead processes)."""

    def __init__(self, root: Path | None, *, library: Path) -> None:
        self.root = root
        self.library = library
        self._folder: Path | None = None
        self._lock: IO[bytes] | None = None

    @property
    def folder(self) -> Path:
        if self._folder is None:
            raise RuntimeError("the spool is not open")
        return self._folder

    def open(self) -> None:
        """Remove the folders of dead processes, then create and lock this process's own."""
        if self.root is None:
            self.root = default_spool_root(self.library)
        self.root.mkdir(parents=True, exist_ok=True)
        removed = remove_stale(self.root)
        if removed:
            logger.info("removed %d stale upload folder(s) from %s", removed, self.root)
        # Locked under a hidden name first, so no other process starting now can take it for
        # a dead one's; then renamed into view (the lock stays with the file).
        hidden = Path(tempfile.mkdtemp(prefix=".new-", dir=self.root))
        lock = open(hidden / LOCK_NAME, "wb")  # noqa: SIM115 (held until close)
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        folder = self.root / f"{socket.gethostname()}-{os.getpid()}-{hidden.name[5:]}"
        hidden.rename(folder)
        self._folder, self._lock = folder, lock

    def close(self) -> None:
        """Remove this process's folder and release its lock."""
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
        if self._lock is not None:
            self._lock.close()
        self._folder = self._lock = None

    @contextmanager
    def temporary_folder(self) -> Iterator[Path]:
        """A folder for one request's files, removed when the request ends."""
        with tempfile.TemporaryDirectory(prefix="upload-", dir=self.folder) as folder:
            yield Path(folder)


def remove_stale(root: Path) -> int:
    """Remove every folder under ``root`` whose lock no live process holds; how many."""
    removed = 0
    for folder in root.iterdir():
        if folder.name.startswith(".") or not folder.is_dir() or folder.is_symlink():
            continue
        try:
            with open(folder / LOCK_NAME, "ab") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                shutil.rmtree(folder, ignore_errors=True)
                removed += 1
        except BlockingIOError:
            continue  # a live process holds it
        except OSError as error:
            logger.warning("cannot clear stale upload folder %s: %s", folder, error)
    return removed
