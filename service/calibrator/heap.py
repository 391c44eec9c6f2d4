"""The calibrator process's heap: freed memory kept for the next EM iteration.

An EM iteration allocates its particle arrays afresh (N = 1000, T = 100: the cloud
2.4 MB, the move normals 3.6 MB, weights and ancestors 1.6 MB) and frees them at its end.
glibc's malloc hands such blocks back to the kernel (blocks above its mmap threshold are
unmapped; a free top of the heap above 128 kB is trimmed), so the next iteration took
every page again: 1830 page faults per particle filter, half of its time (8 against
4 ms here). :func:`keep_freed_heap` raises both thresholds in a process whose work is EM
iterations (the calibrator child, the calibrator node; ``adaptnav bench calibration``
measures as they run): the arrays come from the heap and stay mapped between iterations,
at the cost of up to :data:`TRIM_THRESHOLD_BYTES` of freed memory kept resident.

Only the calibrator's processes: the daemon's allocations are small and steady.
"""
from __future__ import annotations

import ctypes
import logging

log = logging.getLogger(__name__)

# mallopt(3) parameter numbers (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# blocks up to this size come from the heap (the EM's largest array is 2.4 MB at
# N = 1000, T = 100); larger ones are still mapped and unmapped as they come and go
MMAP_THRESHOLD_BYTES = 16 << 20
# freed memory at the top of the heap kept up to this size (an EM iteration's arrays, ~8 MB)
TRIM_THRESHOLD_BYTES = 32 << 20


def keep_freed_heap() -> bool:
    """Raise glibc malloc's mmap and trim thresholds in this process (see the module
    docstring). False, changing nothing, where the C library has no ``mallopt`` (musl,
    macOS) or refuses the values."""
    try:
        # the symbols already loaded in this process (the C library's among them); not
        # ctypes.util.find_library, which starts ldconfig or a compiler to find a name
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        log.debug("no mallopt in the C library: the heap is left as it is")
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success, 0 on error
    ok = (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
          and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1)
    if not ok:
        log.debug("mallopt refused the heap thresholds: the heap is left as it is")
    return ok
