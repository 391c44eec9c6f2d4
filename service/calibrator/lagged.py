"""Replay's calibrator: deterministic application of releases (the release rule).

The release rule, live and in replay. Data time is the latest sample time seen (a
running maximum; a batch counts with its last sample): the runner's over the items it
admitted (truth excepted), the calibrator's over the samples it was given. A release computed by the
calibrator once its data time was ``τ`` is applied by the runner right after the item
that brings the runner's data time to ``τ + L`` or beyond, ``L`` = ``calibrator.latency_s``.
Live, :class:`adaptnav.service.calibrator.live.CalibratorProcess` holds releases until
then and hands them over in ``poll(data_time_s)``.

Here (:class:`LaggedCalibrator`), the runner, after an item that brings its data time to
``t``, calls ``poll(t)`` (the same route as the live calibrator's): it waits until the
calibrator (child process or in-process) has reported that it processed every sample up
to ``t − L`` (a progress message on the return pipe), so every release due by ``t`` is
known, and returns those. Side products (due ``L_p`` after their τ) come only from the
side-scan ping that completes a detector block, whose count the child reports: the runner
waits for them only once its data time is ``L_p`` past that ping's (the child's EM windows
in between cost it no wait). The output does not depend on wall-clock timing: same data and
seed ⇒ the same trajectory and parameter history, whether the calibrator runs in a child
process (``location="process"``, the second core) or in-process (``"inline"``), at any
machine load. ``L`` is how far the runner may run ahead of the calibrator: it should exceed
the calibrator's bursts (one EM window) in data time at the replay speed. At the end of the
data the runner polls with ``t = ∞``: the calibrator finishes and every pending release is
passed.

Releases cross the process boundary in their codec's JSON form
(:mod:`adaptnav.service.transport.release`).
"""
from __future__ import annotations

import dataclasses
import gc
import math
import multiprocessing as mp
import os
import select
import threading
import time
from typing import Any

import numpy as np

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.calibrator.signals import ignore_sigint, start_ignoring_sigint
from adaptnav.service.calibrator.heap import keep_freed_heap
from adaptnav.service.calibrator.batching import DataClock, data_time, next_due, pack_batch, split_due, unpack_batch
from adaptnav.service.compose import make_calibrator
from adaptnav.service.runtime.protocols import RunAborted
from adaptnav.service.transport.release import release_from_dict, release_to_dict

_STOP = "__stop__"
_SHIFT = "__shift__"
_FINISH = "__finish__"  # the data ended: the calibrator hands over what it holds for completion
PROGRESS_EVERY = 32     # samples between the child's progress messages inside a batch the runner waits for
# LaggedCalibrator.quiet_until_s keeps this far below the child's progress + lag (data s, and
# relative): thousands of times the rounding of ``t − lag`` at any data time (UNIX times too)
_QUIET_MARGIN_S = 1e-6
_QUIET_MARGIN_REL = 1e-12


class CalibratorGone(RunAborted):
    """The calibrator's child process died or failed: the replay cannot go on to its
    deterministic output (the message says how; a failure in the child carries its traceback)."""


class InlineBackend:
    """The calibrator in this process (same rule, no second core)."""

    def __init__(self, calibrator: Any) -> None:
        self.calibrator = calibrator
        self.clock = DataClock()
        self.ready: list[tuple[float, Any]] = []   # (τ, release), oldest first
        self.side_scan: dict | None = None  # the object front end's counts, at finish()

    def send(self, sample: Any) -> None:
        self.calibrator.observe(sample)
        tau = self.clock.advance(sample)
        for rel in self.calibrator.poll():
            self.ready.append((tau, rel))

    @property
    def caught_up_s(self) -> float:
        """What :meth:`ProcessBackend.caught_up_s` says: here every output not yet in
        :attr:`ready` comes from a later sample, at a τ no earlier than the data time reached."""
        return self.clock.tau

    def sync(self, t_s: float) -> None:
        """Every release with ``τ ≤ t_s`` is in :attr:`ready` (always, in-process)."""

    def shift_time(self, delta_s: float) -> None:
        """The data clock jumped by ``delta_s`` (re-based by the runner)."""
        self.clock.tau += delta_s

    def finish(self) -> None:
        """The data ended: what the calibrator still holds (:meth:`OnlineCalibrator.finish`)
        is ready at the data time reached."""
        finish = getattr(self.calibrator, "finish", None)
        if finish is not None:
            finish()
            for rel in self.calibrator.poll():
                self.ready.append((self.clock.tau, rel))
        self.side_scan = side_scan_report(self.calibrator)

    def close(self) -> None:
        pass


