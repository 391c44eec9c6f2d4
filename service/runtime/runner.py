"""The one runner loop of adaptnav, shared by the live daemon and replay (DESIGN.md
"Service": ``run(source, estimator, calibrator, sinks, clock)``).

Live: a Zenoh/MAVLink queue source, :class:`~service.clock.LiveClock`, Zenoh and MAVLink
sinks. Replay: a log or simulator source, :class:`~service.clock.LogClock` (or
:class:`~service.clock.RealtimeClock`), file sinks. A calibrator release has one route
back, live and in replay: ``calibrator.poll(data_time_s)`` after every item, which returns
the releases computed at a data time τ with τ + latency ≤ the runner's data time (the
daemon's child :mod:`adaptnav.service.calibrator.live` and remote node
:mod:`adaptnav.service.calibrator.node`, replay's :mod:`adaptnav.service.calibrator.lagged`,
which waits for its calibrator so that the output does not depend on wall-clock timing).
Nothing else differs.

Per item, in the source's deterministic order (``adaptnav.fusion.samples.replay_order_key``):

1. output epochs ``t_k = k / output_rate_hz``: the state of ``t_k`` is the state at the IMU
   sample nearest ``t_k`` — the first one at or after ``t_k`` − half an IMU period — and
   goes to every sink's ``on_nav`` as soon as that sample is processed (an
   :class:`~fusion.samples.ImuBatch` is split there, so the rate is exact). Live, the state
   must not wait for the next sample to learn that the epoch is complete (one IMU period of
   latency): a stamp a hair past ``t_k`` (jitter, float rounding) belongs to ``t_k``
   all the same. An item more than half an IMU period past an epoch not yet emitted (a
   gap in the IMU) emits the current state for it first (before an IMU period is known:
   any item past it); a state is not re-emitted while it has not advanced, e.g. in a gap;
   with a calibrator, the estimator's free-inertial velocity (and its integral) at the
   first epoch of every second goes to ``calibrator.observe`` (its surge-noise evidence,
   :mod:`adaptnav.calibration.inertial`) and to the sinks' ``on_inertial`` (the daemon publishes it
   for a remote calibrator);
2. a sample goes to ``estimator.process`` (truth excepted), its aid statuses to the sinks'
   ``on_aid``, then, with a calibrator, to ``calibrator.observe(sample)`` (unless the sensor
   table says the calibrator has no use for its kind);
3. with a calibrator, after every item but truth: the runner's data time (the latest time
   of the items it admitted) goes to ``calibrator.poll(data_time_s)``; each release it
   returns is applied when accepted (``estimator.set_motion_params``) and goes to every
   sink either way. When the data end (not on a stop), ``poll(inf)``: every release
   computed from them. What else the calibrator returns by that route is data for the
   filter (side-scan object sightings, which it detects where its EM runs): it goes to
   ``estimator.process`` (aid statuses to the sinks, e.g. loop closures) and then back to
   ``calibrator.observe``.

A bad sample never stops the loop: the estimator rejects and counts it; an exception
raised while handling one item is logged, counted in health (``error:<kind>``) and the
loop goes on.
"""
from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Any, Iterable, Sequence

import numpy as np

from adaptnav.fusion.samples import ImuBatch, kinds

# what the calibrator has no use for is not sent to it (the sensor table says which)
_CALIBRATOR_UNUSED = frozenset(kinds(calibrator_uses=False))

from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.protocols import Calibrator, Clock, Estimator, RunAborted, Sink
from adaptnav.service.runtime.sinks import close_sinks as _close_sinks, sample_methods, sink_methods

log = logging.getLogger(__name__)

_QUIET_UNTIL = attrgetter("quiet_until_s")

# before an IMU period is known, a sample this close below an epoch is at it (s): the
# rounding of sample times
EPOCH_ROUNDING_S = 1e-9


