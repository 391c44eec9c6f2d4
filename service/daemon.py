"""The live navigation daemon (``adaptnav run``), DESIGN.md "Service".

Threads and processes::

    Zenoh callbacks ──decode──┬─(runner idle)──► runner (owns the Estimator, one
    MAVLink bridge ──convert──┴─► input queue ──► runner thread    thread at a time)
                                       ▲              │ on_nav  → adaptnav/<v>/nav/state (10 Hz)
    calibrator process ─releases───────┘              │ on_aid  → latest per source
          ▲ samples (batched, non-blocking) ◄─────────┘ observe
    housekeeping thread (1 Hz): health + aid statuses published, calibrator supervised
    (restart with backoff), learned state persisted, systemd watchdog fed.

- The runner is :class:`adaptnav.service.runtime.runner.Runner` (the loop of
  :func:`~adaptnav.service.runtime.runner.run`, item by item) with a
  :class:`~service.clock.LiveClock` — the same loop as replay. A sample (bus or MAVLink)
  that finds the queue empty and the runner idle is run in the thread that received it
  (no thread hand-off on the live path: IMU→nav latency, CPU); everything else is queued
  for the runner thread.
- Releases are applied between samples in data order (stamped with their data time).
- Learned params + slow filter states are snapshotted *in the runner* (whichever thread
  drives it: the estimator is not shared) and written by the housekeeping thread atomically
  (:mod:`adaptnav.service.runtime.persistence`), periodically and on shutdown; restored on start.
- Python's garbage collector: what start-up made is frozen out of its passes, and it
  collects right after a nav state is published, not on the next epoch's path
  (:mod:`adaptnav.service.runtime.collector`; health ``gc``).
- SIGTERM/SIGINT → clean shutdown. With ``NOTIFY_SOCKET`` set (systemd ``Type=notify``)
  READY/WATCHDOG/STOPPING are sent on a plain datagram socket.
"""
from __future__ import annotations

import dataclasses
import heapq
import json
import logging
import math
import os
import queue
import signal
import socket
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from adaptnav import kernels
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.samples import SENSORS, SOURCE_PRIORITY, ImuBatch

from adaptnav.service.compose import make_estimator, make_live_calibrator
from adaptnav.service.runtime.protocols import Calibrator
from adaptnav.service.transport import codec
from adaptnav.service.transport.bus import Bus, encode_sample, message
from adaptnav.service.runtime.clock import LiveClock
from adaptnav.service.runtime.collector import CollectorPacing
from adaptnav.service.config import ServiceConfig, config_dict, log_effective
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.memory import BurstTrimmer
from adaptnav.service.runtime.persistence import load_state, save_state, state_dir_problem
from adaptnav.service.runtime.rehearsal import EpochRehearsal
from adaptnav.service.runtime.sinks import Sink, geo_time_fields
from adaptnav.service.runtime.wakeup import WakeupLatencyRequest

log = logging.getLogger(__name__)

# sensor kind → the aid source whose status says why nothing is fused when it is silent
SENSOR_AID_SOURCE = {s.kind: s.aid_source for s in SENSORS if s.aid_source}


# physical bounds of persisted slow states: accelerometer bias (m/s²), gyro bias (rad/s),
# k_speed (–); a state file beyond them was written by something broken or hostile
_MAX_ACC_BIAS_M_S2, _MAX_GYRO_BIAS_RAD_S, _K_SPEED_RANGE = 2.0, 0.2, (0.25, 4.0)


def slow_states_reason(slow: dict, max_current_m_s: float) -> str:
    """Empty when persisted slow states are physically plausible, else why not."""
    try:
        checks = (("current_n_m_s", max_current_m_s), ("bias_acc_b_m_s2", _MAX_ACC_BIAS_M_S2),
                  ("bias_gyro_b_rad_s", _MAX_GYRO_BIAS_RAD_S))
        for name, bound in checks:
            value = np.asarray(slow[name], dtype=float)
            if not (np.all(np.isfinite(value)) and np.all(np.abs(value) <= bound)):
                return f"{name} {value.tolist()} beyond ±{bound:g}"
        k = float(slow["k_speed"])
        if not _K_SPEED_RANGE[0] <= k <= _K_SPEED_RANGE[1]:
            return f"k_speed {k!r} outside {_K_SPEED_RANGE}"
    except (KeyError, TypeError, ValueError) as e:
        return f"malformed {e}"
    return ""