def side_scan_report(calibrator: Any) -> dict | None:
    """The calibrator's side-scan counts (:meth:`OnlineCalibrator.side_scan_report`), None
    without side-scan or for a calibrator that keeps none."""
    report = getattr(calibrator, "side_scan_report", None)
    return None if report is None else report()


def child_message(out: Any, tau: float) -> tuple:
    """A calibrator's output for the return pipe: a release in its codec's JSON form, a side
    product (side-scan objects for the filter, :mod:`adaptnav.calibration.sidescan`) as it is."""
    if out.KIND == "calibration_release":
        return ("release", release_to_dict(out), tau)
    return ("product", out, tau)


def for_child(sample: Any) -> Any:
    """What of ``sample`` the child is sent: an object batch back from the filter
    (``sonar_objects``) without its sightings — the calibrator reads only its links and
    time (:meth:`OnlineCalibrator._links`); pickled with them it cost both processes
    more than every other sample of the hour (0.07 s to pickle, 0.10 s to unpickle) —,
    anything else as it is."""
    if sample.KIND == "sonar_objects" and getattr(sample, "sightings", None):
        return dataclasses.replace(sample, sightings=())
    return sample


def _lagged_child_main(cfg: Any, params0: MotionParams, seed: int, conn_in: Any, conn_out: Any) -> None:
    """Child of :class:`ProcessBackend`: per sample observe → poll, releases stamped with
    τ; after each batch a progress message ``(seq of the last sample, τ)``."""
    ignore_sigint()
    out_q = conn_out  # Connection.send: what Queue.put did, without a feeder thread
    try:
        try:
            import cv2

            # the parent runs the filter on the other core: OpenCV's worker threads would
            # only compete with it (and with each other) for the second one
            cv2.setNumThreads(1)
        except ImportError:  # pragma: no cover - OpenCV is a dependency
            pass
        keep_freed_heap()  # the EM's arrays stay mapped between iterations (heap.py)
        calibrator = make_calibrator(cfg, params0, seed)
        clock = DataClock()
        pings = 0  # side-scan pings observed
        block_ping = -1  # the count of the ping that completes the next block, as last reported
        to_block = getattr(calibrator, "pings_to_block", lambda: None)

        def progress(done: int, tau: float) -> tuple:
            # with the pings seen and how many more complete the detector's next block, so
            # that the runner sends the one that does at once (ProcessBackend.send) and knows
            # that no side product comes before it (ProcessBackend.sync)
            nonlocal block_ping
            k = to_block()
            if k is None:
                return ("progress", done, tau)
            block_ping = pings + k
            return ("progress", (done, block_ping), tau)

        # the modules forked from the server (numpy, scipy, numba, OpenCV: ~10⁵ objects)
        # stay out of the garbage collector's full passes: they were rescanned at every
        # one, a quarter of the child's CPU (1 h survey with sonar: 18.4 → 13.7–14.0 s)
        gc.freeze()
        out_q.send(("ready", None, None))
        while True:
            try:
                msg = conn_in.recv()
            except EOFError:  # the parent is gone
                return
            if isinstance(msg, str) and msg == _STOP:
                return
            if isinstance(msg, str) and msg == _FINISH:  # the data ended (InlineBackend.finish)
                calibrator.finish()
                for rel in calibrator.poll():
                    out_q.send(child_message(rel, clock.tau))
                out_q.send(("finished", side_scan_report(calibrator), clock.tau))
                continue
            if msg[0] == _SHIFT:  # the runner re-based a clock jump: τ moves with the data
                clock.tau += msg[1]
                out_q.send(("shifted", None, msg[1]))
                continue
            seq, n, items, imu, n_echo, every = msg
            packed = (items, imu, _read_echoes(conn_in, n_echo) if n_echo else None)
            tau = clock.tau
            # progress also every ``every`` samples inside a batch the runner sent because it
            # waits: for a τ just past its data time − L_p, which the first samples of the batch
            # already give (with one message per batch it waited for the whole batch, ~L_p of
            # data with side-scan: the two processes ran in lock-step); not inside the others
            # (most: full batches, block pings), whose progress it reads only later
            for i, sample in enumerate(unpack_batch(packed), start=1):
                at_block = False
                if sample.KIND == "sonar":
                    pings += 1
                    at_block = pings == block_ping
                calibrator.observe(sample)
                t = sample.t_s  # DataClock.advance inlined (once per sample)
                if type(t) is not float:
                    t = data_time(sample)
                if t > tau:  # False for NaN
                    tau = t
                for rel in calibrator.poll():
                    out_q.send(child_message(rel, tau))
                # and after the ping that completed a block: the runner waits for that one
                if (at_block or (every and i % every == 0)) and i < n:
                    out_q.send(progress(seq + i, tau))
            clock.tau = tau
            out_q.send(progress(seq + n, clock.tau))
    except BaseException as e:  # the parent must not wait forever for a dead child
        import traceback

        try:
            out_q.send(("error", f"{type(e).__name__}: {e}\n{traceback.format_exc()}", None))
        except OSError:
            pass
        raise