@dataclass
class RunSummary:
    """What one run did (counts of items, not of messages in a file)."""

    items: int = 0
    samples_used: int = 0           # samples handed to the estimator (IMU counted one by one)
    imu_samples: int = 0
    nav_states: int = 0
    releases: int = 0
    releases_accepted: int = 0
    releases_refused: int = 0       # accepted by their calibrator, outside its bounds here
    errors: Counter = field(default_factory=Counter)   # exceptions by item kind
    first_t_s: float = math.nan
    last_t_s: float = math.nan
    wall_s: float = 0.0
    stopped: bool = False
    clock_jumps: list = field(default_factory=list)   # confirmed input clock jumps (s)

    @property
    def duration_s(self) -> float:
        return 0.0 if math.isnan(self.first_t_s) else self.last_t_s - self.first_t_s

    def to_dict(self) -> dict:
        return {
            "items": self.items, "samples_used": self.samples_used, "imu_samples": self.imu_samples,
            "nav_states": self.nav_states, "releases": self.releases,
            "releases_accepted": self.releases_accepted, "releases_refused": self.releases_refused,
            "errors": dict(sorted(self.errors.items())),
            "first_t_s": None if math.isnan(self.first_t_s) else self.first_t_s,
            "last_t_s": None if math.isnan(self.last_t_s) else self.last_t_s,
            "duration_s": self.duration_s, "wall_s": self.wall_s, "stopped": self.stopped,
            "clock_jumps": list(self.clock_jumps),
        }


def _stop_requested(stop: Any) -> bool:
    if stop is None:
        return False
    is_set = getattr(stop, "is_set", None)
    return bool(is_set() if callable(is_set) else stop())


