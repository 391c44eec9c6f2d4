"""The runner's single-sample path (runner._Loop.item, the sample's handling written into it)
when handling an item fails part way: an item without a KIND, an estimator that raises, a
sink that raises — the summary's errors, health, the calibrator's observations and polls and
the summary's first and last times are what they were with the sample as a method of its own."""
from __future__ import annotations

import math
import types

from adaptnav.fusion.samples import DepthSample, HeadingSample, RpmSample
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.runner import Runner

from .test_runner_item_door import _Calibrator, _truth  # (polls and observed kinds)


class _Estimator:
    initialized = False  # no nav states: the sample path only
    rejected: dict = {}

    def __init__(self):
        self.taken: list = []

    def process(self, item):
        if item.KIND == "heading":
            raise ValueError("heading refused loudly")
        self.taken.append((item.KIND, item.t_s))
        return [("status", item.t_s)]


class _Sink:
    def __init__(self):
        self.aid: list = []
        self.samples: list = []

    def on_aid(self, statuses):
        if statuses[0][1] == 3.0:
            raise RuntimeError("sink failed")
        self.aid.append(statuses[0][1])

    def on_sample(self, sample):
        self.samples.append((sample.KIND, sample.t_s))


def test_failures_part_way_through_a_sample():
    est, cal, sink, health = _Estimator(), _Calibrator(), _Sink(), Health()
    runner = Runner(est, [sink], LogClock(), cal, output_rate_hz=10.0, health=health, door=None)
    assert runner.loop.door is None
    items = [
        types.SimpleNamespace(t_s=1.0),   # no KIND: fails where the sample is read, polled all the same
        DepthSample(2.0, 150000.0),
        HeadingSample(2.5, 0.1),          # the estimator raises: health counted it, nothing after
        DepthSample(3.0, 150000.0),       # a sink raises on its status: no sample sinks, no observe
        _truth(3.5),                      # never polled
        DepthSample(4, 150000.0),         # an int stamp goes on as it is (health's last time)
        RpmSample(4.5, 1000.0),           # the calibrator observes it (not a depth)
    ]
    for it in items:
        runner.feed(it)
    s = runner.summary
    assert dict(s.errors) == {"SimpleNamespace": 1, "heading": 1, "depth": 1}
    assert s.items == 7 and s.samples_used == 3  # (the sink raised before the depth at 3 s was counted)
    assert est.taken == [("depth", 2.0), ("depth", 3.0), ("depth", 4), ("rpm", 4.5)]
    assert cal.polls == [1.0, 2.0, 2.5, 3.0, 4.0, 4.5]
    assert cal.observed == ["rpm"]  # (depths and truth: the calibrator has no use for them)
    assert sink.aid == [2.0, 4, 4.5]
    assert sink.samples == [("depth", 2.0), ("truth", 3.5), ("depth", 4), ("rpm", 4.5)]
    report = health.report()["sensors"]
    assert report["heading"]["count"] == 1 and report["depth"]["count"] == 3 and report["truth"]["count"] == 1
    assert type(report["depth"]["last_seen_t_s"]) is int
    assert health.rejected["error:heading"] == 1 and health.rejected["error:SimpleNamespace"] == 1
    # the failed items did not reach the summary's times; the truth did
    assert (s.first_t_s, s.last_t_s) == (2.0, 4.5)
    assert not math.isnan(s.duration_s)
