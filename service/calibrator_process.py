"""The EM calibrator outside the fusion thread: a supervised child process, or a bus node.

DESIGN.md "Service": fusion must never wait for EM (2 cores). The daemon therefore runs
:class:`calibration.online.OnlineCalibrator` in a ``multiprocessing`` *spawn* child:

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
"""
from __future__ import annotations

import logging
import math
import multiprocessing as mp
import queue
import threading
import time
from collections import Counter
from typing import Any, Callable

from fusion.motion_model import MotionParams

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
    }


def _release_type() -> type:
    try:
        from calibration.online import Release
    except ImportError:  # a daemon without the calibrator package still applies remote releases
        import dataclasses
        from dataclasses import make_dataclass

        Release = make_dataclass("Release", ["t_s", "params", "log_likelihood", "accepted",
                                             "reason", "iterations",
                                             ("current_n_m_s", tuple, dataclasses.field(default=(0.0, 0.0)))],
                                 frozen=True)
    return Release


def _current_from(value: Any) -> tuple[float, float]:
    """Optional ``current_n_m_s`` (north, east, m/s) of a release; absent → (0, 0)."""
    if value is None:
        return (0.0, 0.0)
    n, e = (float(x) for x in value)
    return (n, e)


def release_from_dict(data: Any) -> Any:
    """Dict → ``calibration.online.Release``; ``ValueError`` when malformed."""
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
                       current_n_m_s=_current_from(data.get("current_n_m_s")))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"calibration_release: {e}") from e


def make_calibrator(cfg: Any, params0: MotionParams, seed: int) -> Any:
    """An :class:`OnlineCalibrator` from a :class:`service.config.ServiceConfig`.

    Without its own origin, the calibrator uses the service's mission origin, so its
    poses and the filter's share one NED frame.
    """
    import dataclasses

    import numpy as np

    from calibration.online import OnlineCalibrator

    online = cfg.calibrator.online
    if not (math.isfinite(online.origin_lat_deg) and math.isfinite(online.origin_lon_deg)):
        online = dataclasses.replace(online, origin_lat_deg=cfg.origin.lat_deg,
                                     origin_lon_deg=cfg.origin.lon_deg)
    return OnlineCalibrator(online, params0, cfg.motion.rpm_table, np.random.default_rng(seed))


def compact_imu(batch: list[Any]) -> list[Any]:
    """Runs of consecutive ``ImuSample`` → one ``ImuBatch`` each (order kept, nothing lost).

    The calibrator only bins the yaw rate, and does so vectorised for an ``ImuBatch``;
    one array object instead of hundreds of small ones is also ~50× cheaper to pickle
    across the process boundary (the demo's 100 Hz IMU at 20× real time is 2000 /s).
    """
    import numpy as np

    from fusion.samples import ImuBatch, ImuSample

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


# -- the child ----------------------------------------------------------------------
def _child_main(cfg: Any, params0: MotionParams, seed: int, in_q: Any, out_q: Any) -> None:
    """Child process: observe samples, send releases back; exits on ``_STOP``."""
    calibrator = make_calibrator(cfg, params0, seed)
    out_q.put(("ready", None))
    while True:
        try:
            batch = in_q.get(timeout=0.5)
        except queue.Empty:
            batch = []
        if isinstance(batch, str) and batch == _STOP:
            return
        for sample in batch:
            calibrator.observe(sample)
        for release in calibrator.poll():
            out_q.put(("release", release_to_dict(release)))


class CalibratorProcess:
    """Supervised calibrator child process with the calibrator interface of the runner.

    Parameters
    ----------
    cfg : ServiceConfig
        Whole config (the child needs ``calibrator`` and ``motion``).
    params0 : MotionParams
        Warm start.
    deliver : callable
        ``deliver(release)`` puts a release into the runner's input queue (non-blocking).
    batch_s : float
        Samples are sent to the child in batches at most this old (wall seconds), which
        keeps inter-process overhead off the fusion thread.
    """

    def __init__(self, cfg: Any, params0: MotionParams, deliver: Callable[[Any], None],
                 batch_s: float = 0.05) -> None:
        self.cfg = cfg
        self.params = params0
        self.deliver = deliver
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

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        with self._lock:
            self._spawn()

    def _spawn(self) -> None:
        seed = self.cfg.calibrator.seed + self.restarts
        self._in_q = self._ctx.Queue(maxsize=max(1, self.cfg.calibrator.queue_size // 10))
        self._out_q = self._ctx.Queue()
        self._proc = self._ctx.Process(target=_child_main, name="adaptnav-calibrator", daemon=True,
                                       args=(self.cfg, self.params, seed, self._in_q, self._out_q))
        self._proc.start()
        self._started_at = time.monotonic()
        self.state = "starting"
        self._reader = threading.Thread(target=self._read, args=(self._out_q, self._proc),
                                        name="calibrator-reader", daemon=True)
        self._reader.start()
        log.info("calibrator process started (pid %s)", self._proc.pid)

    def _read(self, out_q: Any, proc: Any) -> None:
        while not self._closed:
            try:
                kind, body = out_q.get(timeout=0.2)
            except queue.Empty:
                if not proc.is_alive():
                    return
                continue
            except (EOFError, OSError):
                return
            if kind == "ready":
                self.state = "running"
            elif kind == "release":
                try:
                    release = release_from_dict(body)
                except ValueError as e:
                    self.counters["bad_release"] += 1
                    log.warning("calibrator sent a bad release: %s", e)
                    continue
                if release.accepted and release.params is not None:
                    self.params = release.params  # warm start of a restart
                self.deliver(release)

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
        return []  # releases arrive through the runner's input queue

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

    from .bus import Bus, nonblocking_enqueue
    from .persistence import load_state

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