class _Loop:
    """State of one :func:`run` call (kept out of the function for readability)."""

    def __init__(self, estimator, sinks, clock, calibrator, output_rate_hz, health, progress, door=None,
                 release_gate=None):
        self.estimator = estimator
        self.door = door
        self.release_gate = release_gate
        self.sinks = list(sinks)
        self.clock = clock
        self.calibrator = calibrator
        self.rate = float(output_rate_hz)
        self.health = health
        self.progress = progress
        self.summary = RunSummary()
        self.next_k: int | None = None     # index of the next output epoch k / rate
        self.last_emitted_t = -math.inf
        self._on_nav = sink_methods(self.sinks, "on_nav")
        self._on_aid = sink_methods(self.sinks, "on_aid")
        self._on_release = sink_methods(self.sinks, "on_release")
        self._on_sample_all = sink_methods(self.sinks, "on_sample")
        self._on_sample: dict[str, list] = {}  # by sample kind (sample_methods)
        self._on_first_sample = sink_methods(self.sinks, "on_first_sample")  # emptied after the first
        self._on_inertial = sink_methods(self.sinks, "on_inertial")
        self._next_inertial_t = -math.inf
        self.imu_period_s = math.nan
        self._last_imu_t = math.nan
        # what the epoch tests of every item read, kept as numbers (not recomputed per item):
        # the next epoch's time (s; -inf before one is known: the first item sets it) and
        # half_window_s() (the half IMU period, EPOCH_ROUNDING_S before it is known)
        self._epoch_s = -math.inf
        self._half_window_s = EPOCH_ROUNDING_S
        self.data_t = -math.inf  # the release rule's data time: latest time of an admitted item
        self._gaps_seen = 0  # the door's data gaps already logged
        self._quiet_until = (_QUIET_UNTIL if hasattr(calibrator, "quiet_until_s")
                             else lambda cal: -math.inf)

    # -- output epochs -------------------------------------------------------------------
    def epoch(self, k: int) -> float:
        return k / self.rate

    def _set_next_epoch(self, k: int | None) -> None:
        self.next_k = k
        self._epoch_s = -math.inf if k is None else self.epoch(k)

    def emit(self) -> None:
        est = self.estimator
        if not est.initialized:
            return
        state = est.nav_state()
        if not state.t_s > self.last_emitted_t:
            return
        self.last_emitted_t = state.t_s
        self.summary.nav_states += 1
        for f in self._on_nav:
            f(state)
        cal = self.calibrator
        if (cal is not None or self._on_inertial) and state.t_s >= self._next_inertial_t - 1e-6:
            # the calibrator's surge-noise evidence (calibration.inertial), once a second: it
            # carries the integral, so step means need nothing in between
            self._next_inertial_t = math.floor(state.t_s + 1e-6) + 1.0
            inertial = est.inertial_velocity()
            if inertial is not None:
                if cal is not None:
                    cal.observe(inertial)
                for f in self._on_inertial:
                    f(inertial)

    def half_window_s(self) -> float:
        """Half the IMU period (s): how far from an epoch its nearest IMU sample may lie
        (EPOCH_ROUNDING_S before the period is known)."""
        return self._half_window_s

    def due_s(self) -> float:
        """Time from which an IMU sample completes the next epoch (it is the nearest one)."""
        return self._epoch_s - self._half_window_s

    def flush_epochs_before(self, t_s: float) -> None:
        """Emit every epoch not yet emitted whose nearest IMU sample lies before ``t_s``
        (more than half an IMU period before it; the state is the same for all)."""
        if self.next_k is None:
            self._set_next_epoch(math.ceil(t_s * self.rate - 1e-9))
        half = self._half_window_s
        if self._epoch_s + half < t_s:
            self.emit()
            # skip the epochs of a gap in one step: the state did not change in between
            k = max(self.next_k + 1, math.ceil((t_s - half) * self.rate - 1e-9))
            while self.epoch(k) + half < t_s:
                k += 1
            self._set_next_epoch(k)

    def emit_if_at_epoch(self, t_s: float) -> None:
        """Emit now when the IMU sample just processed (at ``t_s``) is the one nearest the
        next epoch: the first at or after its :meth:`due_s`."""
        k = self.next_k
        if k is None:
            return
        half = self._half_window_s
        if not t_s >= self._epoch_s - half:  # due_s(), written out: every live IMU sample asks
            return
        self.emit()
        self._set_next_epoch(max(k + 1, math.floor((t_s + half) * self.rate + 1e-9) + 1))

    def imu_time(self, t_s: float) -> None:
        """Track the IMU period (the half window of :meth:`due_s`)."""
        dt = t_s - self._last_imu_t
        if 0.0 < dt < 1.0:
            self.imu_period_s = dt
            self._half_window_s = 0.5 * dt
        self._last_imu_t = t_s

    # -- the door ---------------------------------------------------------------------------
    def admit_batch(self, item: ImuBatch) -> ImuBatch | None:
        """The plausibility door (:mod:`adaptnav.fusion.plausibility`) for an IMU batch: ``None``
        when the whole batch is refused (counted there), else the batch with the refused samples
        removed. It runs before anything that follows data time (clock, epochs, health); a
        single sample's door is in :meth:`item` itself."""
        door = self.door
        t = np.asarray(item.t_s, dtype=float)
        f = np.asarray(item.specific_force_b_m_s2, dtype=float).reshape(-1, 3)
        w = np.asarray(item.omega_b_rad_s, dtype=float).reshape(-1, 3)
        keep, jump = door.check_batch(t, f, w)
        if keep is not None:
            if not keep.any():
                return None
            if not keep.all():
                item = ImuBatch(t[keep], f[keep], w[keep], item.source)
        if jump or len(door.gaps) != self._gaps_seen:
            self._door_events(jump)
        return item

    def _door_events(self, jump_s: float) -> None:
        """What the door reported besides its verdict: a clock jump (re-based), else a data gap
        (logged once)."""
        door = self.door
        if jump_s:
            self.clock_jump(jump_s)
        elif len(door.gaps) != self._gaps_seen:
            self._gaps_seen = len(door.gaps)
            kind, from_s, to_s = door.gaps[-1]
            log.warning("runner: no input for %.1f s of data (%s resumed at %.3f s): data missing, "
                        "navigation coasted through it", to_s - from_s, kind, to_s)

    def clock_jump(self, jump_s: float) -> None:
        """A confirmed jump of the input's clock: re-base the estimator, the clock, health and
        the calibrator's release schedule by ``jump_s`` and restart the output epochs at the
        new time."""
        log.warning("runner: input clock jumped by %+.3f s (stream continued consistently): re-based", jump_s)
        self.summary.clock_jumps.append(float(jump_s))
        for obj in (self.estimator, self.clock, self.health, self.calibrator):
            shift = getattr(obj, "shift_time", None)
            if shift is not None:
                shift(jump_s)
        self._set_next_epoch(None)
        self.last_emitted_t = -math.inf
        self._next_inertial_t = -math.inf
        self.data_t += jump_s

    # -- items ------------------------------------------------------------------------------
    def aid(self, statuses) -> None:
        if statuses:
            for f in self._on_aid:
                f(statuses)

    def release(self, rel: Any) -> None:
        self.summary.releases += 1
        if rel.accepted and rel.params is not None and self.release_gate is not None:
            why = self.release_gate(rel.params)
            if why:  # outside the calibrator's own bounds, wherever it came from: refused
                name = why.split("=")[0].strip("| ")
                self.summary.releases_refused += 1
                if self.health is not None:
                    self.health.on_rejected(f"release_refused:{name}")
                log.warning("runner: release at t=%.1f s refused: %s", rel.t_s, why)
                changes = {"accepted": False, "reason": f"refused by the filter: {why}"}
                rel = dataclasses.replace(rel, **changes) if dataclasses.is_dataclass(rel) else rel._replace(**changes)
        if rel.accepted and rel.params is not None:
            # a k_V the DVL measured is adopted as the speed scale (Estimator.set_motion_params)
            self.estimator.set_motion_params(rel.params, adopt_k_v=getattr(rel, "k_v_teacher", "") == "DVL")
            self.summary.releases_accepted += 1
        if self.health is not None:
            self.health.on_release(rel)
        for f in self._on_release:
            f(rel)

    def imu_batch(self, batch: ImuBatch) -> None:
        t = np.asarray(batch.t_s, dtype=float)
        ts = t.tolist()  # the single times read below as Python floats (numpy scalars cost more)
        n = len(ts)
        start = 0
        while start < n:
            t_first = ts[start]
            if math.isfinite(t_first):
                # emit epochs the first remaining sample is past
                if self._epoch_s + self._half_window_s < t_first:  # flush's own test: no call per batch
                    self.flush_epochs_before(t_first)
                # the piece ends with the sample that completes the next epoch (bisect_left on
                # the floats: searchsorted's probes and comparisons, without its call)
                stop = bisect.bisect_left(ts, self.due_s()) + 1
                if stop <= start:  # (min(max(stop, start + 1), n) without the calls)
                    stop = start + 1
                if stop > n:
                    stop = n
            else:  # not a batch of a well-behaved source: the estimator judges the rest
                stop = n
            piece = batch if (start == 0 and stop >= n) else ImuBatch(
                t[start:stop], batch.specific_force_b_m_s2[start:stop], batch.omega_b_rad_s[start:stop], batch.source)
            statuses = self.estimator.process(piece)
            if statuses:  # (aid(), without its call)
                for f in self._on_aid:
                    f(statuses)
            t_last = ts[stop - 1]
            if math.isfinite(t_last):
                if stop - start >= 2:
                    self._last_imu_t = ts[stop - 2]
                self.imu_time(t_last)
                self.emit_if_at_epoch(t_last)
            self.summary.imu_samples += stop - start
            self.summary.samples_used += stop - start
            start = stop
        if self.health is not None and n:
            self.health.on_sample("imu", ts[-1], n)

    def releases_due(self, data_t_s: float) -> None:
        """The runner's data time reached ``data_t_s``: the calibrator's releases due by it.
        A calibrator's ``quiet_until_s`` (optional) is a data time below which its poll returns
        nothing and does nothing: not called then (replay's polled once per ~10 items)."""
        if data_t_s > self.data_t:  # False for NaN
            self.data_t = data_t_s
        if self.data_t < self._quiet_until(self.calibrator):
            return
        for out in self.calibrator.poll(self.data_t):
            if out.KIND == "calibration_release":
                self.release(out)
            else:
                self.product(out)

    def product(self, item: Any) -> None:
        """A calibrator's side product that is data for the filter (side-scan objects,
        :mod:`adaptnav.calibration.sidescan`): to the estimator like a sample, its aid
        statuses to the sinks, then back to the calibrator (with what the estimator
        made of it)."""
        self.aid(self.estimator.process(item))
        self.calibrator.observe(item)

    def item(self, item: Any) -> None:
        kind = getattr(item, "KIND", None)
        if kind == "imu_batch" and isinstance(item, ImuBatch):
            self._batch_item(item)
            return
        # a single sample (the live path's every item): its door here (a batch's: admit_batch)
        door = self.door
        if door is not None:
            ok, jump = door.check(item)
            if not ok:
                return
            if jump or len(door.gaps) != self._gaps_seen:
                self._door_events(jump)
        t_s = float(item.t_s)
        finite = math.isfinite(t_s)
        if finite:
            self.clock.wait_until(t_s)
        cal = self.calibrator
        try:
            # the sample (was a method of its own: a call per item)
            if kind is None:
                kind = item.KIND  # (an item without one fails here, counted as before)
            t_item_s = item.t_s  # as it is, for the epochs and health
            # flush_epochs_before's own test first: no call for the item that finds no epoch due
            # (true before the first epoch is known; a NaN time goes to the estimator, which rejects it)
            if self._epoch_s + self._half_window_s < t_item_s and finite:
                self.flush_epochs_before(t_item_s)
            try:
                if kind != "truth":
                    statuses = self.estimator.process(item)
                    if statuses:  # (aid(), without its call: most samples answer none or one)
                        for f in self._on_aid:
                            f(statuses)
                    self.summary.samples_used += 1
                    if kind == "imu":
                        self.summary.imu_samples += 1
                        if finite:
                            self.imu_time(t_item_s)
                            self.emit_if_at_epoch(t_item_s)
            finally:  # bookkeeping after the nav state is out (live: its latency), counted either way
                if self.health is not None:
                    self.health.on_sample(kind, t_item_s)
            if self._on_first_sample:
                for f in self._on_first_sample:
                    f(item)
                self._on_first_sample = []
            try:
                on_sample = self._on_sample[kind]
            except KeyError:  # (the first sample of its kind)
                on_sample = self._on_sample[kind] = sample_methods(self._on_sample_all, kind)
            for f in on_sample:
                f(item)
            if cal is not None and kind not in _CALIBRATOR_UNUSED:
                cal.observe(item)
        finally:  # the one route of a release back (module docstring), after a failed item too
            if cal is not None and kind != "truth":
                # releases_due's quiet test first, without its call (replay's calibrator is quiet
                # for ~9 items of 10): the data time as it sets it, the poll when due
                data_t = t_s if t_s > self.data_t else self.data_t  # (a NaN stamp leaves it)
                if data_t < self._quiet_until(cal):
                    self.data_t = data_t
                else:
                    self.releases_due(t_s)
        if finite:
            self._reached(t_s, t_s)

    def _batch_item(self, item: ImuBatch) -> None:
        """:meth:`item` of an IMU batch."""
        if len(item) == 0:
            return
        if self.door is not None:
            item = self.admit_batch(item)
            if item is None:
                return
        t_s = float(item.t_s[0])
        t_last = float(item.t_s[-1])
        if math.isfinite(t_s):
            self.clock.wait_until(t_s)
        cal = self.calibrator
        try:
            self.imu_batch(item)
            if cal is not None:
                cal.observe(item)
        finally:  # the one route of a release back (module docstring), after a failed item too
            if cal is not None:
                self.releases_due(t_last)
        if math.isfinite(t_last):
            self._reached(t_s, t_last)

    def _reached(self, t_s: float, t_last: float) -> None:
        """The summary's first and last data times and the progress, after an item from ``t_s``
        to ``t_last`` (finite)."""
        s = self.summary
        if not (s.first_t_s <= t_s):
            s.first_t_s = t_s if math.isfinite(t_s) else t_last
        if not (s.last_t_s >= t_last):
            s.last_t_s = t_last
        if self.progress is not None:
            self.progress(t_last)


