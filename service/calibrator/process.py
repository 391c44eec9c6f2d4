"""The EM calibrator outside the fusion thread: a supervised child process, or a bus node.

DESIGN.md "Service": fusion must never wait for EM (2 cores). The daemon therefore runs
:class:`adaptnav.calibration.online.OnlineCalibrator` in a ``multiprocessing`` *spawn* child:

- :class:`CalibratorProcess` is what the runner sees as its ``calibrator``:
  ``observe(sample)`` forwards the sample to the child without blocking (a full queue
  drops and counts — EM can afford a gap, fusion cannot afford a stall) and ``poll()``
  returns nothing: releases come back, stamped with the data time they were computed
  up to, through the runner's *input queue* (a reader thread moves them there), so
  they are applied between samples in data order as in replay.
- :meth:`CalibratorProcess.supervise` (called periodically by the daemon) restarts a
  dead child with exponential backoff, warm-started from the latest accepted params.
- :func:`run_node` is ``adaptnav run --calibrator-only``: the same calibrator as its own
  bus node (another computer, or shore-side through a router), subscribing to the
  sensor topics and publishing releases on ``adaptnav/<v>/calibration/params``.

Releases travel as JSON (:func:`release_to_dict` / :func:`release_from_dict`).

The release rule, live and in replay. Data time is the latest sample time seen (a
running maximum; a batch counts with its last sample). A release computed by the
calibrator once its data time was ``τ`` is applied by the runner right after the item
that brings the runner's data time to ``τ + L`` or beyond, ``L`` = ``calibrator.latency_s``.

- Live (:class:`CalibratorProcess`): releases wait in the parent until the data time
  passed to :meth:`CalibratorProcess.observe` reaches ``τ + L``, then
  :meth:`CalibratorProcess.poll` hands them to the runner. The runner never waits: a
  release that comes back later than ``τ + L`` (EM slower than real time) is applied at
  the first poll after it arrives.
- Replay (:class:`LaggedCalibrator`): the runner, after an item that brings its data
  time to ``t``, waits until the calibrator (child process or in-process) has reported
  that it processed every sample up to ``t − L`` (a progress message on the return
  queue), so every release due by ``t`` is known. The output does not depend on
  wall-clock timing: same data and seed ⇒ the same trajectory and parameter history,
  whether the calibrator runs in a child process (``location="process"``, the second
  core) or in-process (``"inline"``), at any machine load. ``L`` is how far the runner
  may run ahead of the calibrator: it should exceed the calibrator's bursts (one EM
  window) in data time at the replay speed. Releases still pending at the end of the
  data are passed after the last item.
"""
from __future__ import annotations

import gc
import logging
import math
import multiprocessing as mp
import queue
import threading
import time
from collections import Counter, deque
from typing import Any, Callable

import numpy as np

from adaptnav.fusion.motion_model import MotionParams

log = logging.getLogger(__name__)

_STOP = "__stop__"


# -- release codec ------------------------------------------------------------------
def release_to_dict(release: Any) -> dict[str, Any]:
    """A calibrator ``Release`` → JSON-ready dict (type ``calibration_release``)."""
    params = getattr(release, "params", None)
    ll = float(getattr(release, "log_likelihood", math.nan))
    return {
        "type": "calibration_release",
        "schema_version": 1,
        "t_s": float(release.t_s),
        "params": params.to_dict() if params is not None else None,
        "log_likelihood": ll if math.isfinite(ll) else None,
        "accepted": bool(release.accepted),
        "reason": str(getattr(release, "reason", "") or ""),
        "iterations": int(getattr(release, "iterations", 0) or 0),
        "current_n_m_s": [float(x) for x in getattr(release, "current_n_m_s", (0.0, 0.0))],
        "teachers": [str(x) for x in getattr(release, "teachers", ())],
    }


