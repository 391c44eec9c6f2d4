"""The daemon's calibrator: :class:`CalibratorProcess`, a supervised *spawn* child running
:class:`adaptnav.calibration.online.OnlineCalibrator` (DESIGN.md "Service": fusion must
never wait for EM, 2 cores).

What the runner sees as its ``calibrator``: ``observe(sample)`` forwards the sample to the
child without blocking (batched; a full queue drops and counts — EM can afford a gap,
fusion cannot afford a stall); a reader thread takes the child's releases (stamped with
the data time τ they were computed at) and holds them; ``poll(data_time_s)`` hands over
those due by the release rule (:mod:`adaptnav.service.calibrator.lagged`): once the runner's
data time reaches ``τ + L``. The runner never waits: a release that comes back later
than ``τ + L`` (EM slower than real time) is applied at the first poll after it arrives,
and counted (:meth:`CalibratorProcess.late_report`, health ``calibrator.late``): such a run is
not what a replay of its log gives, which waits for every release.
That is the one route of a release into the runner, the child's, a remote node's
(:class:`adaptnav.service.calibrator.node.RemoteCalibrator`) and replay's
(:class:`adaptnav.service.calibrator.lagged.LaggedCalibrator`) alike.

:meth:`CalibratorProcess.supervise` (called periodically by the daemon) restarts a dead
child with exponential backoff, warm-started from the latest accepted params.
"""
from __future__ import annotations

import gc
import logging
import math
import multiprocessing as mp
import os
import queue
import threading
import time
from collections import Counter, deque
from typing import Any

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.calibrator.heap import keep_freed_heap
from adaptnav.service.calibrator.signals import ignore_sigint, start_ignoring_sigint
from adaptnav.service.calibrator.batching import DataClock, compact_imu, split_due
from adaptnav.service.calibrator.lagged import child_message, limit_child_threads, side_scan_report
from adaptnav.service.compose import make_calibrator
from adaptnav.service.transport.release import release_from_dict

log = logging.getLogger(__name__)

_STOP = "__stop__"
_SHIFT = "__shift__"


def die_with_parent(parent_pid: int) -> None:
    """Make this (child) process end when its parent does, even a SIGKILLed parent that
    cannot stop it: Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)``; if the parent is already
    gone (it died before the call), exit now. Elsewhere nothing (the child's pipes end)."""
    import os
    import sys

    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    PR_SET_PDEATHSIG = 1
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:  # pragma: no cover
        return
    if os.getppid() != parent_pid:
        os._exit(0)


def _child_main(cfg: Any, params0: MotionParams, seed: int, in_q: Any, out_q: Any,
                parent_pid: int | None = None) -> None:
    """Child process: observe samples, send releases back; exits on ``_STOP``."""
    ignore_sigint()
    if parent_pid is not None:  # dies with its daemon, even a SIGKILLed one
        die_with_parent(parent_pid)
    if cfg.calibrator.nice > 0:
        os.nice(cfg.calibrator.nice)  # raising the niceness needs no privilege
    keep_freed_heap()  # the EM's arrays stay mapped between iterations (heap.py)
    calibrator = make_calibrator(cfg, params0, seed)
    clock = DataClock()
    gc.freeze()  # the imported modules stay out of the collector's full passes (as in replay)
    last_side_scan = None
    out_q.put(("ready", None, None))
    while True:
        try:
            batch = in_q.get(timeout=0.5)
        except queue.Empty:
            batch = []
        if isinstance(batch, str) and batch == _STOP:
            return
        for sample in batch:
            if type(sample) is tuple:  # (_SHIFT, Δ): the runner re-based a clock jump
                clock.tau += sample[1]
                out_q.put(("shifted", None, sample[1]))
                continue
            calibrator.observe(sample)
            tau = clock.advance(sample)
            for release in calibrator.poll():  # stamped with the data time it was computed at
                out_q.put(child_message(release, tau))
        if batch:
            # the object front end's counts for the daemon's health, when they changed
            report = side_scan_report(calibrator)
            if report is not None and report != last_side_scan:
                out_q.put(("side_scan", report, None))
                last_side_scan = report



