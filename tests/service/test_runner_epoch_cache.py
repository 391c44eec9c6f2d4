"""The runner's output epochs with the next epoch's time and the half IMU period kept as numbers
(``_Loop._epoch_s``, ``_half_window_s``) are those of the previous formulation, which computed
both afresh from ``next_k`` and ``imu_period_s`` at every test: the same states at the same
epochs over streams with jitter, period changes, gaps, late and non-finite stamps, batches
split at epochs and a clock jump."""
from __future__ import annotations

import math
import random
import types

import numpy as np
import pytest

from adaptnav.fusion.samples import DepthSample, ImuBatch, ImuSample
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.runner import EPOCH_ROUNDING_S, Runner, _Loop


class _PreviousEpochs(_Loop):
    """The epoch tests as they were: nothing kept but ``next_k`` and ``imu_period_s`` (the kept
    epoch time stays -inf, so the callers' inlined pre-test always hands over to these)."""

    def _set_next_epoch(self, k):
        self.next_k = k

    def half_window_s(self):
        p = self.imu_period_s
        return 0.5 * p if p > 0.0 else EPOCH_ROUNDING_S

    def due_s(self):
        return self.epoch(self.next_k) - self.half_window_s()

    def flush_epochs_before(self, t_s):
        if self.next_k is None:
            self.next_k = math.ceil(t_s * self.rate - 1e-9)
        half = self.half_window_s()
        if self.epoch(self.next_k) + half < t_s:
            self.emit()
            self.next_k = max(self.next_k + 1, math.ceil((t_s - half) * self.rate - 1e-9))
            while self.epoch(self.next_k) + half < t_s:
                self.next_k += 1

    def emit_if_at_epoch(self, t_s):
        k = self.next_k
        if k is None:
            return
        half = self.half_window_s()
        if not t_s >= k / self.rate - half:
            return
        self.emit()
        self.next_k = max(k + 1, math.floor((t_s + half) * self.rate + 1e-9) + 1)


class _Estimator:
    """Its state is the time of the last sample it took (what epoch each state belongs to)."""

    initialized = True
    rejected: dict = {}

    def __init__(self):
        self.t = -math.inf

    def process(self, item):
        t = item.t_s
        t = float(t[-1]) if isinstance(item, ImuBatch) else float(t)
        if math.isfinite(t):
            self.t = max(self.t, t)
        return ()

    def nav_state(self):
        return types.SimpleNamespace(t_s=self.t)

    def inertial_velocity(self):
        return None

    def shift_time(self, delta_s):
        self.t += delta_s


class _Record:
    def __init__(self):
        self.t = []

    def on_nav(self, state):
        self.t.append(state.t_s)


def _stream(seed: int) -> list:
    """IMU singly and in batches at a rate that changes, jitter, gaps, depth samples (some late,
    some NaN), a forward clock jump."""
    rng = random.Random(seed)
    items, t = [], rng.uniform(0.0, 1.0)
    period = rng.choice([0.005, 0.01, 0.0125, 0.02])
    for _ in range(400):
        r = rng.random()
        if r < 0.03:
            period = rng.choice([0.0025, 0.005, 0.01, 0.0125, 0.02, 0.05])
        elif r < 0.06:
            t += rng.uniform(0.05, 2.0)  # a gap in the IMU
        elif r < 0.07:
            t += 1000.0 + rng.uniform(0.0, 1.0)  # the input's clock jumps
        n = rng.choice([1, 1, 3, 8, 25])
        ts = t + period * np.arange(1, n + 1) + rng.uniform(-1e-4, 1e-4) * np.ones(n)
        t = float(ts[-1])
        if n == 1:
            items.append(ImuSample(t, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)))
        else:
            items.append(ImuBatch(ts, np.tile([0.0, 0.0, -9.8], (n, 1)), np.zeros((n, 3))))
        for _ in range(rng.choice([0, 0, 1, 2])):
            dt = rng.choice([rng.uniform(0.0, 0.06), -rng.uniform(0.0, 0.05), math.nan])
            items.append(DepthSample(t + dt, 150000.0))
    return items


def _emitted(loop_type, items) -> tuple[list, int]:
    rec = _Record()
    runner = Runner(_Estimator(), [rec], LogClock(), None, output_rate_hz=10.0, door=None)
    if loop_type is not _Loop:
        old = runner.loop
        runner.loop = loop_type(old.estimator, old.sinks, old.clock, None, old.rate, None, None, None,
                                old.release_gate)
        runner.summary = runner.loop.summary
    for it in items:
        runner.feed(it)
        if it is items[len(items) // 2]:
            runner.loop.clock_jump(-3.0)  # the door's re-base, mid-stream
    runner.finish()
    assert not runner.summary.errors
    return rec.t, runner.loop.next_k


@pytest.mark.parametrize("seed", range(30))
def test_kept_epoch_times_emit_what_the_fresh_computation_did(seed):
    items = _stream(seed)
    new, new_k = _emitted(_Loop, items)
    old, old_k = _emitted(_PreviousEpochs, items)
    assert len(new) > 20
    assert new == old and new_k == old_k


def test_the_kept_numbers_follow_the_epoch_and_the_period():
    runner = Runner(_Estimator(), [], LogClock(), None, output_rate_hz=10.0, door=None)
    loop = runner.loop
    assert loop.half_window_s() == EPOCH_ROUNDING_S and loop._epoch_s == -math.inf
    runner.feed(ImuSample(0.95, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)))
    assert loop.next_k == 10 and loop.due_s() == 1.0 - EPOCH_ROUNDING_S
    runner.feed(ImuSample(0.96, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)))
    assert loop.half_window_s() == 0.5 * (0.96 - 0.95) and loop.due_s() == 1.0 - 0.5 * (0.96 - 0.95)
    loop.clock_jump(5.0)
    assert loop.next_k is None and loop._epoch_s == -math.inf