def _release_type() -> type:
    try:
        from adaptnav.calibration.online import Release
    except ImportError:  # a daemon without the calibrator package still applies remote releases
        import dataclasses
        from dataclasses import make_dataclass

        Release = make_dataclass("Release", ["t_s", "params", "log_likelihood", "accepted",
                                             "reason", "iterations",
                                             ("current_n_m_s", tuple, dataclasses.field(default=(0.0, 0.0))),
                                             ("teachers", tuple, dataclasses.field(default=()))],
                                 frozen=True)
    return Release


def _current_from(value: Any) -> tuple[float, float]:
    """Optional ``current_n_m_s`` (north, east, m/s) of a release; absent → (0, 0)."""
    if value is None:
        return (0.0, 0.0)
    n, e = (float(x) for x in value)
    return (n, e)


def release_from_dict(data: Any) -> Any:
    """Dict → ``adaptnav.calibration.online.Release``; ``ValueError`` when malformed."""
    Release = _release_type()

    if not isinstance(data, dict) or data.get("type") != "calibration_release":
        raise ValueError("not a calibration_release")
    if data.get("schema_version") != 1:
        raise ValueError(f"calibration_release schema_version {data.get('schema_version')!r}")
    try:
        t_s = float(data["t_s"])
        params = MotionParams.from_dict(data["params"]) if data.get("params") is not None else None
        ll = data.get("log_likelihood")
        return Release(t_s=t_s, params=params,
                       log_likelihood=math.nan if ll is None else float(ll),
                       accepted=bool(data["accepted"]), reason=str(data.get("reason", "")),
                       iterations=int(data.get("iterations", 0)),
                       current_n_m_s=_current_from(data.get("current_n_m_s")),
                       teachers=tuple(str(x) for x in data.get("teachers", ())))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"calibration_release: {e}") from e


def make_calibrator(cfg: Any, params0: MotionParams, seed: int) -> Any:
    """An :class:`OnlineCalibrator` from a :class:`service.config.ServiceConfig`.

    Without its own origin, the calibrator uses the service's mission origin, so its
    poses and the filter's share one NED frame.
    """
    import dataclasses

    import numpy as np

    from adaptnav.calibration.online import OnlineCalibrator

    online = cfg.calibrator.online
    if not (math.isfinite(online.origin_lat_deg) and math.isfinite(online.origin_lon_deg)):
        online = dataclasses.replace(online, origin_lat_deg=cfg.origin.lat_deg,
                                     origin_lon_deg=cfg.origin.lon_deg)
    dvl = cfg.filter.dvl  # the DVL teacher needs the head's mounting (calibration.dvl_teacher)
    return OnlineCalibrator(online, params0, cfg.motion.rpm_table, np.random.default_rng(seed),
                            dvl_mount=(dvl.lever_arm_b_m, dvl.rotation_bd_rpy_rad))


def compact_imu(batch: list[Any]) -> list[Any]:
    """Runs of consecutive ``ImuSample`` → one ``ImuBatch`` each (order kept, nothing lost).

    The calibrator only bins the yaw rate, and does so vectorised for an ``ImuBatch``;
    one array object instead of hundreds of small ones is also ~50× cheaper to pickle
    across the process boundary (the demo's 100 Hz IMU at 20× real time is 2000 /s).
    """
    import numpy as np

    from adaptnav.fusion.samples import ImuBatch, ImuSample

    out: list[Any] = []
    run: list[Any] = []

    def close() -> None:
        if len(run) == 1:
            out.append(run[0])
        elif run:
            out.append(ImuBatch(np.array([s.t_s for s in run], dtype=float),
                                np.array([s.specific_force_b_m_s2 for s in run], dtype=float),
                                np.array([s.omega_b_rad_s for s in run], dtype=float)))
        run.clear()

    for s in batch:
        if type(s) is ImuSample:
            run.append(s)
        else:
            close()
            out.append(s)
    close()
    return out


