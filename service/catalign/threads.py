"""Thread pools of the numeric libraries, sized once for the server's worker threads.

Each registration worker runs torch, numpy/scipy (OpenBLAS), OpenMP loops and Open3D (oneTBB).
Left alone, every one of them starts a pool as large as the machine, so N workers on N cores run
N times as many threads as cores and slow each other down. :func:`limit_threads` runs once in
each worker thread: OpenMP's limit is per calling thread, torch's and the BLAS libraries' are
process-wide (the same value in every worker), and Open3D's TBB limit counts every thread of the
process, so it is given the workers' total.
"""

from __future__ import annotations

import os
import threading


def cores() -> int:
    """Cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_threads_per_worker(workers: int) -> int:
    """An even share of the cores for each of ``workers`` workers, at least one thread."""
    return max(1, cores() // max(1, workers))


def limit_threads(threads: int, total: int, niceness: int = 0) -> None:
    """Use ``threads`` threads in this worker (torch, OpenMP, BLAS) and ``total`` in Open3D, and
    run this thread ``niceness`` steps below the process's priority."""
    if niceness:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    import open3d
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(threads)
    threadpool_limits(limits=threads)  # applied now and kept (not used as a context manager)
    open3d.utility.set_max_threads(total)
