"""Rehearsal of the live output epoch: the epoch's path run just before its IMU sample comes.

Live at 100 Hz the daemon runs the held samples in one burst at the IMU sample before an
output epoch's (:class:`adaptnav.service.daemon.LiveBurst`), then sleeps an IMU period. The
epoch's own sample — the one a client waits for — then finds the interpreter's and the filter's
code and data gone from the caches: on a shared 2-core virtual machine its decode → ``put``
took 0.34–0.39 ms (p50) against ~0.07 ms back to back.

:class:`EpochRehearsal` plans, after the sample before an epoch's ran, a rehearsal ``lead_s``
before the epoch's sample is expected (that sample's arrival + one IMU period), and runs it in
its own thread under the runner lock: the estimator's :meth:`~adaptnav.fusion.eskf.Estimator.rehearse_epoch`
(the sample's compiled steps on a scratch copy, the published state computed) and the nav
state's message built, not sent. Nothing of the filter changes, and nothing is published: the
states are the same, bit for bit, with or without it. Timed across the outside client's and
the daemon's processes at 100 Hz (alternated windows; docs/measurements.md, stop 40): decode →
``put`` p50 0.32–0.39 → 0.21–0.26 ms; ~0.3 ms of CPU per epoch.

With a ``window`` (:class:`adaptnav.service.runtime.wakeup.WakeupLatencyRequest` of scope
"epochs"), idle CPUs are also kept quick to wake from the moment a rehearsal is planned (the
sample before the epoch's has run) to ``hold_after_s`` after the epoch's sample is expected: the
sample and the nav state it makes find the CPUs quick to wake, and between epochs they may sleep
deeply.

A rehearsal that would start more than half its lead late is skipped (``late``: it could still
hold the lock when the sample comes), and so is one that finds the runner busy (``busy``); the
counts are in the health report (``epoch_rehearsal``). An epoch's sample that comes while a
rehearsal holds the lock waits for it (it is short) instead of going to the runner thread.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from typing import Any, Callable

log = logging.getLogger(__name__)


class EpochRehearsal:
    """Plans and runs the rehearsals (module docstring).

    ``lock``: the runner lock; ``rehearse(dt_s)``: the rehearsal of a sample ``dt_s`` after the
    state time, False when there was nothing to rehearse (no navigation yet); ``lead_s``: how
    long before the epoch's sample is expected; ``clock``: the monotonic clock (s); ``window``:
    ``tighten()`` when a rehearsal is planned, ``relax()`` ``hold_after_s`` after the sample is
    expected (module docstring)."""

    def __init__(self, lock: Any, rehearse: Callable[[float], Any], lead_s: float,
                 clock: Callable[[], float] = time.monotonic, window: Any = None,
                 hold_after_s: float = 0.0035) -> None:
        if not lead_s > 0.0:
            raise ValueError(f"lead_s must be > 0, got {lead_s!r}")
        if not 0.0 < hold_after_s <= 0.05:
            raise ValueError(f"hold_after_s must be within (0, 0.05] s, got {hold_after_s!r}")
        self.window = window
        self.hold_after_s = float(hold_after_s)
        self.lock = lock
        self.rehearse = rehearse
        self.lead_s = float(lead_s)
        self.clock = clock
        self.counts: Counter[str] = Counter()  # outcomes (run_due), no_room (plan)
        self.holding = False  # a rehearsal holds the runner lock
        self._plan: tuple[float, float] | None = None  # (monotonic time to run at, dt_s)
        self._cond = threading.Condition()
        self._stopped = False
        self._thread: threading.Thread | None = None

    def plan(self, arrived_s: float, t_s: float, loop: Any) -> bool:
        """The IMU sample at data time ``t_s``, come at monotonic ``arrived_s``, has run: when
        the next one completes ``loop``'s next epoch (:class:`adaptnav.service.runtime.runner._Loop`),
        plan its rehearsal ``lead_s`` before it is expected (one IMU period after this one),
        replacing any plan not run yet. Not when that leaves less than ``lead_s`` from now
        (an IMU faster than that: the rehearsal would meet the sample). True when planned."""
        period = loop.imu_period_s
        if loop.next_k is None or not period > 0.0 or not t_s < loop.due_s() <= t_s + 1.5 * period:
            return False
        at = arrived_s + period - self.lead_s
        if at - self.clock() < self.lead_s:
            self.counts["no_room"] += 1
            return False
        if self.window is not None:
            # from now, not from the rehearsal's timer: that timer wakes a CPU that may be asleep
            # deeply (at 100 Hz, late more often), this thread is running now
            self.window.tighten()
        with self._cond:
            self._plan = (at, period)
            self._cond.notify()
        return True

    def run_due(self) -> str | None:
        """Run the planned rehearsal if its time has come: its outcome (``done``, ``not_ready``,
        ``late``, ``busy``, ``failed``), None when there is none to run yet."""
        with self._cond:
            if self._plan is None or self.clock() < self._plan[0]:
                return None
            (at, dt_s), self._plan = self._plan, None
        if self.clock() > at + 0.5 * self.lead_s:
            outcome = "late"
        elif not self.lock.acquire(blocking=False):
            outcome = "busy"
        else:
            self.holding = True
            try:
                outcome = "done" if self.rehearse(dt_s) else "not_ready"
            except Exception:  # noqa: BLE001 — a rehearsal must never cost the service anything
                if not self.counts["failed"]:
                    log.exception("epoch rehearsal failed (logged once; counted in the health report)")
                outcome = "failed"
            finally:
                self.holding = False
                self.lock.release()
        self.counts[outcome] += 1
        return outcome

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="adaptnav-rehearsal", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def _run(self) -> None:
        window, relax_at = self.window, math.inf  # (monotonic s: the open window's end)
        try:
            while True:
                with self._cond:
                    while not self._stopped:
                        due_at = self._plan[0] if self._plan is not None else math.inf
                        wait_s = min(due_at, relax_at) - self.clock()
                        if wait_s <= 0.0:
                            break
                        # a new plan or the stop wakes it sooner
                        self._cond.wait(None if wait_s == math.inf else wait_s)
                    if self._stopped:
                        return
                now = self.clock()
                if relax_at <= now:
                    window.relax()
                    relax_at = math.inf
                if due_at <= now:
                    if window is not None:
                        window.tighten()  # (tightened when planned; again if it was relaxed since)
                        relax_at = due_at + self.lead_s + self.hold_after_s
                    self.run_due()
        finally:
            if window is not None:
                window.relax()
