"""The runner's item paths with the plausibility door (runner._Loop.item: a single sample's
door test in item(), a batch's through admit_batch): what each item leads to — the estimator's
samples, the clock, the calibrator's polls and their data times, the sinks' aid statuses
and samples, a clock jump's re-base, a data gap's warning, the summary's first and last
times — on a stream with refused samples, a confirmed jump, a gap, truth, NaN stamps, an
empty batch and a batch with a refused sample."""
from __future__ import annotations

import logging
import math
import types

import numpy as np

from adaptnav.fusion.plausibility import Door, PlausibilityConfig
from adaptnav.fusion.samples import DepthSample, ImuBatch, ImuSample, RpmSample, TruthSample
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.runner import Runner

_F, _W = (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)


class _Estimator:
    """Takes every sample; a depth answers one status (a marker), other kinds none."""

    initialized = True
    rejected: dict = {}

    def __init__(self):
        self.taken: list = []
        self.shifts: list = []
        self.t = -math.inf

    def process(self, item):
        self.taken.append((item.KIND, len(item) if isinstance(item, ImuBatch) else 1))
        if isinstance(item, ImuBatch):
            self.t = float(item.t_s[-1])
        return [("status", item.t_s)] if item.KIND == "depth" else []

    def nav_state(self):
        return types.SimpleNamespace(t_s=self.t)

    def inertial_velocity(self):
        return None

    def shift_time(self, delta_s):
        self.shifts.append(delta_s)


class _Calibrator:
    def __init__(self):
        self.polls: list = []
        self.observed: list = []

    def observe(self, item):
        self.observed.append(item.KIND)

    def poll(self, data_t_s):
        self.polls.append(data_t_s)
        return []


class _Sink:
    def __init__(self):
        self.aid: list = []
        self.samples: list = []

    def on_aid(self, statuses):
        self.aid.append(statuses)

    def on_sample(self, sample):
        self.samples.append(sample.KIND)


def _truth(t):
    return TruthSample(t, (0.0,) * 3, (0.0,) * 3, (1.0, 0.0, 0.0, 0.0), (0.0,) * 3, 1.0)


def test_items_through_the_door(caplog):
    est, cal, sink = _Estimator(), _Calibrator(), _Sink()
    # a forward jump of more than 100 s is data missing, a shorter one a step of the clock
    door = Door(PlausibilityConfig(jump_confirm_samples=3), None, forward_jump_is_gap=lambda a, b: b - a > 100.0)
    runner = Runner(est, [sink], LogClock(), cal, output_rate_hz=10.0, door=door)
    items = [
        ImuSample(10.0, _F, _W),
        DepthSample(10.05, 150000.0),
        RpmSample(10.06, 1e9),                      # refused (rpm_range): nothing follows from it
        _truth(10.07),                              # passes, never to the estimator nor a poll
        DepthSample(math.nan, 150000.0),            # a NaN stamp: to the estimator (it rejects it)
        ImuBatch(np.array([]), np.zeros((0, 3)), np.zeros((0, 3))),  # empty: nothing
        ImuBatch(np.array([10.1, 10.2, 10.3]), np.array([_F, (0.0, 0.0, 1e6), _F]), np.zeros((3, 3))),
        DepthSample(40.0, 150000.0),                # 30 s ahead: refused (time_ahead) ...
        DepthSample(40.1, 150000.0),
        DepthSample(40.2, 150000.0),                # ... until the third: a clock jump of +29.9 s
        ImuSample(40.3, _F, _W),
        ImuSample(400.0, _F, _W),                   # 360 s on: ahead, then a gap once confirmed
        ImuSample(400.01, _F, _W),
        ImuSample(400.02, _F, _W),
        DepthSample(400.05, 150000.0),
    ]
    with caplog.at_level(logging.WARNING, logger="adaptnav.service.runtime.runner"):
        for it in items:
            runner.feed(it)
    s = runner.summary
    assert not s.errors
    # the batch without its refused sample, split at the epoch of 10.2 s
    assert est.taken == [("imu", 1), ("depth", 1), ("depth", 1), ("imu_batch", 1), ("imu_batch", 1), ("depth", 1),
                         ("imu", 1), ("imu", 1), ("depth", 1)]
    assert door.rejected["rpm_range"] == 1 and door.rejected["imu_acc_range"] == 1
    assert door.rejected["time_ahead"] == 4  # 40.0, 40.1, 400.0, 400.01
    assert est.shifts == [40.2 - 10.3] and s.clock_jumps == est.shifts  # the jump re-based once
    assert door.gaps == [("imu", 40.3, 400.02)]
    assert len([m for m in caplog.messages if "no input for" in m]) == 1
    # a poll after every admitted item but truth, at the data time reached (a NaN stamp: unchanged)
    assert cal.polls == [10.0, 10.05, 10.05, 10.3, 40.2, 40.3, 400.02, 400.05]
    assert cal.observed.count("imu_batch") == 1 and "truth" not in cal.observed
    assert [st[0][1] for st in sink.aid][::2] == [10.05, 40.2]  # the depths' statuses, one call each
    assert len(sink.aid) == 4 and math.isnan(sink.aid[1][0][1])
    assert sink.samples == ["imu", "depth", "truth", "depth", "depth", "imu", "imu", "depth"]
    assert (s.first_t_s, s.last_t_s) == (10.0, 400.05)
    assert (s.items, s.samples_used, s.imu_samples) == (15, 9, 5)
