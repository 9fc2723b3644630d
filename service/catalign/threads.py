"""Thread pools of the numeric libraries, sized once for the server's worker threads.

Each registration worker runs torch, numpy/scipy (OpenBLAS), OpenMP loops and Open3D (oneTBB).
Left alone, every one of them starts a pool as large as the machine, so N workers on N cores run
N times as many threads as cores and slow each other down. :func:`limit_threads` runs once in
each worker thread: OpenMP's limit is per calling thread, torch's and the BLAS libraries' are
process-wide (the same value in every worker), and Open3D's TBB limit counts every thread of the
process, so it is given the workers' total. BLAS gets one thread whatever the share: the
engine's products are small, and OpenBLAS's idle threads spin on the core that torch's next
parallel loop needs (two BLAS threads measured 276 against 204 ms at the 95th percentile of
a query, ``bench/latency.py``'s views, the median 0.98x). :func:`limit_malloc_arenas` keeps
glibc from giving every thread that allocates (workers, the body decoders) a heap of its own,
and :func:`release_free_memory` hands the pages it holds free back to the system after a library
change.
"""

from __future__ import annotations

import ctypes
import functools
import math
import os
import threading
from pathlib import Path

_M_ARENA_MAX = -8  # glibc's mallopt parameter number
# The thread budget :func:`limit_threads` gave this process's workers (None: not limited).
_budget: int | None = None


def cores() -> int:
    """Cores this process may use: its CPU affinity (not the machine's count), capped by the
    container's CPU limit (:func:`cgroup_cpu_limit`)."""
    try:
        allowed = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        allowed = os.cpu_count() or 1
    limit = cgroup_cpu_limit()
    return max(1, min(allowed, limit)) if limit is not None else allowed


def cgroup_cpu_limit(root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """The CPU limit of this process's cgroup in whole CPUs (quota / period, rounded up), or None
    when there is none or it cannot be read.

    cgroup v2: ``root/cpu.max`` holds ``"<quota> <period>"`` in microseconds, ``"max <period>"``
    when unlimited. cgroup v1: ``root/cpu/cpu.cfs_quota_us`` (-1 when unlimited) and
    ``cpu.cfs_period_us`` (also under ``cpu,cpuacct/``). A Kubernetes CPU limit of 2 reads
    ``200000 100000``: 2. Only ``root`` itself is read, which is the container's own cgroup
    under a cgroup namespace (Docker and Kubernetes on cgroup v2) or a v1 bind mount; limits set
    on an ancestor cgroup only (a bare process under systemd) are not seen.
    """
    candidates = [(root / "cpu.max", None)] + [
        (root / folder / "cpu.cfs_quota_us", root / folder / "cpu.cfs_period_us")
        for folder in ("cpu", "cpu,cpuacct", "cpuacct,cpu")
    ]
    for quota_file, period_file in candidates:
        try:
            if period_file is None:
                quota, _, period = quota_file.read_text().strip().partition(" ")
            else:
                quota, period = quota_file.read_text().strip(), period_file.read_text().strip()
        except (OSError, UnicodeDecodeError):
            continue
        if quota in ("max", "-1"):
            return None
        try:
            quota_us, period_us = int(quota), int(period or 100_000)
        except ValueError:
            return None
        if quota_us <= 0 or period_us <= 0:
            return None
        return math.ceil(quota_us / period_us)
    return None


def worker_threads() -> int:
    """Threads a worker's own parallel loops may use (ICP's): the budget :func:`limit_threads`
    gave the workers, else ``OMP_NUM_THREADS`` when it is a positive number, else every core,
    as torch's default."""
    if _budget is not None:
        return _budget
    try:
        return max(1, int(os.environ.get("OMP_NUM_THREADS", "")))
    except ValueError:
        return _cores_at_start()


@functools.cache
def _cores_at_start() -> int:
    """:func:`cores`, read once: ICP asks at every pass, and the affinity and the cgroup's
    files do not change under a running process."""
    return cores()


def default_threads_per_worker(workers: int) -> int:
    """An even share of the cores for each of ``workers`` workers, at least one thread."""
    return max(1, cores() // max(1, workers))


def limit_malloc_arenas(arenas: int) -> bool:
    """Let glibc's malloc keep at most ``arenas`` heaps (``M_ARENA_MAX``); False off glibc.

    Each arena reserves 64 MB of address space and keeps freed memory for its thread. Measured
    on the server with its heaviest request: 1.91 GB of address space at the peak by default,
    1.6 GB with two arenas, the same time and resident memory.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_ARENA_MAX, arenas))
    except (OSError, AttributeError):
        return False


def release_free_memory() -> bool:
    """Return the free pages of glibc's heaps to the system (``malloc_trim``); whether any were
    returned, False off glibc.

    glibc keeps what is freed in the middle of a heap for later allocations. A library change
    frees the old engine with its per-model caches (and, in the server, what describing an
    upload used), and what is built next lands elsewhere, so resident memory would creep up with
    each library version. Measured with the default library: the server process after 25 uploads
    and removals held 603 MiB without this and 516 MiB with it; one engine registering 8 views per
    library version held 640 MiB after 30 versions without it and 586 MiB with it, flat from
    the fourth version on.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.malloc_trim(0))
    except (OSError, AttributeError):
        return False


def limit_threads(threads: int, total: int, niceness: int = 0) -> None:
    """Use ``threads`` threads in this worker (torch, OpenMP), one for BLAS (module docstring)
    and ``total`` in Open3D, and run this thread ``niceness`` steps below the process's
    priority."""
    global _budget
    _budget = threads
    if niceness:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    import open3d
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(threads)
    # Applied now and kept (not used as context managers).
    threadpool_limits(limits=threads, user_api="openmp")
    threadpool_limits(limits=1, user_api="blas")
    open3d.utility.set_max_threads(total)
