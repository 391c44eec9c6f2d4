"""``LaggedCalibrator.quiet_until_s``: the data time below which a poll would return nothing
and do nothing, so that the runner may skip it. Never above the next due output, never
where the backend would have to sync (rounding of ``t − lag`` included), reset when the lag
shortens (the first side-scan ping) or the clock jumps."""
from __future__ import annotations

import math
import random

from adaptnav.calibration.online import Release
from adaptnav.calibration.sidescan import ObjectBatch
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator


def _just_below(quiet_until_s, t_s):
    """At ``t_s`` or below it by no more than the sync bound's margin (µs)."""
    return t_s - 1e-5 < quiet_until_s <= t_s


class _Sample:
    def __init__(self, t_s, kind="depth"):
        self.t_s = t_s
        self.KIND = kind


class _Scripted:
    """Has a release and an object batch of data time ``t_out`` once it sees that sample."""

    def __init__(self, t_out):
        self.t_out, self.out = t_out, []

    def observe(self, sample):
        if sample.t_s == self.t_out:
            self.out += [Release(self.t_out, MotionParams(), 0.0, True, "ok", 1), ObjectBatch(self.t_out, ())]

    def poll(self):
        out, self.out = self.out, []
        return out


class _Child:
    """A child process backend as the poll sees it: its progress and the syncs asked of it."""

    def __init__(self, caught_up_s):
        self.caught_up_s = caught_up_s
        self.ready = []
        self.synced = []

    def send(self, sample):
        pass

    def sync(self, t_s):
        if not self.caught_up_s > t_s:  # ProcessBackend.sync's early return, negated
            self.synced.append(t_s)


def test_quiet_until_the_next_output_can_be_due():
    cal = LaggedCalibrator(InlineBackend(_Scripted(100.0)), 60.0, 5.0)
    cal.observe(_Sample(100.0, "sonar"))
    assert cal.poll(100.0) == []
    assert _just_below(cal.quiet_until_s, 105.0)  # the product's τ + L_p (and any later output's)
    assert [o.KIND for o in cal.poll(105.0)] == ["sonar_objects"]
    cal.observe(_Sample(120.0))
    assert cal.poll(120.0) == []
    assert _just_below(cal.quiet_until_s, 125.0)  # an output of a later sample could be due then
    assert [o.KIND for o in cal.poll(160.0)] == ["calibration_release"]
    assert _just_below(cal.quiet_until_s, 125.0)  # nothing pending: an output of a later sample, L_p after it


class _Random:
    """Outputs (releases, object batches) at random samples, of their data time."""

    def __init__(self, seed):
        self.rng, self.out = random.Random(seed), []

    def observe(self, sample):
        r = self.rng.random()
        if r < 0.02:
            self.out.append(Release(sample.t_s, MotionParams(), 0.0, True, "ok", 1))
        elif r < 0.08:
            self.out.append(ObjectBatch(sample.t_s, ()))

    def poll(self):
        out, self.out = self.out, []
        return out


def _run(seed, skip):
    """A runner's loop over 3000 samples at 10 Hz (side-scan from the 500th): what each poll
    returned, by sample; ``skip``: polls below ``quiet_until_s`` left out, as the runner does."""
    rng = random.Random(seed + 1)
    cal = LaggedCalibrator(InlineBackend(_Random(seed)), 60.0, 5.0)
    got, t = [], 0.0
    for i in range(3000):
        t += rng.choice([0.0, 0.1, 0.1, 0.37])
        cal.observe(_Sample(t, "sonar" if i >= 500 and i % 10 == 0 else "depth"))
        if not (skip and t < cal.quiet_until_s):
            got += [(i, o.KIND, o.t_s) for o in cal.poll(t)]
    return got + [(-1, o.KIND, o.t_s) for o in cal.poll(math.inf)]


def test_skipping_the_quiet_polls_changes_no_output_nor_when_it_comes():
    for seed in range(5):
        every = _run(seed, skip=False)
        assert len(every) > 100
        assert _run(seed, skip=True) == every


def test_quiet_never_reaches_a_data_time_that_needs_a_sync():
    rng = random.Random(17)
    for _ in range(20000):
        tau = rng.choice([1.0, 1e3, 1e5, 1.7e9]) * rng.uniform(0.5, 2.0)
        lag = rng.choice([5.0, 60.0, 0.1, rng.uniform(0.0, 100.0)])
        child = _Child(tau)
        cal = LaggedCalibrator(child, lag)
        cal.poll(tau - 1.0)
        t = math.nextafter(cal.quiet_until_s, -math.inf)  # the latest data time it skips
        assert t - lag < tau, (tau, lag)  # the sync at t would have returned at once
        cal.poll(t)
        assert child.synced == []


def test_the_first_ping_shortens_the_lag_and_forgets_the_quiet_bound():
    child = _Child(150.0)
    cal = LaggedCalibrator(child, 60.0, 5.0)
    cal.poll(100.0)
    assert _just_below(cal.quiet_until_s, 155.0)  # the child's next output L_p after its progress
    cal.observe(_Sample(101.0, "sonar"))
    assert cal.quiet_until_s == -math.inf  # the sync bound it took was for L, too late by L_p
    cal.poll(101.0)
    assert 154.99 < cal.quiet_until_s < 155.0  # the sync at L_p, with its margin


def test_a_clock_jump_forgets_the_quiet_bound():
    cal = LaggedCalibrator(InlineBackend(_Scripted(100.0)), 60.0, 5.0)
    cal.observe(_Sample(100.0, "sonar"))
    cal.poll(100.0)
    cal.shift_time(-50.0)
    assert cal.quiet_until_s == -math.inf
    cal.poll(51.0)
    assert _just_below(cal.quiet_until_s, 55.0)  # the product moved with the data