def _cpu_s(pid: int) -> float:
    """User + system CPU time of process ``pid`` (s) from /proc; NaN elsewhere."""
    import os

    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return math.nan


def _write_all(fd: int, arrays: list) -> None:
    """Write the arrays' bytes (C-contiguous arrays) to ``fd`` back to back, straight from
    their memory (one ``writev`` per up to ``IOV_MAX`` of them; again after a partial write).
    ``writev`` takes the arrays themselves: a byte view is made only of one written in part
    (a view of each cost more than the write, 72k echoes per data hour)."""
    bufs = list(arrays)
    while bufs:
        n = os.writev(fd, bufs[:_IOV_MAX])
        k = 0
        while k < len(bufs) and n >= bufs[k].nbytes:
            n -= bufs[k].nbytes
            k += 1
        bufs = bufs[k:]
        if n:
            bufs[0] = memoryview(bufs[0]).cast("B")[n:]


def _read_echoes(conn: Any, n_samples: int) -> np.ndarray:
    """The ``n_samples`` float32 values :func:`_write_all` wrote after a message on ``conn``,
    read straight into one array (``Connection`` reads exactly each message's length: the
    pipe holds these bytes next)."""
    out = np.empty(n_samples, dtype=np.float32)
    view = memoryview(out).cast("B")
    fd, got = conn.fileno(), 0
    while got < len(view):
        k = os.readv(fd, [view[got:]])
        if k == 0:
            raise EOFError("calibrator pipe closed inside a message's echoes")
        got += k
    return out


_IOV_MAX = os.sysconf("SC_IOV_MAX") if hasattr(os, "sysconf") else 1024


def _enlarge_pipe(conn: Any, size: int = 1 << 20) -> None:
    """Linux: raise the pipe buffer behind ``conn`` to ``size`` bytes (best effort)."""
    try:
        import fcntl

        fcntl.fcntl(conn.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), size)
    except (ImportError, OSError, ValueError):
        pass


# BLAS thread pools of the calibrator's processes: one thread. The child is meant to use
# one core (the fusion thread has the other); OpenBLAS's default pool spins on every core
# for the M-step's small products (20000 × 3): EM iteration 0.044 → 0.030 s of CPU, the
# M-step alone 0.022–0.031 → 0.012 s (`adaptnav bench calibration`, same run).
CHILD_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def limit_child_threads() -> None:
    """Set :data:`CHILD_THREAD_ENV` (where not set already) for the children started
    from now on: their BLAS reads it when numpy loads, this process's own is loaded."""
    import os

    for key, value in CHILD_THREAD_ENV.items():
        os.environ.setdefault(key, value)


