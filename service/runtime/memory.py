"""Giving memory back after a burst.

A burst of input (10,000 messages/s for a few seconds) fills the runner's queue; once it is
drained, the Python objects are freed but the C heap keeps the pages: glibc's ``malloc``
returns memory to the system only from the top of its heaps, and the freed payloads and
queue blocks lie below live data. ``malloc_trim(0)`` releases every free page of every
arena (``madvise(MADV_DONTNEED)``) — what glibc offers for exactly this; elsewhere (musl,
macOS) there is nothing to call and :func:`give_back_heap` says so.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

_libc = None


def _malloc_trim():
    global _libc
    if _libc is None:
        try:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        except OSError:
            _libc = False
    return getattr(_libc, "malloc_trim", None) if _libc else None


def give_back_heap() -> bool:
    """Hand the C heap's free pages back to the system (glibc ``malloc_trim``; a few ms,
    no garbage collection: the queue's items are freed by reference counts). Returns False
    where the C library has no such call."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


class BurstTrimmer:
    """Calls :func:`give_back_heap` once a burst has drained: the queue depth reached
    ``burst_items`` and is back to zero. ``check(depth)`` from a housekeeping loop; True when
    it trimmed."""

    def __init__(self, burst_items: int = 5000) -> None:
        self.burst_items = int(burst_items)
        self.peak = 0

    def check(self, depth: int) -> bool:
        self.peak = max(self.peak, int(depth))
        if self.peak < self.burst_items or depth > 0:
            return False
        self.peak = 0
        done = give_back_heap()
        log.debug("burst drained: heap given back (%s)", "malloc_trim" if done else "not available")
        return done