class CalibratorProcess:
    """Supervised calibrator child process with the calibrator interface of the runner.

    Parameters
    ----------
    cfg : ServiceConfig
        Whole config (the child needs ``calibrator`` and ``motion``).
    params0 : MotionParams
        Warm start.
    batch_s : float
        Samples are sent to the child in batches at most this old (wall seconds), which
        keeps inter-process overhead off the fusion thread.
    """

    def __init__(self, cfg: Any, params0: MotionParams, batch_s: float = 0.05) -> None:
        self.cfg = cfg
        self.params = params0
        self.latency_s = float(getattr(cfg.calibrator, "latency_s", 0.0))
        # side products (side-scan objects for the filter) are due sooner (config.CalibratorSection)
        self.product_latency_s = min(float(getattr(cfg.calibrator, "product_latency_s", self.latency_s)),
                                     self.latency_s)
        self._held: deque = deque()   # (τ, release) from the reader thread, oldest first
        self.batch_s = batch_s
        self.dropped = 0
        self.restarts = 0
        self.state = "stopped"
        self.counters: Counter[str] = Counter()
        self.side_scan: dict | None = None  # the child's object front end's counts, latest
        # outputs that came back after the runner's data time had passed their due time
        # (τ + L, τ + L_p): applied at the next poll, later than the rule, so a replay of the
        # log (which waits for them) does not reproduce this run; by kind, and the largest
        # lateness in data seconds (:meth:`late_report`)
        self.late: Counter[str] = Counter()
        self.late_max_s = 0.0
        self._late_logged_s = 0.0
        self._data_time_s = -math.inf  # the runner's, at its last poll (read by the reader thread)
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._in_q: Any = None
        self._out_q: Any = None
        self._reader: threading.Thread | None = None
        self._batch: list[Any] = []
        self._batch_t0 = 0.0
        self._backoff_s = cfg.calibrator.restart_backoff_s
        self._next_start = 0.0
        self._started_at = 0.0
        self._closed = False
        self._lock = threading.Lock()
        self._held_lock = threading.Lock()  # the reader appends, shift_time() re-bases
        self.received = 0   # releases that came back from the child (any restart)
        self._shift_to_send_s = 0.0  # a clock shift not yet sent to the child (rides the next batch)
        self._unacked_shift_s = 0.0  # shifts sent the child has not confirmed: its τ lags by them
        self._running = threading.Event()

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        with self._lock:
            self._spawn()

    def _spawn(self) -> None:
        limit_child_threads()
        seed = self.cfg.calibrator.seed + self.restarts
        self._in_q = self._ctx.Queue(maxsize=max(1, self.cfg.calibrator.queue_size // 10))
        self._out_q = self._ctx.Queue()
        self._proc = self._ctx.Process(target=_child_main, name="adaptnav-calibrator", daemon=True,
                                       args=(self.cfg, self.params, seed, self._in_q, self._out_q, os.getpid()))
        start_ignoring_sigint(self._proc)
        self._started_at = time.monotonic()
        with self._held_lock:  # a new child's data clock starts in the current time base
            self._shift_to_send_s = self._unacked_shift_s = 0.0
        self.state = "starting"
        self._running.clear()
        self._reader = threading.Thread(target=self._read, args=(self._out_q, self._proc),
                                        name="calibrator-reader", daemon=True)
        self._reader.start()
        log.info("calibrator process started (pid %s)", self._proc.pid)

    def _read(self, out_q: Any, proc: Any) -> None:
        while not self._closed:
            try:
                msg = out_q.get(timeout=0.2)
                kind, body = msg[0], msg[1]
            except queue.Empty:
                if not proc.is_alive():
                    return
                continue
            except (EOFError, OSError):
                return
            if kind == "ready":
                self.state = "running"
                self._running.set()
            elif kind == "release":
                try:
                    release = release_from_dict(body)
                except ValueError as e:
                    self.counters["bad_release"] += 1
                    log.warning("calibrator sent a bad release: %s", e)
                    continue
                if release.accepted and release.params is not None:
                    self.params = release.params  # warm start of a restart
                tau = msg[2] if len(msg) > 2 and msg[2] is not None else -math.inf
                with self._held_lock:  # stamped before a shift the child had not seen: re-based here
                    tau = float(tau) + self._unacked_shift_s + self._shift_to_send_s
                    self._held.append((tau, release))
                self._count_late("releases", tau + self.latency_s)
                self.received += 1
            elif kind == "product":  # side-scan objects for the filter: the release rule too
                tau = msg[2] if msg[2] is not None else -math.inf
                with self._held_lock:
                    tau = float(tau) + self._unacked_shift_s + self._shift_to_send_s
                    self._held.append((tau, body))
                self._count_late("products", tau + self.product_latency_s)
            elif kind == "shifted":
                with self._held_lock:
                    self._unacked_shift_s -= float(msg[2])
            elif kind == "side_scan":  # the object front end's counts (health)
                self.side_scan = body

    def _count_late(self, kind: str, due_s: float) -> None:
        """An output due at data time ``due_s`` has come back: late when the runner's data
        time had already passed it (its next poll hands it over, after the rule's time)."""
        late_s = self._data_time_s - due_s
        if 0.0 < late_s < math.inf:  # (an output with no data time behind it, τ = −∞, is not late)
            self.late[kind] += 1
            if late_s > self.late_max_s:
                # said when it first happens and whenever it doubles: a few lines, however long
                if late_s >= 2.0 * self._late_logged_s:
                    self._late_logged_s = late_s
                    log.warning("calibrator behind: %s back %.1f s of data after its due time (%d late so "
                                "far); the solution is not what a replay of this log gives", kind[:-1], late_s,
                                self.late["releases"] + self.late["products"])
                self.late_max_s = late_s

    def late_report(self) -> dict:
        """Health's ``calibrator.late``: releases and side products that came back after their
        due time, and the largest lateness (data s). Zero while the child keeps up; otherwise
        their effect on the solution came later than a replay of the log applies it."""
        return {"releases": int(self.late["releases"]), "products": int(self.late["products"]),
                "max_s": round(self.late_max_s, 3)}

    def wait_running(self, timeout_s: float) -> bool:
        """Block until the child has said it is ready (True) or ``timeout_s`` passed."""
        return self._running.wait(timeout_s)

    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def supervise(self) -> None:
        """Restart a dead child (exponential backoff); call periodically."""
        if self._closed or self.alive():
            if self.alive() and time.monotonic() - self._started_at > 60.0:
                self._backoff_s = self.cfg.calibrator.restart_backoff_s  # stable again
            return
        now = time.monotonic()
        with self._lock:
            if self.state != "restarting":
                code = self._proc.exitcode if self._proc is not None else None
                log.warning("calibrator process died (exit code %s); restarting in %.1f s",
                            code, self._backoff_s)
                self.state = "restarting"
                self._next_start = now + self._backoff_s
                self._backoff_s = min(2.0 * self._backoff_s, self.cfg.calibrator.restart_backoff_max_s)
                self._discard_queues()
                return
            if now >= self._next_start:
                self.restarts += 1
                self._spawn()

    def _discard_queues(self) -> None:
        for q in (self._in_q, self._out_q):
            if q is not None:
                q.cancel_join_thread()  # never block exit on a dead reader
                q.close()
        self._in_q = None
        self._batch.clear()

    # -- runner interface -----------------------------------------------------------------
    def observe(self, sample: Any) -> None:
        """Forward ``sample`` to the child (batched, never blocking)."""
        if self._in_q is None:
            self.dropped += 1
            return
        if not self._batch:
            self._batch_t0 = time.monotonic()
        self._batch.append(sample)
        if time.monotonic() - self._batch_t0 >= self.batch_s or len(self._batch) >= 500:
            self.flush()

    def flush(self) -> None:
        if not (self._batch or self._shift_to_send_s) or self._in_q is None:
            return
        shift = self._shift_to_send_s
        items = compact_imu(self._batch)
        if shift:  # first in the batch: it applies after the samples sent before it
            items.insert(0, (_SHIFT, shift))
        try:
            self._in_q.put_nowait(items)
        except (queue.Full, ValueError, OSError):
            self.dropped += len(self._batch)  # the shift stays pending for the next batch
        else:
            if shift:
                with self._held_lock:
                    self._shift_to_send_s -= shift
                    self._unacked_shift_s += shift
        self._batch = []

    def shift_time(self, delta_s: float) -> None:
        """The runner confirmed a jump of the input's clock by ``delta_s`` (its data time
        moves with it): the τ of the held releases and the child's own data clock move too
        (the child's with its next batch), so a release after a backward jump comes ``L``
        after its data, not once the data has caught up with the old time base."""
        with self._held_lock:
            self._held = deque((tau + delta_s, rel) for tau, rel in self._held)
            self._shift_to_send_s += delta_s
            self._data_time_s += delta_s

    def poll(self, data_time_s: float) -> list:
        """The held releases with ``τ + L ≤ data_time_s`` (the runner's data time) and side
        products with ``τ + L_p ≤ data_time_s``, oldest first."""
        # the runner polls after every sample: flushing here unconditionally sent
        # one-sample batches (thousands of queue items per second at the demo's pace,
        # the queue filled and samples were dropped); only a batch older than batch_s goes
        self._data_time_s = data_time_s  # (the reader thread compares arrivals with it)
        if self._batch and time.monotonic() - self._batch_t0 >= self.batch_s:
            self.flush()
        held, due = self._held, []
        if not held or held[0][0] > data_time_s - self.product_latency_s:  # the usual poll: nothing due
            return due
        with self._held_lock:  # the release rule (module docstring), products with their own latency
            due, keep = split_due(self._held, data_time_s, self.latency_s, self.product_latency_s)
            self._held = deque(keep)
        return due

    def stop(self, timeout_s: float = 3.0) -> None:
        self._closed = True
        proc, in_q = self._proc, self._in_q
        if proc is not None and proc.is_alive():
            try:
                if in_q is not None:
                    in_q.put(_STOP, timeout=0.5)
            except (queue.Full, ValueError, OSError):
                pass
            proc.join(timeout_s)
            if proc.is_alive():
                proc.terminate()
                proc.join(1.0)
        self._discard_queues()
        self.state = "stopped"