def _forkserver_context() -> Any:
    limit_child_threads()
    ctx = mp.get_context("forkserver")
    # what the children need, imported (and numba's kernels loaded) once in the server
    ctx.set_forkserver_preload(["__main__", "adaptnav.service.calibrator.lagged", "adaptnav.service.calibrator.preload"])
    return ctx


def prestart() -> None:
    """Start the calibrator's forkserver in a background thread, so that its ~1.5 s of
    imports overlap other work (opening or simulating the input); a no-op where there is
    no forkserver. :class:`ProcessBackend` waits for it if it is not up yet."""
    if "forkserver" not in mp.get_all_start_methods():
        return
    from multiprocessing import forkserver

    _forkserver_context()
    threading.Thread(target=forkserver.ensure_running, name="forkserver-start", daemon=True).start()


class ProcessBackend:
    """The calibrator in a child process (the second core; forked from a preloaded
    forkserver, or spawned), flow-controlled by :meth:`sync`: samples go in batches of
    ``batch_size``; the parent blocks only when it needs a progress the child has not
    reported yet. A child that dies raises ``RuntimeError`` in the parent (replay must not
    silently go on without it: its output would no longer be the deterministic one)."""

    def __init__(self, cfg: Any, params0: MotionParams, seed: int, batch_size: int = 256,
                 start_method: str | None = None) -> None:
        if start_method is None:
            # a spawned child re-imports numpy, scipy, numba and OpenCV (~1.5 s, 10 % of a
            # 1 h replay at 200×); the forkserver pays that once per parent process and
            # then forks children from its clean single-threaded state. Plain fork is not
            # safe here: a parent that has used OpenCV's thread pool (an in-process
            # calibrator, the sonar tools) hands the child a pool it deadlocks on.
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        limit_child_threads()
        ctx = _forkserver_context() if start_method == "forkserver" else mp.get_context(start_method)
        self.start_method = start_method
        self.batch_size = int(batch_size)
        self.ready: list[tuple[float, Any]] = []
        # plain pipes written from this thread: an mp.Queue's feeder thread cost the
        # runner ~1 s of CPU (and GIL hand-offs) per 20 min of data. The pipe to the child
        # is enlarged so that a batch never blocks while the child runs an EM window
        # (sync() bounds how far ahead the runner gets anyway).
        child_in, self._w = ctx.Pipe(duplex=False)
        self._r, child_out = ctx.Pipe(duplex=False)
        _enlarge_pipe(self._w)
        _enlarge_pipe(self._r)  # progress messages queue up there while the runner needs none
        # "is a message there?" thousands of times per data hour: Connection.poll builds a
        # selector per call (~10 µs); one poll object on the pipe answers the same
        if hasattr(select, "poll"):
            poller = select.poll()
            poller.register(self._r.fileno(), select.POLLIN)
            self._readable = lambda timeout_s: bool(poller.poll(timeout_s * 1000.0))
        else:  # pragma: no cover - no poll(2)
            self._readable = self._r.poll
        self._proc = ctx.Process(target=_lagged_child_main, name="adaptnav-calibrator", daemon=True,
                                 args=(cfg, params0, seed, child_in, child_out))
        start_ignoring_sigint(self._proc)
        child_in.close()
        child_out.close()
        self._batch: list[Any] = []
        self._sent = 0          # samples sent (sequence number of the next one)
        self._done = 0          # samples the child reported processed
        self._child_tau = -math.inf
        self.wait_s = 0.0       # wall time spent waiting for the child
        self._unacked_shift_s = 0.0  # clock shifts sent to the child it has not confirmed yet
        self.child_cpu_s = math.nan  # the child's CPU time at finish() (Linux /proc)
        self._finished = False  # the child handed over what it held at the end of the data
        self._pings_out = 0     # side-scan pings sent (or batched)
        self.side_scan: dict | None = None  # the child's object front end's counts, at finish()
        self._block_ping = -1   # the count of the ping that completes the child's next block
        # no side product of the samples sent has a τ below this: +∞ while the ping that
        # completes the next block is not sent, that ping's time once it is (the child's τ
        # there is at least that), −∞ when not known (sent before the child said which)
        self._block_t = -math.inf
        self.on_block_ping = None  # called when that ping is sent (LaggedCalibrator)
        # the runner's deferrable work (replay: DeferredSinks.work), done while it waits for
        # the child instead of sleeping: a slice per call, False when there is none
        self.idle: Any = None
        self.idle_s = 0.0       # wall time of that work inside the waits (not in wait_s)

    def send(self, sample: Any) -> None:
        kind = sample.KIND
        if kind == "sonar_objects":
            sample = for_child(sample)
        self._batch.append(sample)
        if kind == "sonar":
            self._pings_out += 1
            if self._pings_out == self._block_ping:
                # the ping that completes the child's next detector block (as its last
                # progress said): sent now, so that the child detects while the runner goes
                # on; held back, it reached the child only when the runner needed its
                # progress, and the runner waited for the whole detection
                t = sample.t_s
                self._block_t = t if type(t) is float and t == t else -math.inf
                self._flush()
                if self.on_block_ping is not None:
                    self.on_block_ping()
                return
        if len(self._batch) >= self.batch_size:
            self._flush()

    def _flush(self, progress_every: int = 0) -> None:
        """Send the batch; ``progress_every``: samples between the child's progress messages
        inside it (0: at its end and after a block's ping only)."""
        if self._batch:
            items, imu, echoes = pack_batch(self._batch)
            try:
                self._w.send((self._sent, len(self._batch), items, imu, sum(e.size for e in echoes),
                              progress_every))
                if echoes:
                    _write_all(self._w.fileno(), echoes)
            except (BrokenPipeError, OSError) as e:
                raise CalibratorGone(f"calibrator process gone (exit code {self._proc.exitcode}): {e}") from None
            self._sent += len(self._batch)
            self._batch = []

    def _wait_read(self) -> None:
        """Handle the child's next message, waiting for it; while none has come, the runner's
        idle work (:attr:`idle`) a slice at a time."""
        idle = self.idle
        if idle is not None:
            while not self._readable(0.0):
                t0 = time.monotonic()
                busy = idle()
                self.idle_s += time.monotonic() - t0
                if not busy:
                    break
        self._read(block=True)

    def _read(self, block: bool) -> bool:
        """Handle one message from the child; False when none (non-blocking)."""
        try:
            if not self._readable(1.0 if block else 0.0):
                if block and not self._proc.is_alive():
                    raise CalibratorGone(f"calibrator process died (exit code {self._proc.exitcode})")
                return False
            kind, body, tau = self._r.recv()
        except (EOFError, OSError):
            raise CalibratorGone(f"calibrator process died (exit code {self._proc.exitcode})") from None
        if kind in ("release", "product"):  # computed before a shift the child has not seen yet: re-based here
            self.ready.append((float(tau) + self._unacked_shift_s,
                               release_from_dict(body) if kind == "release" else body))
        elif kind == "progress":
            if type(body) is tuple:
                body, block_ping = body
                if block_ping != self._block_ping:  # (the same one again: what _block_t says holds)
                    self._block_ping = block_ping
                    self._block_t = math.inf if block_ping > self._pings_out else -math.inf
            self._done, self._child_tau = int(body), float(tau) + self._unacked_shift_s
        elif kind == "shifted":
            self._unacked_shift_s -= float(tau)
        elif kind == "finished":
            self._finished = True
            self.side_scan = body
        elif kind == "error":
            raise CalibratorGone(f"calibrator process failed: {body}")
        return True

    @property
    def caught_up_s(self) -> float:
        """:meth:`sync` returns at once, with nothing to do, for every ``t_s`` below it; every
        output not yet in :attr:`ready` has a τ no earlier (the child reports in order, its τ
        never decreases)."""
        return self._child_tau

    @property
    def products_from_s(self) -> float:
        """Every side product not yet in :attr:`ready` has a τ no earlier (:meth:`sync`)."""
        return max(self._child_tau, self._block_t)

    def _synced(self, t_s: float, release_t_s: float) -> bool:
        # every output the child makes from now on has a τ ≥ its τ so far, a side product
        # also ≥ _block_t (products come only from the ping that completes a block)
        tau = self._child_tau
        return tau > t_s or (tau > release_t_s and self._block_t > t_s)

    def sync(self, t_s: float, release_t_s: float | None = None) -> None:
        """Block until every output with ``τ ≤ t_s`` is in :attr:`ready` — of the releases,
        every one with ``τ ≤ release_t_s`` (≤ ``t_s``; default ``t_s``): the child has processed
        a sample later than ``t_s`` (τ is non-decreasing and messages are in order) or every
        sample observed so far, or it has processed one later than ``release_t_s`` and no side
        product can have a τ ≤ ``t_s`` (the ping that completes its next block is not sent,
        or is later than ``t_s``; such a ping is what the runner waited for, not the child's
        EM windows)."""
        if release_t_s is None:
            release_t_s = t_s
        if self._synced(t_s, release_t_s) or self._done >= self._sent + len(self._batch):
            return
        # what the child reported already may do (its progress comes every PROGRESS_EVERY
        # samples): read it before sending the batch, which would otherwise go out a few
        # samples long after every progress message
        while self._read(block=False):
            if self._synced(t_s, release_t_s) or self._done >= self._sent + len(self._batch):
                return
        self._flush(PROGRESS_EVERY)
        t0, idle0 = time.monotonic(), self.idle_s
        while not (self._synced(t_s, release_t_s) or self._done >= self._sent):
            self._wait_read()
        self.wait_s += time.monotonic() - t0 - (self.idle_s - idle0)

    def shift_time(self, delta_s: float) -> None:
        """The data clock jumped by ``delta_s``: the child's τ moves with it (after the
        samples already sent), what it reports before it has seen the shift is re-based here."""
        self._flush()
        try:
            self._w.send((_SHIFT, float(delta_s)))
        except (BrokenPipeError, OSError) as e:
            raise CalibratorGone(f"calibrator process gone (exit code {self._proc.exitcode}): {e}") from None
        self._unacked_shift_s += delta_s
        self._child_tau += delta_s
        if self._block_t != math.inf:  # a block ping sent before the jump: its time not re-based
            self._block_t = -math.inf

    def finish(self) -> None:
        """Wait for the child to process everything observed, then for what it still holds
        (:meth:`InlineBackend.finish`)."""
        self._flush()
        t0, idle0 = time.monotonic(), self.idle_s
        while self._done < self._sent:
            self._wait_read()
        if not self._finished:
            try:
                self._w.send(_FINISH)
            except (BrokenPipeError, OSError) as e:
                raise CalibratorGone(f"calibrator process gone (exit code {self._proc.exitcode}): {e}") from None
            while not self._finished:
                self._wait_read()
        self.wait_s += time.monotonic() - t0 - (self.idle_s - idle0)
        self.child_cpu_s = _cpu_s(self._proc.pid)

    def close(self, timeout_s: float = 5.0) -> None:
        proc = self._proc
        if proc.is_alive():
            try:
                self._w.send(_STOP)
            except (ValueError, OSError):
                pass
            proc.join(timeout_s)
            if proc.is_alive():
                proc.terminate()
                proc.join(1.0)
        self._w.close()
        self._r.close()