# -- deterministic (lagged) application ------------------------------------------------
def data_time(sample: Any) -> float:
    """Latest finite time of a sample or :class:`~fusion.samples.ImuBatch` (s); NaN if none."""
    t = getattr(sample, "t_s", None)
    if t is None:
        return math.nan
    if isinstance(t, (int, float)):
        return float(t)
    try:
        n = len(t)
    except TypeError:
        return math.nan
    for i in range(n - 1, -1, -1):  # the last finite entry (a bad batch may end in NaN)
        v = float(t[i])
        if math.isfinite(v):
            return v
    return math.nan


class _DataClock:
    """Running maximum of the sample times observed (the calibrator's data time τ)."""

    def __init__(self) -> None:
        self.tau = -math.inf

    def advance(self, sample: Any) -> float:
        t = data_time(sample)
        if t > self.tau:  # False for NaN
            self.tau = t
        return self.tau


class InlineBackend:
    """The calibrator in this process (same rule, no second core)."""

    def __init__(self, calibrator: Any) -> None:
        self.calibrator = calibrator
        self.clock = _DataClock()
        self.ready: list[tuple[float, Any]] = []   # (τ, release), oldest first

    def send(self, sample: Any) -> None:
        self.calibrator.observe(sample)
        tau = self.clock.advance(sample)
        for rel in self.calibrator.poll():
            self.ready.append((tau, rel))

    def sync(self, t_s: float) -> None:
        """Every release with ``τ ≤ t_s`` is in :attr:`ready` (always, in-process)."""

    def finish(self) -> None:
        pass

    def close(self) -> None:
        pass


def pack_batch(batch: list[Any]) -> tuple:
    """Samples → a compact picklable form for the child: the arrays of every
    :class:`~fusion.samples.ImuBatch` concatenated (three arrays per message instead of three
    per batch: pickling many small arrays was most of the transport's cost), each batch
    replaced by its row span; other samples as they are. Inverse: :func:`unpack_batch`."""
    from adaptnav.fusion.samples import ImuBatch

    items: list[Any] = []
    ts, fs, ws = [], [], []
    row = 0
    for s in batch:  # not compact_imu: the child must see what an in-process calibrator sees
        if type(s) is ImuBatch:
            n = len(s)
            ts.append(np.asarray(s.t_s, dtype=float))
            fs.append(np.asarray(s.specific_force_b_m_s2, dtype=float))
            ws.append(np.asarray(s.omega_b_rad_s, dtype=float))
            items.append((row, row + n))
            row += n
        else:
            items.append(s)
    if not ts:
        return items, None
    return items, (np.concatenate(ts), np.concatenate(fs), np.concatenate(ws))


def unpack_batch(packed: tuple) -> list[Any]:
    """Inverse of :func:`pack_batch` (batches become views of the shared arrays)."""
    from adaptnav.fusion.samples import ImuBatch

    items, arrays = packed
    if arrays is None:
        return items
    t, f, w = arrays
    return [ImuBatch(t[s[0]:s[1]], f[s[0]:s[1]], w[s[0]:s[1]]) if type(s) is tuple else s for s in items]


