"""One hierarchy for every error catalign raises on purpose.

Callers (the CLI, the HTTP layer, tests) catch :class:`CatalignError` and show its message; the
message always says what was wrong in words a user can act on, never a stack trace.

    CatalignError
    ├── InvalidInputError       bad points or options from a caller
    │   └── DegenerateInputError  too few points, a line or a plane
    ├── ShapeReadError          a file that is missing, unreadable, empty or non-finite
    ├── LibraryError            a library index that cannot be used
    │   ├── LibraryCorruptError
    │   ├── LibraryMismatchError  built with other extractor weights
    │   └── ModelNotFoundError
    ├── ConfigError             an unknown method name or a bad setting
    └── DeadlineExceededError   the request ran out of time or its caller went away
"""

from __future__ import annotations


class CatalignError(Exception):
    """Base of every error catalign raises on purpose."""


class InvalidInputError(CatalignError):
    """The caller's points or options are not usable."""


class DegenerateInputError(InvalidInputError):
    """The points are finite but cannot be registered (too few, collinear or planar)."""


class ShapeReadError(CatalignError):
    """A shape file is missing, unreadable, empty or holds non-finite values."""


class LibraryError(CatalignError):
    """A CAD library index cannot be used."""


class LibraryCorruptError(LibraryError):
    """The index on disk fails its format or checksum checks."""


class LibraryChangedError(LibraryError):
    """An entry the served library names was replaced or removed on disk while a request ran:
    the request is worth retrying on the library as it is now (at once: ``retry_after``)."""

    retry_after = 0


class LibraryMismatchError(LibraryError):
    """The index was built with other feature-extractor weights."""


class ModelNotFoundError(LibraryError):
    """No library entry has the requested id."""


class ConfigError(CatalignError):
    """An unknown name or an out-of-range setting."""


class DeadlineExceededError(CatalignError):
    """The work stopped: its deadline passed or its caller stopped waiting for it.

    ``retry_after`` (seconds), when known, is how long the service expects to be this busy.
    """

    def __init__(self, message: str, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.retry_after = retry_after