def _below(bound_s: float) -> float:
    """``bound_s`` less a margin far above the rounding of ``t − lag`` (the backend's test is
    ``τ_child > t − lag``)."""
    if math.isfinite(bound_s):
        bound_s -= _QUIET_MARGIN_S + _QUIET_MARGIN_REL * abs(bound_s)
    return bound_s


class LaggedCalibrator:
    """The runner's calibrator with deterministic application (module docstring).

    Use as ``run(source, ..., calibrator=lagged)``: :meth:`observe` forwards samples to the
    backend, :meth:`poll` returns each release once the runner's data time has reached its
    ``τ + L``.

    Parameters
    ----------
    backend : InlineBackend or ProcessBackend
    latency_s : float
        ``L`` (data seconds, ≥ 0).
    product_latency_s : float, optional
        ``L_p`` ≤ ``L`` for the side products (side-scan objects for the filter); default ``L``.
    """

    def __init__(self, backend: Any, latency_s: float, product_latency_s: float | None = None) -> None:
        if not (math.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"calibrator latency_s must be a finite number ≥ 0, got {latency_s}")
        lp = latency_s if product_latency_s is None else float(product_latency_s)
        if not 0.0 <= lp <= latency_s:
            raise ValueError(f"calibrator product_latency_s must be within [0, latency_s], got {lp}")
        self.backend = backend
        self.latency_s = float(latency_s)
        self.product_latency_s = lp
        # how far behind the runner the calibrator may be: L until products can come (they
        # come only from side-scan pings), then L_p — a replay without side-scan never
        # waits for the calibrator more than before
        self._sync_lag_s = self.latency_s
        self.released = 0
        # poll(t) returns [] and does nothing for every t below it (the runner skips it then)
        self.quiet_until_s = -math.inf
        self.observe = backend.send  # the runner calls it for every sample: no extra frame
        if lp < latency_s:
            self.observe = self._observe
        # a backend that bounds its side products' τ apart from its releases' (ProcessBackend:
        # products come only from the ping that completes a block) syncs for each by its lag
        self._bounds_products = hasattr(backend, "products_from_s")
        if self._bounds_products:
            # the ping that completes the child's next block was sent: a side product may be
            # due L_p after it (quiet_until_s assumed none before the next release's due time)
            backend.on_block_ping = self._wake

    def _observe(self, sample: Any) -> None:
        if sample.KIND == "sonar":
            self._sync_lag_s = self.product_latency_s
            self.quiet_until_s = -math.inf  # it assumed the longer lag
            self.observe = self.backend.send
        self.backend.send(sample)

    def _wake(self) -> None:
        self.quiet_until_s = -math.inf

    def poll(self, data_time_s: float) -> list:
        """The releases with ``τ + L ≤ data_time_s`` (the runner's data time) and the side
        products with ``τ + L_p ≤ data_time_s``, oldest first, once the calibrator has caught
        up with ``data_time_s − L`` (``− L_p`` once products can come); ``data_time_s = ∞``:
        the data ended, the calibrator finishes and everything is due."""
        backend = self.backend
        # side products can come (their L_p is shorter), bounded apart by the backend
        products = self._bounds_products and self._sync_lag_s < self.latency_s
        if data_time_s == math.inf:
            backend.finish()
        elif products:
            backend.sync(data_time_s - self._sync_lag_s, data_time_s - self.latency_s)
        else:
            backend.sync(data_time_s - self._sync_lag_s)
        ready = backend.ready
        if not ready or ready[0][0] + self.product_latency_s > data_time_s:  # the usual poll: nothing due
            due = []
        else:
            due, keep = split_due(ready, data_time_s, self.latency_s, self.product_latency_s)
            ready[:] = keep
            self.released += len(due)
        # until the next release or product is due, or the backend would have to sync: below
        # that, a poll would return [] without touching anything (a pending release held
        # every poll of its minute to the test above). An output that reaches ready later has
        # τ ≥ caught_up_s: due no earlier than caught_up_s + L_p. The sync bound with a margin
        # far above the rounding of ``t − lag`` (the child's test is ``τ_child > t − lag``)
        caught_up = backend.caught_up_s
        if products:  # a product's τ is bounded apart from a release's (ProcessBackend.sync)
            self.quiet_until_s = min(_below(caught_up + self.latency_s),
                                     _below(backend.products_from_s + self.product_latency_s),
                                     next_due(ready, self.latency_s, self.product_latency_s))
        else:
            self.quiet_until_s = min(_below(caught_up + self._sync_lag_s), caught_up + self.product_latency_s,
                                     next_due(ready, self.latency_s, self.product_latency_s))
        return due

    def shift_time(self, delta_s: float) -> None:
        """The runner confirmed a jump of the input's clock by ``delta_s`` (it re-bases the
        estimator, its clock, health and its data time alike): the τ of every pending release
        and the calibrator's own data clock move with it, so releases keep coming ``L`` after
        their data. Without it a backward jump held every later release for as long as the
        jump (the running maximum stayed in the old time base)."""
        self.backend.ready[:] = [(tau + delta_s, rel) for tau, rel in self.backend.ready]
        self.backend.shift_time(delta_s)
        self.quiet_until_s = -math.inf

    def close(self) -> None:
        self.backend.close()