def _lagged_child_main(cfg: Any, params0: MotionParams, seed: int, conn_in: Any, conn_out: Any) -> None:
    """Child of :class:`ProcessBackend`: per sample observe → poll, releases stamped with
    τ; after each batch a progress message ``(seq of the last sample, τ)``."""
    out_q = conn_out  # Connection.send: what Queue.put did, without a feeder thread
    try:
        try:
            import cv2

            # the parent runs the filter on the other core: OpenCV's worker threads would
            # only compete with it (and with each other) for the second one
            cv2.setNumThreads(1)
        except ImportError:  # pragma: no cover - OpenCV is a dependency
            pass
        calibrator = make_calibrator(cfg, params0, seed)
        clock = _DataClock()
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
            seq, n, packed = msg
            tau = clock.tau
            for sample in unpack_batch(packed):
                calibrator.observe(sample)
                t = sample.t_s  # _DataClock.advance inlined (once per sample)
                if type(t) is not float:
                    t = data_time(sample)
                if t > tau:  # False for NaN
                    tau = t
                for rel in calibrator.poll():
                    out_q.send(("release", release_to_dict(rel), tau))
            clock.tau = tau
            out_q.send(("progress", seq + n, clock.tau))
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
    ctx.set_forkserver_preload(["__main__", "adaptnav.service.calibrator.process", "adaptnav.service.calibrator.preload"])
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
        self._proc = ctx.Process(target=_lagged_child_main, name="adaptnav-calibrator", daemon=True,
                                 args=(cfg, params0, seed, child_in, child_out))
        self._proc.start()
        child_in.close()
        child_out.close()
        self._batch: list[Any] = []
        self._sent = 0          # samples sent (sequence number of the next one)
        self._done = 0          # samples the child reported processed
        self._child_tau = -math.inf
        self.wait_s = 0.0       # wall time spent waiting for the child
        self.child_cpu_s = math.nan  # the child's CPU time at finish() (Linux /proc)

    def send(self, sample: Any) -> None:
        self._batch.append(sample)
        if len(self._batch) >= self.batch_size:
            self._flush()

    def _flush(self) -> None:
        if self._batch:
            try:
                self._w.send((self._sent, len(self._batch), pack_batch(self._batch)))
            except (BrokenPipeError, OSError) as e:
                raise RuntimeError(f"calibrator process gone (exit code {self._proc.exitcode}): {e}") from None
            self._sent += len(self._batch)
            self._batch = []

    def _read(self, block: bool) -> bool:
        """Handle one message from the child; False when none (non-blocking)."""
        try:
            if not self._r.poll(1.0 if block else 0.0):
                if block and not self._proc.is_alive():
                    raise RuntimeError(f"calibrator process died (exit code {self._proc.exitcode})")
                return False
            kind, body, tau = self._r.recv()
        except (EOFError, OSError):
            raise RuntimeError(f"calibrator process died (exit code {self._proc.exitcode})") from None
        if kind == "release":
            self.ready.append((float(tau), release_from_dict(body)))
        elif kind == "progress":
            self._done, self._child_tau = int(body), float(tau)
        elif kind == "error":
            raise RuntimeError(f"calibrator process failed: {body}")
        return True

    def sync(self, t_s: float) -> None:
        """Block until every release with ``τ ≤ t_s`` is in :attr:`ready`: the child has
        processed a sample later than ``t_s`` (τ is non-decreasing and messages are in
        order) or every sample observed so far."""
        if self._child_tau > t_s or self._done >= self._sent + len(self._batch):
            return
        self._flush()
        t0 = time.monotonic()
        while not (self._child_tau > t_s or self._done >= self._sent):
            self._read(block=True)
        self.wait_s += time.monotonic() - t0

    def finish(self) -> None:
        """Wait for the child to process everything observed."""
        self._flush()
        t0 = time.monotonic()
        while self._done < self._sent:
            self._read(block=True)
        self.wait_s += time.monotonic() - t0
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