def sd_notify(state: str) -> bool:
    """Send ``state`` (e.g. ``"READY=1"``) to systemd if ``NOTIFY_SOCKET`` is set."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]  # abstract namespace socket
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(addr)
            s.sendall(state.encode())
        return True
    except OSError as e:
        log.debug("sd_notify(%s) failed: %s", state, e)
        return False


def warm_up_filter(cfg: ServiceConfig, params: MotionParams | None = None) -> float:
    """Run a throwaway filter over a few seconds of synthetic rest data so that the numba
    kernels are compiled (or loaded from their cache) before READY, not on the first live
    samples; also what ``adaptnav warmup`` runs at install time. Returns the seconds spent."""
    from adaptnav.fusion.samples import DepthSample, DvlSample, HeadingSample, ImuSample, RpmSample

    t0 = time.monotonic()
    est = make_estimator(cfg, params)
    g = 9.80665
    n = cfg.filter.alignment.n_samples + 400
    for k in range(n):
        t = k * 0.005
        est.process(ImuSample(t, (0.0, 0.0, -g), (0.0, 0.0, 0.0)))
        if k % 20 == 0:
            for s in (HeadingSample(t, 0.0), DepthSample(t, 101325.0 + 1025.0 * g),
                      RpmSample(t, 0.0), DvlSample(t, (0.0, 0.0, 0.0))):
                est.process(s)
        if k % 20 == 10 and est.initialized:
            est.nav_state().to_dict()
    est.slow_states()
    from adaptnav.service.runtime.runner import door_for

    door = door_for(est)  # the runner's door in front of it (its IMU-run test is a kernel too)
    if door is not None:
        t = np.arange(1, 11) * 0.005
        door.check_batch(t, np.tile([0.0, 0.0, -g], (10, 1)), np.zeros((10, 3)))
    elapsed = time.monotonic() - t0
    log.info("filter warmed up in %.1f s", elapsed)
    return elapsed


class QueueSource:
    """The runner's input queue, put back in data order across transports (``qsize`` for
    health).

    Samples reach the queue over paths of different latency (the MAVLink bridge thread,
    Zenoh callbacks of other drivers): a side-scan ping or a USBL fix can overtake the IMU
    samples before it. The runner assumes data order — a later sample completes an output
    epoch — so such an overtaking sample would emit the epoch with a state short of it and
    the epochs in between would be lost. A sample *ahead* of the IMU clock is therefore
    held until the IMU passes it (replay order, ``adaptnav.fusion.samples.replay_order_key``), or
    for at most ``max_hold_s`` of wall time (an IMU-less configuration, a stalled link).
    Late samples pass at once (the estimator fuses or rejects them). ``counters``:
    ``held`` (samples reordered), ``released_on_timeout``.

    The runner thread waits (:meth:`wait`) and hands every queued item to the runner
    (:meth:`drain`); an item that need not wait behind queued ones goes through
    :meth:`take` directly (the daemon's bus and MAVLink samples, :meth:`Daemon._from_transport`).
    """

    IMU_KINDS = ("imu", "imu_batch")

    def __init__(self, q: "queue.Queue[Any]", stop: threading.Event, max_hold_s: float = 0.5) -> None:
        self.q = q
        self.stop = stop
        self.max_hold_s = max_hold_s
        self.counters: Counter[str] = Counter()
        self._held: list[tuple] = []  # heap of (t_s, priority, seq, wall_in, sample)
        self._seq = 0
        self._imu_t = -math.inf
        self._imu_wall = -math.inf
        self._wake = threading.Event()  # set when an item is queued
        # monotonic time the runner last came back for input (processing or waiting on
        # an empty queue): the watchdog's proof that the runner is not wedged
        self.heartbeat_s = time.monotonic()

    def qsize(self) -> int:
        return self.q.qsize() + len(self._held)

    def put(self, item: Any) -> bool:
        """Queue ``item`` without blocking; False when the queue is full."""
        try:
            self.q.put_nowait(item)
        except queue.Full:
            return False
        self._wake.set()
        return True

    def _pop_held_before(self, t_s: float):
        while self._held and self._held[0][0] < t_s:
            yield heapq.heappop(self._held)[-1]

    def _split_at_held(self, batch: Any, last: float):
        """A batch (rising finite times) with held samples inside its span: its pieces and
        each held sample where it goes among single samples — before the first IMU sample
        past its time. Yields all but the last piece, and returns that."""
        t = np.asarray(batch.t_s, dtype=float)
        if t.ndim != 1 or not np.isfinite(t).all() or not (np.diff(t) > 0).all():
            return batch  # not a burst's run: the estimator judges it as it comes
        f, w = np.asarray(batch.specific_force_b_m_s2), np.asarray(batch.omega_b_rad_s)
        start = 0
        while self._held and self._held[0][0] < last:
            cut = int(np.searchsorted(t, self._held[0][0], side="right"))  # samples at or before it go first
            if cut > start:
                yield ImuBatch(t[start:cut], f[start:cut], w[start:cut], batch.source)
                start = cut
            yield from self._pop_held_before(float(t[start]))
        return ImuBatch(t[start:], f[start:], w[start:], batch.source) if start else batch

    def _expired(self, now: float):
        while self._held and now - self._held[0][3] > self.max_hold_s:
            self.counters["released_on_timeout"] += 1
            yield heapq.heappop(self._held)[-1]

    def _order(self, item: Any, now: float):
        kind = getattr(item, "KIND", None)
        if kind in self.IMU_KINDS:
            t_s = item.t_s
            if kind == "imu" and isinstance(t_s, (int, float)):  # the live case: one sample, no numpy
                first = last = float(t_s) if math.isfinite(t_s) else None
            else:
                t = np.asarray(t_s, dtype=float).ravel()
                t = t[np.isfinite(t)]
                first, last = (float(t[0]), float(t[-1])) if t.size else (None, None)
            if first is not None:
                yield from self._pop_held_before(first)
                if kind == "imu_batch" and self._held and self._held[0][0] < last:
                    item = yield from self._split_at_held(item, last)
                self._imu_t = max(self._imu_t, last)
                self._imu_wall = now
            yield item
            return
        t_s = getattr(item, "t_s", None)
        if (kind is not None and isinstance(t_s, (int, float)) and math.isfinite(t_s) and t_s > self._imu_t
                and now - self._imu_wall <= self.max_hold_s):
            self.counters["held"] += 1
            self._seq += 1
            heapq.heappush(self._held, (t_s, SOURCE_PRIORITY.get(kind, 50), self._seq, now, item))
            return
        yield item  # releases, late or on-time samples, NaN times (the estimator rejects them)

    def take(self, item: Any, feed: Any) -> None:
        """``item`` (arrived now) to ``feed`` in data order: with the held samples it
        passes before it, or held itself; then the held samples whose time is up."""
        now = time.monotonic()
        self.heartbeat_s = now
        for out in self._order(item, now):
            feed(out)
        if self._held:
            for out in self._expired(now):
                feed(out)

    def wait(self) -> None:
        """Until an item is queued, or the next look at the held ones (at most 0.1 s)."""
        self.heartbeat_s = time.monotonic()
        self._wake.wait(0.05 if self._held else 0.1)
        self._wake.clear()  # before the queue is read: a later put wakes the next wait

    def drain(self, feed: Any) -> None:
        """Every queued item to ``feed`` through :meth:`take` (until ``stop``), then the
        held samples whose time is up."""
        while not self.stop.is_set():
            try:
                item = self.q.get_nowait()
            except queue.Empty:
                break
            self.take(item, feed)
        for out in self._expired(time.monotonic()):
            feed(out)


class LiveBurst:
    """Samples between output epochs (bus or MAVLink), run in one burst just before the
    epoch's sample.

    Live, a sample arrives every few ms and the daemon sleeps in between, so each one finds
    the interpreter's and the filter's code and data gone from the caches (``adaptnav bench
    service`` ``cold_call_*``: 6–30× the back-to-back cost on a shared virtual machine) and
    pays its whole path cold. Held from the first sample after an epoch (IMU or aid) to the
    IMU sample just before the one that completes the next epoch, then run in data order — each run of
    IMU samples as one :class:`ImuBatch` (the estimator's compiled propagation, which the
    runner splits at epochs) — they pay it about once per epoch: the daemon's CPU at 200 Hz
    10.7 → 8.0 % of a core (``adaptnav bench service --only latency``). The epoch's own
    sample still runs alone, as it arrives: what a client waits for is unchanged, and so are
    the states, bit for bit (``tests/service/test_live_burst.py``). A held aid waits at most an output period, or
    :attr:`MAX_HOLD_S` when the IMU stops (the runner thread runs it then).
    """

    MAX_ITEMS = 512
    MAX_HOLD_S = 0.25

    def __init__(self) -> None:
        self.items: list[Any] = []
        self.since_s = 0.0  # monotonic time the oldest held item came

    def __len__(self) -> int:
        return len(self.items)

    def hold(self, item: Any, loop: Any) -> bool:
        """Keep ``item`` for the burst (True); False: run the burst, then ``item``."""
        items = self.items
        if len(items) >= self.MAX_ITEMS:
            return False
        aid_inside_burst = bool(items) and getattr(item, "KIND", None) != "imu"  # held: its place kept
        if not aid_inside_burst:
            period = loop.imu_period_s
            t_s = getattr(item, "t_s", None)
            # not the epoch's sample, nor the one before it (the burst runs there, off the
            # epoch's path: the bound lies half a period before it, between two samples); a
            # stream whose period or epochs are not known yet runs as it comes. An aid opens
            # a burst by the same rule: one that comes right after an epoch's state (a sensor
            # sampled on the epoch) would otherwise run as the state leaves and take the core
            # its delivery needs
            if (loop.next_k is None or not period > 0.0 or not isinstance(t_s, (int, float))
                    or not t_s < loop.due_s() - period):
                return False
        if not items:
            self.since_s = time.monotonic()
        items.append(item)
        return True

    def run(self, take: Any, feed: Any) -> None:
        """The held items to ``take(item, feed)`` in arrival order, each run of consecutive
        IMU samples (one source, rising finite times) as one batch."""
        items, self.items = self.items, []
        i, n = 0, len(items)
        while i < n:
            first = items[i]
            j = i + 1
            if getattr(first, "KIND", None) == "imu" and math.isfinite(first.t_s):
                t, source = first.t_s, first.source  # one run: one source, rising times
                while (j < n and getattr(items[j], "KIND", None) == "imu" and items[j].source == source
                       and items[j].t_s > t):
                    t = items[j].t_s
                    j += 1
            if j - i == 1:
                take(first, feed)
            else:
                take(ImuBatch.of(items[i:j]), feed)
            i = j


class BusSink(Sink):
    """Runner sink of the daemon: publishes nav states, keeps the latest of everything.

    Runs in the runner (its thread or a Zenoh callback): only quick work (JSON + ``put``)
    happens here.
    """

    def __init__(self, daemon: "Daemon") -> None:
        self.d = daemon
        self.origin = daemon.cfg.origin.geo()
        self.latest_payload: bytes | None = None  # the last nav state as published
        self.latest_aid: dict[str, Any] = {}
        self.nav_count = 0
        self.state_finite = True  # the last nav state's position and velocity were finite

    @property
    def latest_state(self) -> dict | None:
        """The last nav state as published (its JSON read back), or ``None``."""
        payload = self.latest_payload
        return None if payload is None else json.loads(payload)

    def document(self, state: Any) -> tuple[dict, bytes]:
        """The nav state's message: its fields, and the payload as published."""
        # the vectors as arrays: orjson writes them (NavState.to_dict's lists cost a
        # Python float per element of the covariance, on the latency path)
        doc = state.fields()
        bridge = self.d.bridge
        # latitude/longitude (deg) and altitude (m) beside local NED, from the mission origin
        # (to_geodetic's numbers in Python floats: no arrays on the latency path)
        north_m, east_m, down_m = doc["pos_n_m"].tolist()
        lat, lon = self.origin.to_geodetic_ne(north_m, east_m)
        doc["lat_deg"], doc["lon_deg"], doc["alt_m"] = math.degrees(lat), math.degrees(lon), self.origin.alt_m - down_m
        if bridge is not None:  # UNIX time when the MAVLink link gives a wall-clock reference
            doc.update(geo_time_fields(state, bridge.converter.time.unix_of))
        return doc, message("nav_state", doc)

    def on_nav(self, state: Any) -> None:
        doc, payload = self.document(state)
        pos = doc["pos_n_m"]
        bridge = self.d.bridge
        self.latest_payload = payload
        self.nav_count += 1
        self.d.bus.put(self.d.bus.keys.nav_state, payload)
        self.d.collector.after_output()  # the state is out: the collector's turn, off its path
        self.state_finite = bool(np.isfinite(pos).all() and np.isfinite(doc["vel_n_m_s"]).all())
        if bridge is not None:
            bridge.offer_nav(state)  # ODOMETRY on its fixed schedule
        if self.d._snapshot_due.is_set():
            self.d._take_snapshot(state.t_s)

    def on_aid(self, statuses: list) -> None:
        for s in statuses:
            self.latest_aid[s.source] = s

    def on_release(self, release: Any) -> None:
        if release.accepted and release.params is not None:
            self.d.params = release.params
            self.d._snapshot_due.set()  # persist what was learned soon
        if self.d.cfg.calibrator.location == "process":  # remote: the node publishes
            self.d.bus.put(self.d.bus.keys.params, codec.encode(release))


class InertialSink(Sink):
    """A remote calibrator node gets the filter's free-inertial velocity over the bus (its
    surge-noise evidence, :mod:`adaptnav.calibration.inertial`); a sink of its own, in the
    runner only then: the runner computes that velocity once a second for whoever takes it."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def on_inertial(self, sample: Any) -> None:
        self.bus.put(self.bus.keys.nav_inertial, encode_sample(sample))


class Daemon:
    """The live service. ``start()``, then ``stop()`` (or :func:`serve` for the CLI).

    Parameters
    ----------
    cfg : ServiceConfig
    """

    def __init__(self, cfg: ServiceConfig) -> None:
        cfg = cfg.resolved(autopilot_thrust=cfg.mavlink.enabled)  # the thrust is the autopilot's PWM
        self.cfg = cfg
        self.stop_event = threading.Event()
        self._snapshot_due = threading.Event()
        self._snapshot: tuple[float, MotionParams, dict] | None = None
        self.queue: queue.Queue = queue.Queue(maxsize=cfg.health.queue_size)
        self.source = QueueSource(self.queue, self.stop_event)
        # one thread at a time drives the runner (it owns the estimator): the runner thread
        # or a receiving thread (_from_transport); set while the runner thread runs
        self._runner_lock = threading.Lock()
        self._runner: Any = None
        # where the samples went (_from_transport): held for a burst, run on receipt, queued
        # for the runner thread (it was busy); in the health report as "live_path"
        self.live_path: Counter[str] = Counter()
        self.burst = LiveBurst()  # samples held for the next burst (under _runner_lock)
        self.overflow: Counter[str] = Counter()
        self.health = Health(silent_after_s=cfg.health.sensor_timeout_s)
        self.clock = LiveClock()
        # with the MAVLink bridge the thrust is the autopilot's PWM (motion.prior "auto")
        self.params, self.motion_prior = cfg.motion.initial_params(autopilot_thrust=cfg.mavlink.enabled)
        self.restored = False
        self.bridge: Any = None
        self.foxglove: Any = None  # LiveServer when [foxglove] is enabled
        self._saved_once = False
        self.calibrator: Calibrator | None = None  # CalibratorProcess, RemoteCalibrator
        self.bus: Bus | None = None  # type: ignore[assignment]
        self.sink = BusSink(self)
        self.summary: Any = None
        self.latest_health: dict = {}
        self._threads: list[threading.Thread] = []
        self._health_lock = threading.Lock()
        self.collector = CollectorPacing()
        self._malformed_reported: Counter[str] = Counter()
        self._overflow_reported: Counter[str] = Counter()
        self._trimmer = BurstTrimmer()
        # idle CPUs kept quick to wake while the daemon runs, or around each output epoch (held
        # in start())
        outputs_cfg = cfg.outputs
        self.wakeup: WakeupLatencyRequest | None = (
            WakeupLatencyRequest(outputs_cfg.cpu_wakeup_latency_us, outputs_cfg.cpu_wakeup_scope)
            if outputs_cfg.cpu_wakeup_latency_us >= 0 else None)
        # the output epoch's path rehearsed before its IMU sample comes (started in start())
        self.rehearsal: EpochRehearsal | None = (
            EpochRehearsal(self._runner_lock, self._rehearse, outputs_cfg.rehearsal_lead_s,
                           window=self.wakeup if outputs_cfg.cpu_wakeup_scope == "epochs" else None)
            if outputs_cfg.rehearsal_lead_s > 0.0 else None)

    # -- construction ---------------------------------------------------------------------
    def _make_estimator(self) -> Any:
        from adaptnav.service.runtime.runner import default_release_gate

        restored = load_state(self.cfg.state_dir)
        gate = default_release_gate(self.cfg.calibrator.online)
        why = gate(restored.params) if gate is not None and restored is not None and restored.params else ""
        if why:  # a state file is input like any other: held to the calibrator's bounds
            log.warning("persisted params refused (%s); starting from the configured ones", why)
            self.health.on_rejected(f"persisted_params_refused:{why.split('=')[0].strip('| ')}")
            restored = dataclasses.replace(restored, params=None)
        if restored is not None and restored.slow_states:
            why = slow_states_reason(restored.slow_states, self.cfg.calibrator.online.max_current_m_s)
            if why:
                log.warning("persisted slow states refused (%s); starting from defaults", why)
                self.health.on_rejected(f"persisted_states_refused:{why.split(' ')[0]}")
                restored = dataclasses.replace(restored, slow_states={})
        if restored is not None and restored.params is not None:
            self.params = restored.params
        if restored is not None and restored.slow_states.get("pos_saved_unix_s") is not None:
            # the wall time since the position was saved: at least that long the vehicle may
            # have moved (the autopilot's clock may have restarted meanwhile)
            slow = dict(restored.slow_states)
            slow["pos_min_elapsed_s"] = max(0.0, time.time() - float(slow["pos_saved_unix_s"]))
            restored = dataclasses.replace(restored, slow_states=slow)
        # side-scan sightings come only from the daemon's own calibrator child: without it
        # pings cost the filter nothing (no navigation record, no clones)
        cal = self.cfg.calibrator
        est = make_estimator(self.cfg, self.params, objects=cal.enabled and cal.location == "process")
        if restored is not None:
            try:
                if restored.slow_states:
                    est.restore_slow_states(restored.slow_states)
                self.restored = True
                log.info("restored learned state from %s (data time %.1f s)", self.cfg.state_dir, restored.t_s)
            except (KeyError, TypeError, ValueError) as e:
                log.warning("persisted slow states not usable (%s); starting from defaults", e)
                self.restored = restored.params is not None
        return est

    def _warm_up(self) -> None:
        warm_up_filter(self.cfg, self.params)

    def enqueue(self, item: Any) -> None:
        """Non-blocking put into the runner's input queue (overflow counted)."""
        if not self.source.put(item):
            self.overflow["queue_overflow"] += 1

    def _from_transport(self, item: Any) -> None:
        """A sample in the thread that received it (a Zenoh callback, the MAVLink bridge's
        thread): handled right here when nothing is queued and no other thread is in the
        runner, else queued behind what is. The live IMU stream then reaches the filter
        without a hand-off to the runner thread (a wake-up per sample, and the GIL passed
        back and forth between the two threads); the lock keeps one thread at a time in the
        runner, and queued items go first, so the order is the queue's. Between epochs it
        is held for the next burst (:class:`LiveBurst`)."""
        # the queue's deque: its len() without the queue's lock
        lock, queued, path, rehearsal = self._runner_lock, self.queue.queue, self.live_path, self.rehearsal
        arrived_s = rehearsal.clock() if rehearsal is not None else 0.0
        # a rehearsal holding the lock is short: waited for, not queued behind (the epoch's sample)
        if not queued and (lock.acquire(blocking=False)
                           or (rehearsal is not None and rehearsal.holding and lock.acquire(timeout=0.005))):
            try:
                runner = self._runner
                if runner is not None and not queued and not self.stop_event.is_set():
                    burst = self.burst
                    if burst.hold(item, runner.loop):
                        path["held_for_burst"] += 1
                    else:
                        path["run_on_receipt"] += 1
                        if burst.items:
                            burst.run(self.source.take, runner.feed)
                        self.source.take(item, runner.feed)
                        if rehearsal is not None and getattr(item, "KIND", None) == "imu":
                            rehearsal.plan(arrived_s, item.t_s, runner.loop)
                    return
            finally:
                lock.release()
        path["queued"] += 1
        self.enqueue(item)

    def _rehearse(self, dt_s: float) -> bool:
        """An output epoch's path, ``dt_s`` ahead, rehearsed (:mod:`~adaptnav.service.runtime.rehearsal`):
        the estimator's and the nav state's message; nothing changes, nothing is sent. Under
        the runner lock. False when there is no navigation to rehearse yet."""
        state = self.estimator.rehearse_epoch(dt_s) if self._runner is not None else None
        if state is None:
            return False
        self.sink.document(state)
        return True

    def start(self) -> None:
        cfg = self.cfg
        log_effective(cfg)
        log.info("motion model: %s", self.motion_prior)
        self._warm_up()
        self.estimator = self._make_estimator()
        problem = state_dir_problem(cfg.state_dir)
        if problem:  # navigation goes on; what it learns is lost at the next restart
            log.warning("state dir %s is not writable (%s): the learned motion model and the last position "
                        "will not survive a restart", cfg.state_dir, problem)
            self.health.state_save_error = f"state dir not writable at start: {problem}"
        self.bus = Bus(cfg.zenoh, cfg.vehicle.name)
        self.bus.subscribe_samples(self._from_transport)
        if cfg.calibrator.enabled and cfg.calibrator.location == "remote":
            from adaptnav.service.calibrator.node import RemoteCalibrator

            self.calibrator = RemoteCalibrator(self.bus)
            self.health.calibrator_state = "remote"
        self.bus.queryable("state", lambda: self.sink.latest_payload or message("nav_state", {"valid": False}))
        self.bus.queryable("params", lambda: message("motion_params", {
            "params": self.params.to_dict(), "restored": self.restored}))
        self.bus.queryable("config", lambda: message("service_config", config_dict(cfg)))
        self.bus.queryable("health", lambda: message("health", self._health_report()))
        if cfg.calibrator.enabled and cfg.calibrator.location == "process":
            self.calibrator = make_live_calibrator(cfg, self.params)
            self.calibrator.start()
        if cfg.mavlink.enabled:
            self._start_bridge()
        if cfg.foxglove.enabled:
            from adaptnav.service.runtime.foxglove import LiveServer

            self.foxglove = LiveServer(cfg.foxglove.host, cfg.foxglove.port, cfg.origin.geo(),
                                       name=f"adaptnav {cfg.vehicle.name}")
            log.info("foxglove live view on ws://%s:%d", cfg.foxglove.host, self.foxglove.port)
        runner = threading.Thread(target=self._run, name="adaptnav-runner", daemon=True)
        house = threading.Thread(target=self._housekeeping, name="adaptnav-housekeeping", daemon=True)
        self._threads = [runner, house]
        for t in self._threads:
            t.start()
        if self.wakeup is not None:  # (before the rehearsals, which tighten it around the epochs)
            self.wakeup.hold()  # refused: logged, in the health report, and on without it
        if self.rehearsal is not None:
            self.rehearsal.start()
        self.collector.start()
        self.collector.freeze()  # all that start-up made, out of every later collection
        sd_notify("READY=1\nSTATUS=navigating")
        log.info("adaptnav daemon up: vehicle %s, zenoh %s", cfg.vehicle.name, cfg.zenoh.mode)

    def _start_bridge(self) -> None:
        from adaptnav.service.transport.mavlink_bridge import MavlinkBridge

        # the bridge thread converts and runs (or queues) its samples; nav output goes back
        # through BusSink
        # its reset_counter persists next to the learned state: a restart is a reset
        self.bridge = MavlinkBridge(None, self._from_mavlink, self.cfg.origin.geo(), self.cfg.mavlink,
                                    state_path=Path(self.cfg.state_dir) / "mavlink_bridge.json",
                                    output_rate_hz=self.cfg.mavlink.output_rate_hz)

    def _from_mavlink(self, sample: Any) -> None:
        """A sample from the autopilot: to the runner, and on the bus for the other nodes
        (``adaptnav record`` then records every sample the daemon fuses, whatever transport
        it came in on, and a replay of the recording reproduces the live solution). Run in
        the bridge's thread as a bus sample is in its callback (:meth:`_from_transport`):
        handing each autopilot sample to the runner thread woke it ~150 times a second."""
        self._from_transport(sample)
        try:
            self.bus.publish_sample_to_others(sample)
        except Exception as e:  # noqa: BLE001 — the bus must never cost the filter a sample
            self.overflow["republish_failed"] += 1
            log.debug("re-publishing a MAVLink sample failed: %s", e)

    def sinks(self) -> list:
        """The runner's sinks: the bus (nav state, latest aid statuses, releases), the
        lifecycle log, the Foxglove view when on, the free-inertial velocity for a remote
        calibrator when there is one."""
        from adaptnav.service.runtime.events import LifecycleLog

        cal = self.cfg.calibrator
        return ([self.sink, LifecycleLog()] + ([self.foxglove.sink] if self.foxglove is not None else [])
                + ([InertialSink(self.bus)] if cal.enabled and cal.location == "remote" else []))

    def _run(self) -> None:
        """The runner thread: queued items (samples that found the runner busy), bursts
        the IMU left held, and the release of held ones; samples that find it idle are run
        in the thread that received them (:meth:`_from_transport`)."""
        from adaptnav.service.runtime.runner import Runner, default_release_gate

        runner = Runner(self.estimator, self.sinks(), self.clock, self.calibrator,
                        output_rate_hz=self.cfg.outputs.nav_rate_hz, health=self.health,
                        release_gate=default_release_gate(self.cfg.calibrator.online))
        # (no qsize: the health report reads the queue depth itself, not after every item)
        with self._runner_lock:
            self._runner = runner
        try:
            burst = self.burst
            while not self.stop_event.is_set():
                self.source.wait()
                with self._runner_lock:
                    # the held burst goes before anything queued after it (their order), and
                    # does not wait long for an IMU sample that may not come
                    if burst.items and (self.queue.queue or time.monotonic() - burst.since_s > burst.MAX_HOLD_S):
                        burst.run(self.source.take, runner.feed)
                    self.source.drain(runner.feed)
        finally:
            with self._runner_lock:  # no bus callback in the runner from here on (stop_event)
                if self.burst.items:
                    self.burst.run(self.source.take, runner.feed)
                self._runner = None
                runner.finish(releases=False)  # the epochs up to the last data, the last state
                self.summary = runner.close(close_sinks=False)

    # -- housekeeping ---------------------------------------------------------------------
    def _take_snapshot(self, t_s: float) -> None:
        """In the runner: copy what persistence needs."""
        self._snapshot_due.clear()
        try:
            self._snapshot = (t_s, self.params, self._slow_states())
        except Exception:
            log.exception("slow_states() failed; persisting params only")
            self._snapshot = (t_s, self.params, {})

    def _slow_states(self) -> dict:
        """The estimator's slow states; a position in them is stamped with the wall time."""
        slow = self.estimator.slow_states()
        if "pos_n_m" in slow:
            slow["pos_saved_unix_s"] = time.time()
        return slow

    def _persist(self) -> None:
        snap = self._snapshot
        if snap is None:
            return
        self._snapshot = None
        try:
            save_state(self.cfg.state_dir, snap[0], snap[1], snap[2], self.cfg.vehicle.name)
        except OSError as e:  # counted in health (persistence.failures): an operator must see it
            log.error("could not persist learned state to %s: %s", self.cfg.state_dir, e)
            self.health.on_state_saved(f"{type(e).__name__}: {e.strerror or e}")
            return
        self.health.on_state_saved()
        # the first save and the last (shutdown) at INFO; the periodic ones at DEBUG
        level = logging.INFO if (not self._saved_once or self.stop_event.is_set()) else logging.DEBUG
        self._saved_once = True
        log.log(level, "state saved to %s (data time %.1f s, k_V %.4g)", self.cfg.state_dir, snap[0], snap[1].k_v,
                extra={"event": {"event": "state_saved", "t_s": snap[0]}})

    def _health_report(self) -> dict:
        with self._health_lock:  # housekeeping thread and health queries
            return self._health_report_locked()

    def _health_report_locked(self) -> dict:
        # merge counters kept outside the runner thread (bus callbacks, queue overflow)
        for source, reported in ((self.bus.malformed, self._malformed_reported),
                                 (self.overflow, self._overflow_reported)):
            for key, n in list(source.items()):
                delta = n - reported[key]
                if delta:
                    name = key if source is self.overflow else f"malformed:{key}"
                    self.health.on_rejected(name, delta)
                    reported[key] = n
        for _ in range(3):  # the runner may add a sensor while we iterate
            try:
                rep = self.health.report(self.clock.now_data_s())
                break
            except RuntimeError:
                continue
        else:
            return self.latest_health
        rep["queue_depth"] = self.source.qsize()
        rep["reordered"] = dict(self.source.counters)  # samples held until the IMU passed them
        rep["live_path"] = dict(self.live_path)
        rep["gc"] = self.collector.report()  # paced after outputs vs CPython's own (automatic_*)
        if self.wakeup is not None:  # the CPU wake-up latency bound: asked for, held, why not
            rep["cpu_wakeup_latency"] = self.wakeup.report()
        if self.rehearsal is not None:  # the output epochs' rehearsals: done, late, busy, no_room
            rep["epoch_rehearsal"] = dict(self.rehearsal.counts)
        if self.bridge is not None:  # what the MAVLink link did, lost or refused, counted
            rep["mavlink"] = self.bridge.health()
        side_scan = getattr(self.calibrator, "side_scan", None)
        if side_scan is not None:  # what the calibrator's object front end made of the pings
            rep["calibrator"]["side_scan"] = side_scan
        rep["nav_states"] = self.sink.nav_count
        rep["runner_alive"] = bool(self._threads and self._threads[0].is_alive())
        rep["runner_heartbeat_age_s"] = round(time.monotonic() - self.source.heartbeat_s, 3)
        rep["state_finite"] = self.sink.state_finite
        # per aid, what its recent innovations say of the covariance (the validity's nis:<source>)
        integrity = getattr(self.estimator, "integrity_report", None)
        rep["integrity"] = integrity() if integrity is not None else {}
        resets = list(getattr(self.estimator, "position_resets", ()))
        rep["position_resets"] = {"count": len(resets), "last": [
            {"t_s": t, "source": src, "size_m": round(size, 3)} for t, src, size in resets[-3:]]}
        imu = rep["sensors"].get("imu")
        # the IMU model the filter runs on ("attitude": no IMU fast enough, the attitude's
        # increments drive the strapdown) and why (a plain read of a frozen record)
        model = getattr(self.estimator, "imu_model", None)
        rep["imu_grade"], rep["imu_grade_why"] = (model.grade, model.why) if model is not None else (None, None)
        attitude_driven = rep["imu_grade"] == "attitude" and self.sink.nav_count
        rep["status"] = ("navigating on the attitude (no IMU fast enough to integrate)" if attitude_driven else
                         "not navigating: no IMU" if imu is None or imu["silent"] else
                         "navigating" if self.sink.nav_count else "aligning")
        cal = self.calibrator
        if cal is not None:
            rep["calibrator"].update(state=cal.state, pid=cal.pid(), restarts=cal.restarts,
                                     dropped_samples=cal.dropped)
            late = getattr(cal, "late_report", None)  # (a remote node's come when they come)
            if late is not None:
                rep["calibrator"]["late"] = late()
        # the filter's kernels: compiled ahead of time, or just in time and why (a damaged build:
        # `adaptnav warmup` builds it again; the filter runs either way, slower to start)
        rep["kernels"] = {"ahead_of_time": kernels.using_aot(), "build": kernels.loaded_build(),
                          "problem": kernels.aot_error}
        rep["params"] = self.params.to_dict()
        rep["motion_prior"] = self.motion_prior
        rep["type"] = "health"
        return rep

    def _aid_statuses(self, report: dict) -> dict[str, dict]:
        """Latest status per aid source; a silent sensor's source says ``stale`` and why."""
        from adaptnav.fusion.status import AidStatus

        out = {src: s.to_dict() for src, s in list(self.sink.latest_aid.items())}
        now = report.get("t_s")
        for kind in report.get("silent", []):
            src = SENSOR_AID_SOURCE.get(kind)
            if src is None:
                continue
            age = report["sensors"][kind]["age_s"]
            status = AidStatus(float(now) if now is not None else math.nan, src, (), (), (), math.nan,
                               False, "stale").to_dict()
            status["detail"] = f"no {kind} sample for {age:.1f} s (limit {self.cfg.health.sensor_timeout_s} s)"
            out[src] = status
        return out

    def _housekeeping(self) -> None:
        cfg = self.cfg
        period_s = 1.0 / cfg.outputs.health_rate_hz
        aid_period_s = 1.0 / cfg.outputs.aid_rate_hz
        watchdog_s = int(os.environ.get("WATCHDOG_USEC", "0")) / 2e6
        next_persist = time.monotonic() + cfg.persistence.period_s
        next_aid = time.monotonic()
        tick = min(period_s, aid_period_s, watchdog_s or period_s, 0.25)
        next_health = time.monotonic()
        while not self.stop_event.wait(tick):
            now = time.monotonic()
            try:  # the housekeeping thread must outlive one failing report or save
                if self.calibrator is not None:
                    self.calibrator.supervise()
                if now >= next_health:
                    next_health = now + period_s
                    self.latest_health = rep = self._health_report()
                    self.bus.publish(self.bus.keys.health, "health", rep)
                    if self.foxglove is not None:
                        self.foxglove.sink.on_health(rep)
                    if now >= next_aid:
                        next_aid = now + aid_period_s
                        for src, doc in self._aid_statuses(rep).items():
                            self.bus.put(self.bus.keys.aid(src), json.dumps(doc).encode())
                if self._trimmer.check(self.source.qsize()):
                    self.health.memory_trims += 1  # a burst drained: its heap given back
                if now >= next_persist:
                    next_persist = now + cfg.persistence.period_s
                    self._snapshot_due.set()  # the runner snapshots at its next nav output
                self._persist()
            except Exception:
                self.health.on_rejected("error:housekeeping")
                log.exception("housekeeping failed")
            if watchdog_s and self.runner_sound(watchdog_s):
                sd_notify("WATCHDOG=1")  # only while the runner is sound: systemd restarts it otherwise

    def runner_sound(self, wedged_after_s: float) -> bool:
        """The runner thread lives, came back for input within ``wedged_after_s`` (it
        processes its queue or waits on an empty one — no IMU is not a reason to restart)
        and its last state was finite: the condition for feeding the systemd watchdog."""
        return bool(self._threads and self._threads[0].is_alive()
                    and time.monotonic() - self.source.heartbeat_s < wedged_after_s
                    and self.sink.state_finite)

    # -- shutdown -------------------------------------------------------------------------
    def abort(self) -> None:
        """Undo a start that failed half-way: close what was opened; nothing ran, so
        nothing is persisted."""
        for obj, method in ((self.bridge, "close"), (self.foxglove, "stop"), (self.calibrator, "stop"),
                            (self.bus, "close")):
            if obj is not None:
                try:
                    getattr(obj, method)()
                except Exception as e:  # noqa: BLE001 — best effort on the way out
                    log.debug("abort: %s.%s: %s", type(obj).__name__, method, e)
        self.stop_event.set()
    def stop(self, timeout_s: float = 5.0) -> None:
        if self.stop_event.is_set() and not self._threads:
            return
        sd_notify("STOPPING=1")
        self.stop_event.set()
        if self.rehearsal is not None:
            self.rehearsal.stop(timeout_s)
        for t in self._threads:
            t.join(timeout_s)
        if self.bridge is not None:
            self.bridge.close()
        if self.foxglove is not None:
            self.foxglove.stop()
        if self.calibrator is not None:
            self.calibrator.stop()
        # the runner has ended: the estimator is ours to read
        try:
            t_s = self.estimator.nav_state().t_s if self.estimator.initialized else math.nan
            self._snapshot = (t_s if math.isfinite(t_s) else 0.0, self.params, self._slow_states())
        except Exception:
            log.exception("final snapshot failed")
            self._snapshot = (0.0, self.params, {})
        self._persist()
        if self.bus is not None:
            self.bus.close()
        self.collector.stop()
        if self.wakeup is not None:
            self.wakeup.release()
        self._threads = []
        log.info("adaptnav daemon stopped")


def startup_error(e: BaseException) -> str:
    """One line of why the daemon could not start (a busy port, an unreachable router):
    Zenoh's error text without its Rust source locations."""
    import re

    text = re.sub(r"\s+at /\S+", "", str(e)).replace("[", "").replace("]", "").strip().rstrip(".")
    return f"{type(e).__name__}: {text}" if not isinstance(e, OSError) else text


def serve(cfg: ServiceConfig) -> int:
    """Run the daemon until SIGTERM/SIGINT. Exit 2 (one logged line, no traceback) when it
    cannot start: a Zenoh port in use, a router that does not answer, the Foxglove port in use."""
    import sys

    # A thread holding the GIL delays the runner by up to the switch interval (5 ms by
    # default): 1 ms keeps the nav-output latency tail short at negligible cost.
    sys.setswitchinterval(0.001)
    daemon = Daemon(cfg)
    stop = threading.Event()

    def on_signal(signum, frame):  # noqa: ARG001
        log.info("signal %s: shutting down", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    import zenoh

    try:
        daemon.start()
    except (zenoh.ZError, OSError) as e:
        log.error("cannot start: %s", startup_error(e), extra={"event": {"event": "startup_failed"}})
        daemon.abort()
        return 2
    try:
        while not stop.wait(0.5):
            if not daemon._threads[0].is_alive():
                log.error("runner thread ended unexpectedly")
                daemon.stop()
                return 1
    finally:
        daemon.stop()
    return 0


def serve_calibrator(cfg: ServiceConfig) -> int:
    """``--calibrator-only``: the calibrator as its own bus node until SIGTERM/SIGINT."""
    import zenoh

    from adaptnav.service.calibrator.node import run_node

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    sd_notify("READY=1\nSTATUS=calibrating")
    try:
        return run_node(cfg, stop)
    except (zenoh.ZError, OSError) as e:
        log.error("cannot start the calibrator node: %s", startup_error(e))
        return 2
