"""A bound on how long an idle CPU takes to wake, held while the live daemon runs (Linux PM QoS).

An idle CPU sleeps in the deepest idle state whose exit latency the kernel's cpuidle governor
thinks it can afford. An IMU sample that arrives then waits for the CPU to come back before
Zenoh's receiving thread runs, and again for the nav state to leave: a cost paid only when the
CPUs were idle, so more often at 100 Hz than at 200 Hz — the "slow mode that tracks the IMU
period" of issue 17. On a virtual machine an idle vCPU halts out to the hypervisor, and waking it
waits for the host's scheduler (this machine, a Firecracker guest with ``haltpoll`` and guest
halt-polling off: a plain Zenoh echo at 100 Hz, 60 s windows, p99 1.68 / 2.02 ms with the CPUs
free to halt, 0.87 / 1.05 ms with this request at 0 µs); x86 companion computers' deep C-states
cost 50–200 µs each; a Raspberry Pi's only idle state (WFI) costs about nothing, and the request
changes nothing there.

:class:`WakeupLatencyRequest` writes the bound (µs) to ``/dev/cpu_dma_latency`` and keeps the file
open: the kernel holds the request while it is open and drops it when it is closed — at
:meth:`~WakeupLatencyRequest.release` or when the process ends, however it ends. The price is
power: CPUs that may not sleep deeply draw more while idle (0 µs: they poll). The file is
root's; refused (no permission, no such device), the daemon logs it once, reports it in its
health (``cpu_wakeup_latency``) and runs on without it.
"""
from __future__ import annotations

import logging
import os
import struct

log = logging.getLogger(__name__)

PM_QOS_DEVICE = "/dev/cpu_dma_latency"


class WakeupLatencyRequest:
    """Hold a CPU wake-up latency bound of ``max_us`` µs (module docstring) from :meth:`hold`
    until :meth:`release`. ``device``: the PM QoS file (another path only in tests)."""

    def __init__(self, max_us: int, device: str = PM_QOS_DEVICE) -> None:
        if type(max_us) is not int or max_us < 0:  # (the kernel takes a 32-bit signed count)
            raise ValueError(f"max_us must be a non-negative integer, got {max_us!r}")
        if max_us > 2**31 - 1:
            raise ValueError(f"max_us must be below 2**31 µs, got {max_us!r}")
        self.max_us = max_us
        self.device = device
        self._fd: int | None = None
        self.error: str | None = None  # why the request could not be made

    @property
    def held(self) -> bool:
        return self._fd is not None

    def hold(self) -> bool:
        """Make the request; False (and :attr:`error` says why, logged once) when the kernel
        refused it. Idempotent."""
        if self._fd is not None:
            return True
        fd = None
        try:
            fd = os.open(self.device, os.O_WRONLY | os.O_CLOEXEC)
            # the binary form, a native int32 (the kernel also reads hex text, not decimal)
            if os.write(fd, struct.pack("=i", self.max_us)) != 4:
                raise OSError("short write")
        except OSError as e:
            if fd is not None:
                os.close(fd)
            self.error = f"{type(e).__name__}: {e.strerror or e}"
            log.warning("CPU wake-up latency bound of %d µs not held (%s): idle CPUs may wake slowly",
                        self.max_us, self.error)
            return False
        self._fd, self.error = fd, None
        log.info("CPU wake-up latency bound held: %d µs (%s)", self.max_us, self.device)
        return True

    def release(self) -> None:
        """Drop the request (closing the file is what drops it). Idempotent."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def report(self) -> dict:
        """For the health report: the bound asked for, whether it is held, why not."""
        return {"max_us": self.max_us, "held": self.held, "error": self.error}


def current_bound_us(device: str = PM_QOS_DEVICE) -> int:
    """The bound the kernel applies now (the tightest request held by any process; 2 000 000 000
    µs without any): read from the same file."""
    fd = os.open(device, os.O_RDONLY | os.O_CLOEXEC)
    try:
        return struct.unpack("=i", os.read(fd, 4))[0]
    finally:
        os.close(fd)
