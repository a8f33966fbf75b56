"""How a QuakeScan process allocates (glibc only): freed large arrays stay in its heap.

By default glibc maps every block above its mmap threshold (128 KiB, rising with use to at
most 32 MiB) anew and unmaps it when freed; the next array of that size page-faults all its
pages back. Scan batches (~100 MB per thread) and the descriptors of a tile (arrays of
10-240 MB) are freed and allocated again and again. Blocks up to 512 MiB therefore come from
the heap, and up to 2 GiB freed at its top stay there. A process never holds more than it
held at its peak; it only keeps it. A process-wide setting: the command sets it for itself
(`quakescan.cli.main`), and its LocalCluster's workers receive it through their environment
(`ENVIRON`, read by glibc as they start, with one arena for all their threads: a worker's
tasks run in a thread), not the library's callers.
"""
from __future__ import annotations

MMAP_THRESHOLD_BYTES = 512 << 20
TRIM_THRESHOLD_BYTES = 2 << 30
# glibc's names for the same two settings, read once as a process starts, and one setting for
# workers only: a Dask worker runs its tasks in a thread, and glibc gives a thread an arena of
# its own whose heaps hold at most 64 MiB, so every larger array of a tile was mapped anew
# whatever the thresholds said (a 100 MB array: mapped in a thread, kept in the main thread).
# One arena, the main heap, for every thread of a worker: 40 tiles of the 2 x 75 M pair on one
# worker 109.9 -> 101.4 s (126,000 -> 70,000 page faults; 101.0 s in a plain process's main
# thread), measured side by side. Its other threads (event loop, comms) allocate little.
ENVIRON = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES),
           "MALLOC_ARENA_MAX": "1"}


def tune_allocator() -> None:
    """These settings for this process, from now on (glibc only; elsewhere nothing changes)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES)
        libc.mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES)
    except (OSError, AttributeError, TypeError):
        pass  # not glibc: keep the default allocator


def where_an_array_lands(megabytes: int = 100) -> dict:
    """Where glibc puts an array of `megabytes` MB and what it keeps once it is freed, in
    bytes (`mallinfo2`; empty where that is missing): "mapped", the growth of the blocks
    mapped on their own (about the array's size under glibc's defaults, 0 under these
    settings), and "kept", the heap's growth left after freeing it (0 under the defaults,
    about the array's size under these settings). How a process, a worker say, is checked
    to allocate as `tune_allocator` says."""
    import ctypes
    import ctypes.util

    import numpy as np

    class Mallinfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                           "fsmblks", "uordblks", "fordblks", "keepcost")]

    try:
        mallinfo2 = ctypes.CDLL(ctypes.util.find_library("c")).mallinfo2
    except (OSError, AttributeError, TypeError):
        return {}
    mallinfo2.restype = Mallinfo2
    before = mallinfo2()
    array = np.ones(megabytes * 131072)
    held = mallinfo2()
    del array
    after = mallinfo2()
    return {"mapped": held.hblkhd - before.hblkhd, "kept": after.arena - before.arena}