def default_release_gate(calibrator_config: Any = None) -> Any:
    """``params -> reason`` against the calibrator's bounds (``calibrator_config``, default
    :class:`~adaptnav.calibration.online.CalibratorConfig`), or ``None`` without the
    calibration package."""
    try:
        from adaptnav.calibration.online import CalibratorConfig, gate_reason
    except ImportError:
        return None
    bounds = calibrator_config if calibrator_config is not None else CalibratorConfig()
    return lambda params: gate_reason(params, bounds)


def door_for(estimator: Any, forward_jump_is_gap: Any = None) -> Any:
    """The plausibility door of ``estimator`` (its config's bounds, origin and depth
    conversion), or ``None`` for an estimator without a filter config;
    ``forward_jump_is_gap`` as :class:`~adaptnav.fusion.plausibility.Door`'s (a source's or a
    clock's method of that name)."""
    from adaptnav.fusion.plausibility import Door

    cfg = getattr(estimator, "config", None)
    bounds = getattr(cfg, "plausibility", None)
    if bounds is None:
        return None
    return Door(bounds, getattr(estimator, "origin", None), cfg.depth.water_density_kg_m3,
                cfg.depth.atmospheric_pressure_pa, forward_jump_is_gap=forward_jump_is_gap)


class Runner:
    """The loop of :func:`run` item by item, for a caller that drives it itself (the live
    daemon feeds each bus sample in the Zenoh thread it arrives on when the runner is
    idle, and queued items from its runner thread; the caller serialises the calls).

    Parameters are those of :func:`run` without ``source``, ``stop`` and ``close_sinks``;
    ``qsize`` is the source's queue depth (for health), if any.
    """

    def __init__(self, estimator: Estimator, sinks: Sequence[Sink], clock: Clock,
                 calibrator: Calibrator | None = None, *, output_rate_hz: float = 10.0,
                 health: Health | None = None, progress: Any = None, door: Any = None,
                 release_gate: Any = None, qsize: Any = None) -> None:
        if not (output_rate_hz > 0 and math.isfinite(output_rate_hz)):
            raise ValueError(f"output_rate_hz must be a positive number, got {output_rate_hz}")
        if door is None:
            # live, the clock tells a dropout from a step of the data's clock (LiveClock)
            door = door_for(estimator, getattr(clock, "forward_jump_is_gap", None))
        if health is not None:
            health.estimator_rejected = getattr(estimator, "rejected", None)
            health.door_rejected = getattr(door, "rejected", None)
            if calibrator is not None and health.calibrator_state == "off":
                health.calibrator_state = "in-process"
        if release_gate is None:
            release_gate = default_release_gate()
        self.loop = _Loop(estimator, sinks, clock, calibrator, output_rate_hz, health, progress, door, release_gate)
        # the estimator's work that no output of the item depends on, once they are out
        self._settle = getattr(estimator, "settle", None)
        self.summary = self.loop.summary
        self.health = health
        self.qsize = qsize
        self._wall0 = time.monotonic()

    def feed(self, item: Any) -> None:
        """Handle one item; an exception is logged and counted (``error:<kind>``), never raised."""
        loop, health = self.loop, self.health
        loop.summary.items += 1
        try:
            loop.item(item)
            if self._settle is not None:
                self._settle()
        except RunAborted:  # not one bad item: every later one would fail too, or go wrong
            raise
        except Exception as exc:  # one bad item must not stop navigation
            kind = getattr(item, "KIND", type(item).__name__)
            loop.summary.errors[kind] += 1
            if health is not None:
                health.on_rejected(f"error:{kind}")
            if loop.summary.errors[kind] <= 10:
                log.exception("runner: error handling %s item at t=%s: %s", kind,
                              getattr(item, "t_s", "?"), exc)
        if health is not None and self.qsize is not None:
            health.queue_depth = int(self.qsize())

    def finish(self, releases: bool = True) -> None:
        """The data ended: every release computed from them (``releases``: not on a stop),
        the last epochs up to the end of the data, then the final state itself."""
        loop = self.loop
        if releases and loop.calibrator is not None:
            loop.releases_due(math.inf)
        if loop.next_k is not None and math.isfinite(loop.summary.last_t_s):
            loop.flush_epochs_before(loop.summary.last_t_s + 1e-9)
            loop.emit()

    def close(self, close_sinks: bool = True) -> RunSummary:
        """The run's wall time; every sink's ``close()`` (``close_sinks``)."""
        self.summary.wall_s = time.monotonic() - self._wall0
        if close_sinks:
            _close_sinks(self.loop.sinks)
        return self.summary


