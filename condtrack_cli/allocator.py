"""The C allocator of a tracking process: large frame-sized arrays reused instead of returned to the system.

Each frame pair allocates and frees dozens of frame-sized float32 arrays
(1242 x 375 x 4 B = 1.9 MB each on KITTI). glibc's malloc serves every block
above its mmap threshold (128 kB, raised only after a block of that size is
freed) with a fresh ``mmap`` and gives it back with ``munmap`` on ``free``, so
every such array costs its pages' faults again (about 2,100 faults a call of the
Q_k field, measured with ``ru_minflt``). :func:`keep_freed_memory` raises the
mmap threshold to ``MMAP_THRESHOLD`` and keeps ``TOP_PAD`` of freed memory in the
heap (trimmed above ``TRIM_THRESHOLD``): the arrays of one frame pair reuse the
pages of the last one. Measured with the same thresholds set through glibc's
MALLOC_*_ environment variables, whole-process wall time, quiet machine, two runs
each (issue 26): 640 x 480 clf 2.98-3.12 -> 2.76-2.92 s, KITTI
seq005 clf 1.75-1.76 -> 1.62-1.64 s, auto unchanged to 0.05 s; peak RSS 12-20 MiB
higher. It changes no value. Only ``condtrack track`` (and its batch jobs) call
it: a notebook's process keeps its own allocator settings.
"""

from __future__ import annotations

import ctypes
import ctypes.util

#: mallopt parameters (glibc's malloc.h) and the values set.
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
MMAP_THRESHOLD = 32 * 2**20
TRIM_THRESHOLD = 256 * 2**20
TOP_PAD = 64 * 2**20


def keep_freed_memory() -> bool:
    """Set the thresholds above (module docstring) with glibc's ``mallopt``; False where there is no glibc."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return False
    settings = ((M_MMAP_THRESHOLD, MMAP_THRESHOLD), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD))
    return all(mallopt(parameter, value) == 1 for parameter, value in settings)