class LaggedCalibrator:
    """The runner's calibrator with deterministic application (module docstring).

    Use as ``run(lagged.schedule(source), ..., calibrator=lagged)``: :meth:`observe`
    forwards samples to the backend, :meth:`poll` returns nothing, and
    :meth:`schedule` puts each release into the item stream once the data time has
    reached its ``τ + L``.

    Parameters
    ----------
    backend : InlineBackend or ProcessBackend
    latency_s : float
        ``L`` (data seconds, ≥ 0).
    """

    def __init__(self, backend: Any, latency_s: float) -> None:
        if not (math.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"calibrator latency_s must be a finite number ≥ 0, got {latency_s}")
        self.backend = backend
        self.latency_s = float(latency_s)
        self.released = 0
        self.observe = backend.send  # the runner calls it for every sample: no extra frame

    def observe(self, sample: Any) -> None:  # replaced per instance by backend.send (__init__)
        self.backend.send(sample)

    def poll(self) -> list:
        return []  # releases go into the stream by schedule()

    def schedule(self, source: Any):
        """``source``'s items, each release inserted right after the item that brings the
        data time to its ``τ + L`` (module docstring)."""
        ready = self.backend.ready
        lag = self.latency_s
        sync = self.backend.sync
        now = -math.inf  # the runner's data time (as _DataClock, inlined: once per item)
        for item in source:
            yield item
            kind = getattr(item, "KIND", None)
            if kind is None or kind == "truth":
                continue  # releases, truth: not calibrator data (live, they do not exist)
            if kind != "imu_batch":
                t = item.t_s
            else:  # its last time, unless not finite (then data_time looks further back)
                t = float(item.t_s[-1]) if len(item) else math.nan
                if not math.isfinite(t):
                    t = data_time(item)
            if t > now:  # False for NaN
                now = t
            sync(now - lag)
            while ready and ready[0][0] + lag <= now:
                self.released += 1
                yield ready.pop(0)[1]
        self.backend.finish()
        while ready:
            self.released += 1
            yield ready.pop(0)[1]

    def close(self) -> None:
        self.backend.close()


def make_lagged_calibrator(cfg: Any, params0: MotionParams, location: str = "process",
                           latency_s: float | None = None) -> LaggedCalibrator:
    """:class:`LaggedCalibrator` from a ServiceConfig: ``location`` ``"process"`` (child
    process) or ``"inline"``; ``latency_s`` default ``cfg.calibrator.latency_s``."""
    lag = getattr(cfg.calibrator, "latency_s", 30.0) if latency_s is None else latency_s
    seed = cfg.calibrator.seed
    if location == "inline":
        backend: Any = InlineBackend(make_calibrator(cfg, params0, seed))
    elif location == "process":
        backend = ProcessBackend(cfg, params0, seed)
    else:
        raise ValueError(f"calibrator location {location!r}: expected 'process' or 'inline'")
    return LaggedCalibrator(backend, lag)


# -- the child ----------------------------------------------------------------------
def _child_main(cfg: Any, params0: MotionParams, seed: int, in_q: Any, out_q: Any) -> None:
    """Child process: observe samples, send releases back; exits on ``_STOP``."""
    calibrator = make_calibrator(cfg, params0, seed)
    clock = _DataClock()
    gc.freeze()  # the imported modules stay out of the collector's full passes (as in replay)
    out_q.put(("ready", None, None))
    while True:
        try:
            batch = in_q.get(timeout=0.5)
        except queue.Empty:
            batch = []
        if isinstance(batch, str) and batch == _STOP:
            return
        for sample in batch:
            calibrator.observe(sample)
            tau = clock.advance(sample)
            for release in calibrator.poll():  # stamped with the data time it was computed at
                out_q.put(("release", release_to_dict(release), tau))