def run(source: Iterable[Any], estimator: Estimator, sinks: Sequence[Sink], clock: Clock,
        calibrator: Calibrator | None = None, *, output_rate_hz: float = 10.0, stop: Any = None,
        health: Health | None = None, progress: Any = None, close_sinks: bool = True,
        door: Any = None, release_gate: Any = None) -> RunSummary:
    """Run ``source`` through ``estimator`` into ``sinks`` (see the module docstring).

    Parameters
    ----------
    source : iterable
        Samples (``adaptnav.fusion.samples``), :class:`~fusion.samples.ImuBatch` runs and
        calibrator releases, in replay order. Optional ``qsize()`` gives the queue depth.
    estimator : fusion.eskf.Estimator
        ``process(sample) -> list[AidStatus]``, ``set_motion_params``, ``nav_state()``,
        ``initialized``, ``rejected`` (Counter by reason).
    sinks : sequence of :class:`adaptnav.service.runtime.sinks.Sink`
    clock : :class:`adaptnav.service.runtime.clock.Clock`
    calibrator : :class:`adaptnav.service.runtime.protocols.Calibrator`, optional
        ``observe(sample)``, and ``poll(data_time_s) -> [Release]`` after every item (the live
        child, the remote node, replay's lagged calibrator alike).
    output_rate_hz : float
        Nav-state output rate in data time (Hz).
    stop : threading.Event or callable, optional
        Checked between items; when set the loop ends (sinks are still closed).
    health : Health, optional
        Accumulates counters; gets a live view of ``estimator.rejected``.
    progress : callable, optional
        Called with the data time reached after each item (progress bars).
    close_sinks : bool
        Call every sink's ``close()`` at the end.
    door : adaptnav.fusion.plausibility.Door, optional
        The plausibility check in front of everything; by default built from
        ``estimator.config.plausibility`` (when the estimator has one).
    release_gate : callable, optional
        ``params -> reason`` ("" when acceptable): a release outside these bounds is not
        applied, counted (``release_refused:<name>``) and passed on as not accepted. Default:
        the calibrator's own bounds at their defaults
        (:func:`adaptnav.calibration.online.gate_reason`).

    Returns
    -------
    RunSummary
    """
    runner = Runner(estimator, sinks, clock, calibrator, output_rate_hz=output_rate_hz, health=health,
                    progress=progress, door=door, release_gate=release_gate,
                    qsize=getattr(source, "qsize", None))
    try:
        feed = runner.feed
        for item in source:
            if stop is not None and _stop_requested(stop):  # (no call per item without one)
                runner.summary.stopped = True
                break
            feed(item)
        else:
            runner.finish(releases=not _stop_requested(stop))
    finally:
        runner.close(close_sinks)
    return runner.summary
