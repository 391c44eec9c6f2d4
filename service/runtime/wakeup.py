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
power: CPUs that may not sleep deeply draw more while idle (0 µs: they poll). Two scopes:

- ``always``: the bound from start to stop;
- ``epochs``: only around each output epoch, the one IMU sample a client waits for — from the
  moment its rehearsal is planned (:mod:`adaptnav.service.runtime.rehearsal`: the IMU sample
  before it has run) to ``hold_after_s`` after it is expected (:meth:`~WakeupLatencyRequest.tighten`,
  :meth:`~WakeupLatencyRequest.relax`); between epochs the request stays open at the kernel's
  "no bound". At 10 Hz outputs and a 100 Hz IMU that is ~14 ms in 100 (200 Hz: ~9). Changing
  the bound makes the kernel kick every idle CPU to choose its idle state again, so tightening
  also wakes them ahead of the sample.

The daemon's default is 0 µs around the epochs (``outputs.cpu_wakeup_latency_us``,
``outputs.cpu_wakeup_scope``). The file is root's; refused (no permission, no such device), the
daemon logs it once, reports it in its health (``cpu_wakeup_latency``) and runs on without it.
"""
from __future__ import annotations

import logging
import os
import struct
import threading
from collections import Counter

log = logging.getLogger(__name__)

PM_QOS_DEVICE = "/dev/cpu_dma_latency"
NO_BOUND_US = 2_000_000_000  # the kernel's value for "no bound" (PM_QOS_CPU_LATENCY_DEFAULT_VALUE)
SCOPES = ("always", "epochs")


class WakeupLatencyRequest:
    """Hold a CPU wake-up latency bound of ``max_us`` µs (module docstring) from :meth:`hold`
    until :meth:`release`, all along (``scope`` "always") or between :meth:`tighten` and
    :meth:`relax` ("epochs"). ``device``: the PM QoS file (another path only in tests)."""

    def __init__(self, max_us: int, scope: str = "always", device: str | None = None) -> None:
        if type(max_us) is not int or max_us < 0:  # (the kernel takes a 32-bit signed count)
            raise ValueError(f"max_us must be a non-negative integer, got {max_us!r}")
        if max_us >= NO_BOUND_US:
            raise ValueError(f"max_us must be below {NO_BOUND_US} µs (the kernel's no bound), got {max_us!r}")
        if scope not in SCOPES:
            raise ValueError(f"scope must be one of {SCOPES}, got {scope!r}")
        self.max_us = max_us
        self.scope = scope
        self.device = PM_QOS_DEVICE if device is None else device
        self._fd: int | None = None
        self.tight = False  # the bound applies now
        self.error: str | None = None  # why the request could not be made
        self.counts: Counter[str] = Counter({"tightened": 0, "write_failed": 0})
        self._lock = threading.Lock()  # tightened by the runner's thread, relaxed by the rehearsal's

    @property
    def held(self) -> bool:
        return self._fd is not None

    def hold(self) -> bool:
        """Make the request (scope "epochs": at no bound until :meth:`tighten`); False (and
        :attr:`error` says why, logged once) when the kernel refused it. Idempotent."""
        if self._fd is not None:
            return True
        fd = None
        try:
            fd = os.open(self.device, os.O_WRONLY | os.O_CLOEXEC)
            _write_bound(fd, self.max_us if self.scope == "always" else NO_BOUND_US)
        except OSError as e:
            if fd is not None:
                os.close(fd)
            self.error = f"{type(e).__name__}: {e.strerror or e}"
            # (the default asks for it; not root is no fault of the service's: the health says so)
            log.info("CPU wake-up latency bound of %d µs not held (%s): idle CPUs may wake slowly",
                     self.max_us, self.error)
            return False
        self._fd, self.error, self.tight = fd, None, self.scope == "always"
        log.info("CPU wake-up latency bound: %d µs, %s (%s)", self.max_us,
                 "held" if self.scope == "always" else "around each output epoch", self.device)
        return True

    def tighten(self) -> None:
        """Scope "epochs": the bound applies from now (an output epoch is near). Nothing
        otherwise, or when it already applies."""
        if self.scope == "epochs" and not self.tight:
            with self._lock:
                if not self.tight and self._fd is not None:
                    self._set(self.max_us)
                    self.tight = self._fd is not None
                    self.counts["tightened"] += self.tight

    def relax(self) -> None:
        """Scope "epochs": back to no bound (the epoch is past)."""
        if self.scope == "epochs" and self.tight:
            with self._lock:
                if self.tight and self._fd is not None:
                    self._set(NO_BOUND_US)
                    self.tight = False

    def _set(self, us: int) -> None:
        try:
            _write_bound(self._fd, us)
        except OSError as e:  # (never seen: the open file was writable) the request is dropped
            self.counts["write_failed"] += 1
            self.error = f"{type(e).__name__}: {e.strerror or e}"
            log.warning("CPU wake-up latency bound dropped: %s", self.error)
            self.release()

    def release(self) -> None:
        """Drop the request (closing the file is what drops it). Idempotent."""
        fd, self._fd, self.tight = self._fd, None, False
        if fd is not None:
            os.close(fd)

    def report(self) -> dict:
        """For the health report: the bound asked for, its scope, whether it is held, why not,
        how often an epoch's window tightened it."""
        return {"max_us": self.max_us, "scope": self.scope, "held": self.held, "error": self.error,
                "tightened": self.counts["tightened"]}


def _write_bound(fd: int, us: int) -> None:
    # the binary form, a native int32 (the kernel also reads hex text, not decimal)
    if os.write(fd, struct.pack("=i", us)) != 4:
        raise OSError("short write")


def current_bound_us(device: str = PM_QOS_DEVICE) -> int:
    """The bound the kernel applies now (the tightest request held by any process;
    :data:`NO_BOUND_US` without any): read from the same file."""
    fd = os.open(device, os.O_RDONLY | os.O_CLOEXEC)
    try:
        return struct.unpack("=i", os.read(fd, 4))[0]
    finally:
        os.close(fd)