class CalibratorProcess:
    """Supervised calibrator child process with the calibrator interface of the runner.

    Parameters
    ----------
    cfg : ServiceConfig
        Whole config (the child needs ``calibrator`` and ``motion``).
    params0 : MotionParams
        Warm start.
    deliver : callable or None
        Not called any more (kept for callers): releases come back through :meth:`poll`
        once due (the release rule in the module docstring).
    batch_s : float
        Samples are sent to the child in batches at most this old (wall seconds), which
        keeps inter-process overhead off the fusion thread.
    """

    def __init__(self, cfg: Any, params0: MotionParams, deliver: Callable[[Any], None] | None = None,
                 batch_s: float = 0.05) -> None:
        self.cfg = cfg
        self.params = params0
        self.deliver = deliver
        self.latency_s = float(getattr(cfg.calibrator, "latency_s", 0.0))
        self._held: deque = deque()   # (τ, release) from the reader thread, oldest first
        self._clock = _DataClock()    # the runner's data time, from observe()
        self.batch_s = batch_s
        self.dropped = 0
        self.restarts = 0
        self.state = "stopped"
        self.counters: Counter[str] = Counter()
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
        self.received = 0   # releases that came back from the child (any restart)
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
                                       args=(self.cfg, self.params, seed, self._in_q, self._out_q))
        self._proc.start()
        self._started_at = time.monotonic()
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
                self._held.append((float(tau), release))  # deque.append: thread-safe
                self.received += 1

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
        self._clock.advance(sample)  # the runner's data time: when held releases are due
        if self._in_q is None:
            self.dropped += 1
            return
        if not self._batch:
            self._batch_t0 = time.monotonic()
        self._batch.append(sample)
        if time.monotonic() - self._batch_t0 >= self.batch_s or len(self._batch) >= 500:
            self.flush()

    def flush(self) -> None:
        if not self._batch or self._in_q is None:
            return
        try:
            self._in_q.put_nowait(compact_imu(self._batch))
        except (queue.Full, ValueError, OSError):
            self.dropped += len(self._batch)
        self._batch = []

    def poll(self) -> list:
        # the runner polls after every sample: flushing here unconditionally sent
        # one-sample batches (thousands of queue items per second at the demo's pace,
        # the queue filled and samples were dropped); only a batch older than batch_s goes
        if self._batch and time.monotonic() - self._batch_t0 >= self.batch_s:
            self.flush()
        held, due = self._held, []
        limit = self._clock.tau - self.latency_s
        while held and held[0][0] <= limit:  # the release rule (module docstring)
            due.append(held.popleft()[1])
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


# -- standalone bus node ------------------------------------------------------------------
def run_node(cfg: Any, stop: threading.Event) -> int:
    """``adaptnav run --calibrator-only``: calibrate from the bus, publish releases."""
    import dataclasses
    import json

    from adaptnav.service.transport.bus import Bus, nonblocking_enqueue
    from adaptnav.service.runtime.persistence import load_state

    restored = load_state(cfg.state_dir)
    params0 = restored.params if restored and restored.params else cfg.motion.params0
    calibrator = make_calibrator(cfg, params0, cfg.calibrator.seed)
    # a node, not a second daemon: a Zenoh *client* of the router, or of the daemon's peer
    # (which then routes between it and the other programs: peers behind one peer do not
    # see each other without gossip), listening nowhere, so it can share the config file
    zcfg = dataclasses.replace(cfg.zenoh, mode="client",
                               connect=tuple(cfg.zenoh.connect) or tuple(cfg.zenoh.listen), listen=())
    bus = Bus(zcfg, cfg.vehicle.name)
    inbox: queue.Queue = queue.Queue(maxsize=cfg.calibrator.queue_size)
    overflow: Counter[str] = Counter()
    bus.subscribe_samples(nonblocking_enqueue(inbox, overflow))
    # the daemon's free-inertial velocity: the surge-noise evidence (calibration.inertial)
    bus.subscribe_samples(nonblocking_enqueue(inbox, overflow), key=bus.keys.nav_inertial)
    last: dict[str, Any] = {"params": params0.to_dict()}
    received: Counter[str] = Counter()  # samples taken, by kind
    bus.queryable("calibrator", lambda: json.dumps(
        {"type": "calibrator_status", "schema_version": 1, **last, "received": dict(received),
         "overflow": dict(overflow), "malformed": dict(bus.malformed)}).encode())
    log.info("calibrator node up for vehicle %s", cfg.vehicle.name)
    try:
        while not stop.is_set():
            try:
                sample = inbox.get(timeout=0.2)
            except queue.Empty:
                sample = None
            if sample is not None:
                received[getattr(sample, "KIND", type(sample).__name__)] += 1
                calibrator.observe(sample)
            for release in calibrator.poll():
                body = release_to_dict(release)
                if release.accepted and release.params is not None:
                    last["params"] = release.params.to_dict()
                bus.put(bus.keys.params, json.dumps(body).encode())
    finally:
        bus.close()
    return 0
