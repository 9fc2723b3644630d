"""A cap on the address space, for tests of readers that must refuse a header's lie before
allocating what it claims (Linux: it reads ``/proc/self/status``)."""

from __future__ import annotations

import contextlib
import re
import resource
from collections.abc import Iterator
from pathlib import Path

HEADROOM = 1 << 30  # bytes a refused read may still map: far below what any lie claims


@contextlib.contextmanager
def address_space_capped(headroom: int = HEADROOM) -> Iterator[None]:
    """Let the process map at most ``headroom`` more bytes while the block runs."""
    status = Path("/proc/self/status").read_text()
    used_kb = int(re.search(r"VmSize:\s+(\d+) kB", status).group(1))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = used_kb * 1024 + headroom
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
