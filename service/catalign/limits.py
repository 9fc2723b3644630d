"""Sizes more than one layer agrees on, and the process limits a served library needs.

A library entry must be describable as a query would be, so the least number of occupied voxels
a query needs is also the least a library model may have; both read it here.
"""

# Occupied voxels a query (and a library model) needs: fewer leave too little to describe.
MIN_VOXELS = 50


def raise_open_files_limit(wanted: int) -> int:
    """Raise this process's soft limit on open files towards ``wanted`` (never past the hard
    limit, never lowering it); the soft limit in effect after."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= wanted:
        return wanted if soft == resource.RLIM_INFINITY else soft
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if target > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return max(target, soft)


def max_memory_maps() -> int | None:
    """How many memory maps a process may hold (Linux ``vm.max_map_count``); None elsewhere."""
    try:
        return int(open("/proc/sys/vm/max_map_count").read())
    except (OSError, ValueError):
        return None
